"""The last guarantee: a map that leaves ``cmtool sample`` runs no lane against a one-way SD road and leaves no SD
road without a lane, whatever the model drew.

- **One-way roads.** A lane whose length along one-way SD roads runs mostly against them (judged as
  :func:`cmtool.metrics.geometric.legal_oneway` judges a map) is turned round; its successor links are dropped
  and found again by endpoint proximity.
- **Roads without a lane.** The rule layout of the same frame without its junction connectors
  (:mod:`cmtool.data.layouts`, where the input has an SD map) lends every lane of it that lies mostly farther
  than ``COVER_M`` from the map's lanes, with the successor links among them and to the map's lanes at shared
  ends.

The map's meta keeps the model's own scores (``raw``: validity, legal one-way share, SD road covered) beside
the final ones and what was changed (``guarantee``: lanes turned, lanes added), so the repair never hides what the
model did.
"""

from __future__ import annotations

import math

import numpy as np

from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.maps.neighbours import relaned
from cmtool.metrics.geometric import legal_oneway_by_lane
from cmtool.metrics.lanes import resampled, within_distance

COVER_M = 3.0  # a rule lane farther than this from the map's lanes along most of its length is added


def guarantee(graph: LaneGraph, sd: np.ndarray | None, rules: LaneGraph | None = None) -> LaneGraph:
    """``graph`` with lanes against one-way SD roads (on the SD raster ``sd``) turned round and the lanes of the
    rule layout ``rules`` of the same frame added where the map has none (module doc)."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    successors = list(graph.successors)
    turned: list[int] = []
    if sd is not None:
        shares, judged = legal_oneway_by_lane(lanes, sd, frame_m=graph.frame_m)
        turned = [k for k in range(len(lanes)) if judged[k] > 0 and shares[k] < 0.5]
        for k in turned:
            lanes[k] = lanes[k][::-1].copy()
    added = []
    if rules is not None and rules.lanes:
        samples = resampled([np.asarray(l, np.float64) for l in rules.lanes], 1.0)
        owner = np.repeat(np.arange(len(samples)), [len(p) for p in samples])
        far = np.bincount(owner, ~within_distance(np.concatenate(samples), lanes, COVER_M)) / np.bincount(owner)
        added = np.flatnonzero(far > 0.5).tolist()
    if not turned and not added:
        return graph
    first = len(lanes)
    lanes += [np.asarray(rules.lanes[k], np.float64) for k in added]
    index = {k: first + n for n, k in enumerate(added)}
    changed = set(turned) | set(index.values())
    successors = [(i, j) for i, j in successors if i not in changed and j not in changed]
    successors += [(index[i], index[j]) for i, j in (rules.successors if added else []) if i in index and j in index]
    successors += [(i, j) for i, j in infer_successors(lanes) if (i in changed or j in changed)]
    return relaned(graph, lanes, successors, dict(graph.meta) | {"guarantee": {"turned": len(turned),
                                                                             "added": len(added)}})


def raw_scores(graph: LaneGraph) -> dict:
    """The scores :func:`cmtool.sample.run.score_map` recorded, to keep as the model's own."""
    return {k: graph.meta[k] for k in ("validity", "legal_oneway", "sd_coverage")
            if graph.meta.get(k) is not None and math.isfinite(graph.meta[k])}
