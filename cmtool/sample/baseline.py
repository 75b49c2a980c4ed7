"""``cmtool baseline``: the rule-based lane layouts (:mod:`cmtool.data.layouts`) of the same SD inputs that
``cmtool sample`` takes, written as ``sample`` writes its maps, so that they compare file for file."""

from __future__ import annotations

import time
from pathlib import Path

from cmtool.core.jsonio import OutputSet, json_text
from cmtool.sample.files import write_maps
from cmtool.sample.inputs import ControlInput
from cmtool.sample.job import Job, SampledMap
from cmtool.sample.layouts import layout_scenes
from cmtool.sample.scores import score_map


def baseline_maps(inputs: list[ControlInput], method: str, side: str | None = None) -> list[SampledMap]:
    """The ``method`` layout of each input's frame as a scored map (``seconds``: each map's share of the time)."""
    began = time.perf_counter()
    maps = []
    for item, scene in zip(inputs, layout_scenes(inputs, method, side)):
        graph = scene.to_lanegraph()
        graph.city = item.city
        graph.meta = {"source": item.source, "method": method, **({"geo": item.geo} if item.geo else {})}
        score_map(graph, item.sd)
        maps.append(SampledMap(Job(item.name, item, -1, 0), graph, 0.0))
    for m in maps:
        m.seconds = (time.perf_counter() - began) / len(maps)
    return maps


def write_baseline_maps(maps: list[SampledMap], method: str, out: Path, grid: Path | None = None) -> None:
    """Each map's lane graph, ground truth (when known) and picture in ``out``, as ``cmtool sample`` writes them,
    and all maps in one ``METHOD.jsonl`` (with the ground truth in ``truth.jsonl`` when every input has one), for
    ``cmtool metrics``."""
    outputs = OutputSet()
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_maps(out, maps, method, outputs, grid)  # a method name has no braces
        outputs.write_text(out / f"{method}.jsonl", "".join(json_text(m.graph.to_json()) for m in maps))
        if all(m.job.source.truth is not None for m in maps):
            outputs.write_text(out / "truth.jsonl", "".join(json_text(m.job.source.truth.to_json()) for m in maps))
        outputs.commit()
    except BaseException:
        outputs.discard()
        raise
