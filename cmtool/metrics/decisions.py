"""What a lane map decides where the SD map leaves it open, measured against the ground truth of the same frame, on the
frame's SD roads (:func:`cmtool.sample.roads.frame_roads`).

A lane, sampled every ``STEP_M``, is matched point by point to the nearest SD road segment that runs along it (within
``ALIGN_DEG`` and within ``MAX_LANES`` + 1 lane widths of the road's line); a stretch of at least ``MIN_RUN_M`` on one
road, one way, is a run (:func:`lane_runs`; :func:`cmtool.sample.roads.drawn_lane_counts` counts a road direction's
lanes from them). Three decisions are measured:

- **lanes per road direction**: :func:`cmtool.sample.roads.drawn_lane_counts` of a map against the truth's;
- **movements**: the frame's roads are split where they meet and grouped into junctions as the rules do
  (:func:`cmtool.data.rules.road_junctions`); a map makes the movement (arm A one way, arm B one way) of a junction
  where a lane runs along A into the junction and then, itself or through a chain of up to ``LINKS`` successor links
  over lanes that follow no road (junction connectors), along B out of it (A and B different edges: no U-turns).
  The movements of a map against the truth's, true and false positives and misses pooled over the frames, give a
  precision, a recall and an F1 (a score over nothing is 1);
- **unexplained lane length**: the share of a map's lane length in lanes lying mostly farther than a road's reach
  (:func:`road_reach`) from every SD road (:func:`unexplained`), pooled over the frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from cmtool.core.geometry import polyline_length, unit
from cmtool.data.rules import lane_counts, lane_width, road_junctions
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.lanes import distance_to_polylines, resampled

STEP_M = 1.0  # lanes are matched to roads at points this far apart
ALIGN_DEG = 25.0  # a lane point follows a road whose direction is within this of the lane's
MIN_RUN_M = 6.0  # shorter stretches along a road are not counted
MAX_LANES = 4  # lanes per direction at most: lanes this many lane widths out (and one more) are matched
GAP_POINTS = 3  # a lane's points matched elsewhere (or nowhere) between two stretches on one road join them
LINKS = 3  # successor links from a lane on one arm, over lanes on no road, to a lane on another

Run = tuple[int, int, int, int, float]  # road index, +1 along its polyline / -1 against it, first and last point, lateral
Movement = tuple[tuple[int, int], tuple[int, int]]  # (edge, direction) in, (edge, direction) out


def road_reach(road: Road) -> float:
    """How far from a road's line a lane of it may lie: one lane beyond the lanes a direction the SD map allows, its
    ``lanes`` tag's count or, untagged, up to ``MAX_LANES`` (the count is left open, as a map may decide it)."""
    allowed = max(lane_counts(road)) if road.lanes is not None else MAX_LANES
    return (allowed + 1) * lane_width(road)


