"""The last guarantee: a map that leaves ``cmtool sample`` says what its SD map says, whatever the model drew.

- **Where the input has an SD map** (a picture's roads are traced), the map is composed from it
  (:mod:`cmtool.sample.compose`): every road of the frame carries its lanes, whole, one-way roads one way; lanes
  where the SD map has no road are not written; junctions are joined from the laid lanes. The model decides what the
  SD map leaves open: which movements a junction has and, with ``counts="model"``, how many lanes an untagged road
  carries.
- **Without one** (an SD raster whose roads could not be traced), a lane whose length along one-way SD roads runs
  mostly against them (judged as :func:`cmtool.metrics.geometric.legal_oneway` judges a map) is turned round; its
  successor links are dropped and found again by endpoint proximity.

The map's meta keeps the model's own scores (``raw``: validity, legal one-way share, SD road covered) beside the
final ones, and what was made of the model's map (``composed``, or ``guarantee``: lanes turned), so the guarantee
never hides what the model did.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.maps.neighbours import relaned
from cmtool.maps.sdmap import Road
from cmtool.metrics.geometric import legal_oneway_by_lane
from cmtool.sample import DEFAULT_COUNTS
from cmtool.sample.compose import compose


def guarantee(graph: LaneGraph, sd: np.ndarray | None, roads: list[Road] | None = None, side: str = "right",
              counts: str = DEFAULT_COUNTS) -> LaneGraph:
    """``graph`` composed from the frame's SD ``roads`` (:func:`cmtool.sample.roads.frame_roads`; ``side``: the
    driving side; ``counts``: :func:`cmtool.sample.compose.compose`'s) or, without roads, with its lanes against the
    one-way roads of the SD raster ``sd`` turned round (module doc). Its lane neighbours are found by the caller."""
    if roads is not None:
        return compose(graph, roads, side, counts)
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    turned = []
    if sd is not None:
        shares, judged = legal_oneway_by_lane(lanes, sd, frame_m=graph.frame_m)
        turned = [k for k in range(len(lanes)) if judged[k] > 0 and shares[k] < 0.5]
    meta = dict(graph.meta) | {"guarantee": {"turned": len(turned)}}
    if not turned:
        return replace(graph, meta=meta)
    for k in turned:
        lanes[k] = lanes[k][::-1].copy()
    successors = [(i, j) for i, j in graph.successors if i not in turned and j not in turned]
    successors += [(i, j) for i, j in infer_successors(lanes) if i in turned or j in turned]
    return relaned(graph, lanes, successors, meta, found=False)


def raw_scores(graph: LaneGraph) -> dict:
    """The scores :func:`cmtool.sample.scores.score_map` recorded, to keep as the model's own."""
    return {k: graph.meta[k] for k in ("validity", "legal_oneway", "sd_coverage")
            if graph.meta.get(k) is not None and math.isfinite(graph.meta[k])}
