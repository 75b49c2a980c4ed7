"""The last guarantee: a map that leaves ``cmtool sample`` runs no lane against a one-way SD road, lays its lanes on
the SD roads they follow and leaves no SD road without a lane, whatever the model drew.

- **One-way roads.** A lane whose length along one-way SD roads runs mostly against them (judged as
  :func:`cmtool.metrics.geometric.legal_oneway` judges a map) is turned round; its successor links are dropped
  and found again by endpoint proximity.
- **Geometry from the SD map.** Where the input has an SD map (a picture's roads are traced), the lanes along its
  roads take their shape from the roads (:mod:`cmtool.sample.anchor`); the model keeps the decisions the SD map
  leaves open. A lane that laying gave a validity problem it did not have keeps the model's points (and so do the
  lanes joined to it where laying moved their shared end); a lane that laying made run mostly against a one-way
  road is turned round.
- **Roads without a lane.** The rule layout of the same frame without its junction connectors
  (:mod:`cmtool.data.layouts`, where the input has an SD map) lends every lane of it that lies mostly farther
  than ``COVER_M`` from the map's lanes, with the successor links among them. A lent lane joins the map's lanes:
  an end within ``LEND_JOIN_M`` of a map lane's end (or start) that heads on is moved there and linked. A lent
  lane that would still be joined to nothing inside the frame, or that would cross a joined map lane, is not
  lent; map lanes joined to nothing that a lent lane crosses give way to it (the model's broken pieces).

The map's meta keeps the model's own scores (``raw``: validity, legal one-way share, SD road covered) beside
the final ones and what was changed (``guarantee``: lanes turned, added and replaced; ``anchored``: lanes and metres
laid, ``undone``: lanes put back as drawn), so the repair never hides what the model did.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import shapely

from cmtool.core.geometry import moved_start, unit
from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.maps.neighbours import relaned
from cmtool.maps.sdmap import Road
from cmtool.metrics.geometric import legal_oneway_by_lane
from cmtool.metrics.lanes import resampled, within_distance
from cmtool.metrics.validity import BORDER_M, Validity, check
from cmtool.sample.anchor import anchor

COVER_M = 3.0  # a rule lane farther than this from the map's lanes along most of its length is added
LEND_JOIN_M = 4.0  # a lent lane's end this close to a map lane's end, heading on, is joined to it
LEND_TURN_DEG = 60.0


def guarantee(graph: LaneGraph, sd: np.ndarray | None, rules: LaneGraph | None = None,
              roads: list[Road] | None = None, side: str = "right", checked: Validity | None = None) -> LaneGraph:
    """``graph`` with lanes against one-way SD roads (on the SD raster ``sd``) turned round, its lanes laid on the
    frame's SD ``roads`` (:func:`cmtool.sample.anchor.frame_roads`; None: not laid; ``side``: the driving side) and
    the lanes of the rule layout ``rules`` of the same frame lent where the map has none (module doc); ``checked``:
    ``graph``'s validity report, when the caller has it."""
    drawn = graph  # the steps' graphs have their neighbours found once, at the end
    graph, turned = _turned(graph, sd)
    if roads is not None:
        graph = _no_worse(graph, anchor(graph, roads, side), None if turned else checked)
        graph, again = _turned(graph, sd)  # a lane that laying made run mostly against a one-way road
        turned += again
    added, replaced = _lent(graph, rules)
    if not turned and not added and roads is None:
        return graph
    meta = dict(graph.meta) | {"guarantee": {"turned": turned, "added": len(added), "replaced": len(replaced)}}
    if not added:
        return replace(graph, meta=meta) if graph is drawn else relaned(graph, graph.lanes, graph.successors, meta)
    first = len(graph.lanes)
    index = {k: first + n for n, (_, _, k) in enumerate(added)}
    successors = list(graph.successors) + [(i, j) for i, j in rules.successors if i in index and j in index]
    successors += [(index[k] if a < 0 else a, index[k] if b < 0 else b) for _, links, k in added for a, b in links]
    lanes = list(graph.lanes) + [line for line, _, _ in added]
    kept = [k for k in range(len(lanes)) if k not in replaced]  # replaced lanes have no links
    renumber = {k: n for n, k in enumerate(kept)}
    return relaned(graph, [lanes[k] for k in kept],
                   [(renumber[i], renumber[j]) for i, j in successors if i in renumber and j in renumber], meta)


def _turned(graph: LaneGraph, sd: np.ndarray | None) -> tuple[LaneGraph, int]:
    """``graph`` with each lane that runs mostly against the one-way SD roads of the raster ``sd`` turned round (its
    successor links found anew by endpoint proximity), and how many were."""
    if sd is None:
        return graph, 0
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    shares, judged = legal_oneway_by_lane(lanes, sd, frame_m=graph.frame_m)
    turned = [k for k in range(len(lanes)) if judged[k] > 0 and shares[k] < 0.5]
    if not turned:
        return graph, 0
    for k in turned:
        lanes[k] = lanes[k][::-1].copy()
    successors = [(i, j) for i, j in graph.successors if i not in turned and j not in turned]
    successors += [(i, j) for i, j in infer_successors(lanes) if i in turned or j in turned]
    return relaned(graph, lanes, successors, dict(graph.meta), found=False), len(turned)