def lane_runs(samples: list[np.ndarray], roads: list[Road]) -> list[list[Run]]:
    """Each lane's (``samples``: its points every ``STEP_M``) stretches along one of ``roads`` (module doc), in its
    order: (road index, +1 along its polyline / -1 against it, first point, last point, median lateral position left
    of the road's line); stretches against a one-way road are left out."""
    if not roads:
        return [[] for _ in samples]
    a = np.concatenate([r.polyline[:-1] for r in roads])
    b = np.concatenate([r.polyline[1:] for r in roads])
    piece = np.repeat(np.arange(len(roads)), [len(r.polyline) - 1 for r in roads])
    seg = b - a
    seg_len = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    seg_dir = seg / seg_len[:, None]
    reach = np.array([(MAX_LANES + 1) * lane_width(r) for r in roads])[piece]
    cos = math.cos(math.radians(ALIGN_DEG))
    out = []
    for pts in samples:
        runs: list[Run] = []
        out.append(runs)
        if len(pts) < 2:
            continue
        tangent = unit(np.gradient(pts, axis=0))
        rel = pts[:, None, :] - a[None]  # (P, S, 2)
        t = np.clip(np.einsum("psk,sk->ps", rel, seg_dir), 0.0, seg_len[None])
        dist = np.linalg.norm(rel - t[..., None] * seg_dir[None], axis=2)
        along = tangent @ seg_dir.T  # (P, S) cosine of the angle between the lane and the segment
        dist = np.where((np.abs(along) >= cos) & (dist <= reach[None]), dist, np.inf)
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(pts))
        key = _filled(np.where(np.isfinite(dist[rows, best]), piece[best] * 2 + (along[rows, best] < 0), -1))
        d, r = seg_dir[best], rel[rows, best]
        lateral = d[:, 0] * r[:, 1] - d[:, 1] * r[:, 0]  # left of the road
        for first, last in _stretches(key):
            if key[first] < 0 or (last - first) * STEP_M < MIN_RUN_M:
                continue
            p, sign = int(key[first] // 2), -1 if key[first] % 2 else 1
            if roads[p].oneway and sign != (1 if roads[p].oneway == 1 else -1):
                continue
            runs.append((p, sign, int(first), int(last), float(np.median(lateral[first:last + 1]))))
    return out


def _filled(key: np.ndarray) -> np.ndarray:
    """``key`` with stretches of at most ``GAP_POINTS`` between two stretches of one key given that key."""
    key = key.copy()
    spans = _stretches(key)
    for (a0, a1), (b0, b1), (c0, c1) in zip(spans, spans[1:], spans[2:]):
        if key[a0] >= 0 and key[a0] == key[c0] and b1 - b0 + 1 <= GAP_POINTS:
            key[b0:b1 + 1] = key[a0]
    return key


def _stretches(key: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each stretch of equal keys."""
    cuts = np.flatnonzero(np.diff(key)) + 1
    starts = np.r_[0, cuts]
    return list(zip(starts, np.r_[cuts - 1, len(key) - 1]))


def unexplained(graph: LaneGraph, roads: list[Road]) -> list[int]:
    """The lanes of ``graph`` that lie mostly farther than a road's reach (:func:`road_reach`) from every SD road."""
    if not graph.lanes or not roads:
        return list(range(len(graph.lanes)))
    samples = resampled([np.asarray(l, np.float64) for l in graph.lanes], 1.0)
    near = np.zeros(sum(len(s) for s in samples), bool)
    points = np.concatenate(samples)
    for road in roads:
        near |= distance_to_polylines(points, [road.polyline]) <= road_reach(road)
    owner = np.repeat(np.arange(len(samples)), [len(s) for s in samples])
    return np.flatnonzero(np.bincount(owner, ~near) / np.bincount(owner) > 0.5).tolist()


def unexplained_length(graph: LaneGraph, roads: list[Road]) -> tuple[float, float]:
    """The length (m) of the :func:`unexplained` lanes of ``graph`` and of all its lanes."""
    lengths = [polyline_length(np.asarray(l, np.float64)) for l in graph.lanes]
    return float(sum(lengths[k] for k in unexplained(graph, roads))), float(sum(lengths))


@dataclass
class Junctions:
    """A frame's roads split where they meet (:func:`cmtool.data.rules.road_junctions`), each a :class:`Road` in its
    travel direction (``oneway`` 1 or 0), and the junction each (edge, direction) arrives at or leaves from."""

    edges: list[Road]
    arrives: dict[tuple[int, int], int]
    leaves: dict[tuple[int, int], int]


def frame_junctions(roads: list[Road]) -> Junctions:
    """The :class:`Junctions` of a frame's ``roads``; an edge with both ends in one junction is part of it, no arm."""
    found, junction = road_junctions(SDMap(roads=roads))
    edges, arrives, leaves = [], {}, {}
    for e in found:
        start, end = (junction.get(n) for n in e.nodes)
        if start is not None and start == end:
            continue
        k = len(edges)
        edges.append(Road(e.road.id, e.line, e.road.road_class, e.road.lanes, 1 if e.road.oneway else 0,
                          e.road.link, e.road.layer))
        for sign, into, out in ((1, end, start), (-1, start, end)):
            if sign == -1 and e.road.oneway:
                continue
            if into is not None:
                arrives[(k, sign)] = into
            if out is not None:
                leaves[(k, sign)] = out
    return Junctions(edges, arrives, leaves)


def movements(graph: LaneGraph, frame: Junctions) -> set[Movement]:
    """The junction movements ``graph`` makes over the frame's :class:`Junctions` (module doc)."""
    if not graph.lanes or not frame.edges:
        return set()
    runs = [[(p, sign) for p, sign, *_ in lane] for lane in
            lane_runs(resampled([np.asarray(l, np.float64) for l in graph.lanes], STEP_M), frame.edges)]
    after: dict[int, list[int]] = {}
    for i, j in graph.successors:
        if i != j:
            after.setdefault(i, []).append(j)
    made = set()

    def make(a: tuple[int, int], b: tuple[int, int]) -> None:
        if a[0] != b[0] and a in frame.arrives and frame.arrives[a] == frame.leaves.get(b):
            made.add((a, b))

    for k, keys in enumerate(runs):
        for a, b in pairwise(keys):  # a lane drawn through the junction
            make(a, b)
        if not keys:
            continue
        frontier, seen = after.get(k, []), {k}
        for _ in range(LINKS):
            on = []
            for j in frontier:
                if j in seen:
                    continue
                seen.add(j)
                if runs[j]:
                    make(keys[-1], runs[j][0])
                else:  # a connector: on along its successors
                    on += after.get(j, [])
            frontier = on
    return made


def decision_counts(graph: LaneGraph, truth: set[Movement], frame: Junctions, roads: list[Road]) -> dict:
    """One frame's movements of ``graph`` against the ``truth``'s (true and false positives, misses) and its unexplained
    and whole lane length (m)."""
    made = movements(graph, frame)
    off, total = unexplained_length(graph, roads)
    return {"true": len(made & truth), "false": len(made - truth), "missed": len(truth - made),
            "unexplained_m": off, "lane_m": total}


def pooled(counts: list[dict]) -> dict:
    """:func:`decision_counts` of the frames pooled: movement precision, recall and F1 (a score over no movements is
    1, F1 0 where both scores are), the movements made and the truth's, and the unexplained share of the lane
    length (0 over no lanes)."""
    tp, fp, fn = (sum(c[k] for c in counts) for k in ("true", "false", "missed"))
    precision, recall = tp / (tp + fp) if tp + fp else 1.0, tp / (tp + fn) if tp + fn else 1.0
    off, total = sum(c["unexplained_m"] for c in counts), sum(c["lane_m"] for c in counts)
    return {"movement_precision": precision, "movement_recall": recall,
            "movement_f1": 2 * precision * recall / (precision + recall) if precision + recall else 0.0,
            "movements": tp + fp, "true_movements": tp, "truth_movements": tp + fn,
            "unexplained_share": off / total if total else 0.0, "lane_m": total}


def truth_frames(reference: list[LaneGraph], roads: list[list[Road]]) -> list[tuple[Junctions, set[Movement]]]:
    """Each frame's :class:`Junctions` (on its SD roads ``roads[k]``) and the movements of its ground truth
    ``reference[k]``: what :func:`decision_scores` scores maps against."""
    frames = [frame_junctions(r) for r in roads]
    return [(f, movements(g, f)) for g, f in zip(reference, frames)]


def decision_scores(maps: list[LaneGraph], frames: list[tuple[Junctions, set[Movement]]],
                    roads: list[list[Road]]) -> dict:
    """The pooled decision scores (:func:`pooled`) of ``maps`` (scene k against ``frames[k]``, :func:`truth_frames`,
    on the SD roads ``roads[k]``)."""
    return pooled([decision_counts(g, t, f, r) for g, (f, t), r in zip(maps, frames, roads)])


def decisions(generated: dict[str, list[LaneGraph]], reference: list[LaneGraph], roads: list[list[Road]]) -> dict:
    """:func:`decision_scores` of each set of maps in ``generated`` (scene k of each against ``reference[k]``, on the
    SD roads ``roads[k]``), and of the ground truth itself under ``"truth"``."""
    frames = truth_frames(reference, roads)
    return {m: decision_scores(maps, frames, roads) for m, maps in {**generated, "truth": reference}.items()}
