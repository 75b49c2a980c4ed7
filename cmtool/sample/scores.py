"""The scores of a sampled map, in its meta: validity, SD road covered and the legal one-way share; and the choice
of the best of the candidates drawn for one map."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from cmtool.maps.lanegraph import LaneGraph
from cmtool.metrics.geometric import legal_oneway, sd_adherence
from cmtool.metrics.validity import Validity, check

if TYPE_CHECKING:
    from cmtool.sample.job import SampledMap

SCORES = {"validity": "validity", "sd_coverage": "SD covered", "legal_oneway": "one-way ok"}  # meta key: column
SCORES_NOTE = ("validity: share of lanes free of problems (cmtool validate); SD covered: share of the SD road with a "
               "lane within 3 m; one-way ok: share of the lane length on one-way SD roads that runs the legal way; "
               "-: nothing to judge")


def score_map(graph: LaneGraph, sd: np.ndarray | None) -> Validity:
    """Record in the map's meta its validity score and, against an SD raster ``sd``, the share of its lane length
    along one-way SD roads that runs the legal way and the share of the SD road with a lane within 3 m; returns the
    validity report (without routability)."""
    report = check(graph, routes=False)
    graph.meta["validity"] = round(report.score, 6)
    if sd is not None:
        share, judged = legal_oneway(graph.lanes, sd)
        graph.meta["legal_oneway"] = None if math.isnan(share) else round(share, 6)
        graph.meta["oneway_judged_m"] = round(judged, 1)
        covered = sd_adherence(graph.lanes, sd)["sd_coverage"]
        graph.meta["sd_coverage"] = None if math.isnan(covered) else round(covered, 6)
    return report


def choose(maps: list[SampledMap], candidates: int) -> list[SampledMap]:
    """Of each run of ``candidates`` maps drawn for one map (consecutive, as :func:`cmtool.sample.run.plan` orders
    them), the one with the best mean of its validity score, SD road covered and legal one-way share (those it has;
    the first of equals), its meta recording every candidate's mean under ``candidates``; the time is the run's."""
    if candidates == 1:
        return maps
    chosen = []
    for start in range(0, len(maps), candidates):
        run = maps[start:start + candidates]
        scores = [round(float(np.mean([v for v in (m.graph.meta["validity"], m.graph.meta.get("sd_coverage"),
                                                    m.graph.meta.get("legal_oneway")) if v is not None])), 6)
                  for m in run]
        best = run[int(np.argmax(scores))]
        best.graph.meta["candidates"] = {"chosen": best.job.candidate, "scores": scores}
        best.seconds = sum(m.seconds for m in run)
        chosen.append(best)
    return chosen
