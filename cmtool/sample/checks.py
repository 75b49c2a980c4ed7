"""The checks of sampled maps: each map, as its file will hold it, scored in its meta and, unless off, replaced by
its guaranteed form."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cmtool.maps.hdmap import drives_on
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.neighbours import with_neighbours
from cmtool.sample.guarantee import guarantee, raw_scores
from cmtool.sample.roads import frame_roads
from cmtool.sample.scores import score_map

if TYPE_CHECKING:
    from cmtool.sample.job import Job, SampleSettings


def check_maps(batch: list[Job], graphs: list[LaneGraph], settings: SampleSettings) -> None:
    """Score each map in its meta (:func:`~cmtool.sample.scores.score_map`, on its coordinates as written) and, unless
    ``settings.guarantee`` is off, replace it in ``graphs`` by its guaranteed form
    (:func:`cmtool.sample.guarantee.guarantee`), the model's own scores kept; each map's lane neighbours found where it
    records none."""
    for k, (job, graph) in enumerate(zip(batch, graphs)):
        graph = graph.as_written()
        score_map(graph, job.source.sd)
        if settings.guarantee and job.source.sd is not None:
            raw = raw_scores(graph)
            src = job.source
            roads = frame_roads(src.sd_map, src.pose, graph.frame_m) if src.sd_map is not None else None
            graph = guarantee(graph, src.sd, roads, drives_on(graph.city), settings.lane_counts).as_written()
            score_map(graph, job.source.sd)
            graph.meta["raw"] = raw
        graphs[k] = with_neighbours(graph)


def guaranteed(item) -> LaneGraph:
    """A dataset scene's map as ``cmtool sample`` writes it (:func:`cmtool.sample.guarantee.guarantee`): ``item`` is
    (the map, its scene, the scene's SD map, how lane counts are decided)."""
    graph, scene, sd_map, counts = item
    return guarantee(graph, scene.sd, frame_roads(sd_map, scene.pose.as_array(), scene.frame_m),
                     drives_on(scene.city), counts).as_written()