def _no_worse(graph: LaneGraph, laid: LaneGraph, checked: Validity | None = None) -> LaneGraph:
    """``laid`` (``graph``'s lanes laid on the SD roads, one for one) with every lane that laying gave a problem
    (:func:`cmtool.metrics.validity.check`; ``checked``: ``graph``'s report, when known) the model's lane did not
    have put back as the model drew it."""
    before = {k for p in (checked or check(graph, routes=False)).problems for k in p.lanes}
    worse = {k for p in check(laid, routes=False).problems for k in p.lanes} - before
    if not worse:
        return laid
    while True:  # and the lanes joined to those whose shared end laying moved, so that each join stays whole
        more = {b for i, j in graph.successors for a, b, end in ((i, j, 0), (j, i, -1)) if a in worse and b not in worse
                and not np.allclose(laid.lanes[b][end], graph.lanes[b][end])}
        if not more:
            break
        worse |= more
    lanes = [graph.lanes[k] if k in worse else lane for k, lane in enumerate(laid.lanes)]
    successors = [(i, j) for i, j in laid.successors if i not in worse and j not in worse]
    successors += [(i, j) for i, j in graph.successors if i in worse or j in worse]
    return relaned(laid, lanes, successors, dict(laid.meta, anchored=dict(laid.meta["anchored"], undone=len(worse))),
                   found=False)


def _lent(graph: LaneGraph, rules: LaneGraph | None) -> tuple[list[tuple[np.ndarray, list, int]], set[int]]:
    """The rule lanes to lend (module doc), each as (its line, its links with the map's lanes (-1 standing for
    itself), its index in ``rules``), and the map's lanes joined to nothing that they cross, which they replace."""
    if rules is None or not rules.lanes:
        return [], set()
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    samples = resampled([np.asarray(l, np.float64) for l in rules.lanes], 1.0)
    owner = np.repeat(np.arange(len(samples)), [len(p) for p in samples])
    far = np.bincount(owner, ~within_distance(np.concatenate(samples), lanes, COVER_M)) / np.bincount(owner)
    candidates = np.flatnonzero(far > 0.5).tolist()
    if not candidates:
        return [], set()
    ends = np.array([l[-1] for l in lanes]).reshape(-1, 2)
    starts = np.array([l[0] for l in lanes]).reshape(-1, 2)
    end_dir = unit(np.array([l[-1] - l[-2] for l in lanes]).reshape(-1, 2))
    start_dir = unit(np.array([l[1] - l[0] for l in lanes]).reshape(-1, 2))
    tree = shapely.STRtree([shapely.LineString(l) for l in lanes]) if lanes else None
    half = graph.frame_m / 2.0 - BORDER_M
    cos = math.cos(math.radians(LEND_TURN_DEG))
    joined = []
    for k in candidates:
        line, links = np.asarray(rules.lanes[k], np.float64), []
        if len(lanes):
            d = np.linalg.norm(ends - line[0], axis=1)
            ok = (d <= LEND_JOIN_M) & (end_dir @ unit(line[1] - line[0]) >= cos)
            if ok.any():
                i = int(np.argmin(np.where(ok, d, np.inf)))
                line, links = moved_start(line, ends[i], LEND_JOIN_M * 2), [(i, -1)]
            d = np.linalg.norm(starts - line[-1], axis=1)
            ok = (d <= LEND_JOIN_M) & (start_dir @ unit(line[-1] - line[-2]) >= cos)
            if ok.any():
                j = int(np.argmin(np.where(ok, d, np.inf)))
                line = moved_start(line[::-1], starts[j], LEND_JOIN_M * 2)[::-1]
                links.append((-1, j))
        joined.append((line, links, k))
    lent = set(candidates)
    among = {k for i, j in rules.successors if i in lent and j in lent for k in (i, j)}
    linked = {m for edge in graph.successors for m in edge} | {m for _, links, _ in joined for edge in links
                                                               for m in edge if m >= 0}
    out, stray = [], set()  # stray: the map's lanes joined to nothing that a lent lane crosses: it replaces them
    for line, links, k in joined:
        crossed = [int(c) for c in tree.query(shapely.LineString(line), predicate="crosses")] if tree else []
        if any(c in linked for c in crossed):
            continue  # it would cross the map's joined lanes
        if not links and k not in among and not np.any(np.abs(line[[0, -1]]) >= half):
            continue  # joined to nothing inside the frame
        stray.update(crossed)
        out.append((line, links, k))
    return out, stray


def raw_scores(graph: LaneGraph) -> dict:
    """The scores :func:`cmtool.sample.scores.score_map` recorded, to keep as the model's own."""
    return {k: graph.meta[k] for k in ("validity", "legal_oneway", "sd_coverage")
            if graph.meta.get(k) is not None and math.isfinite(graph.meta[k])}
