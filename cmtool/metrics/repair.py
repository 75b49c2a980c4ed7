"""Opt-in repair of a lane graph (``cmtool validate --repair``), each change reported.

In this order: lanes shorter than 2 m are dropped; duplicate lanes (the same direction, within
0.5 m of each other on average, lengths within 20%) are merged into the first of them, which takes
over their successor edges; near-miss joints are snapped: lane ends and starts within 1.5 m of each other
(a successor edge, or headings within 60 degrees) move to their common mean, transitively (forks
and merges meet at one point), and the successor edge is added if it was missing.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from cmtool.core.geometry import polyline_length, resample
from cmtool.core.unionfind import UnionFind
from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.metrics.validity import MAX_GAP_M, MAX_TURN_DEG, MIN_LENGTH_M

DUPLICATE_M = 0.5


def repair(graph: LaneGraph) -> tuple[LaneGraph, list[str]]:
    """A repaired copy of ``graph`` and the list of changes (lane indices refer to the input)."""
    lanes = [np.array(l, np.float64) for l in graph.lanes]
    lengths = [polyline_length(lane) for lane in lanes]
    keep = [i for i, length in enumerate(lengths) if length >= MIN_LENGTH_M]  # input index of each kept lane
    changes = [f"dropped lane {i} ({length:.2f} m long)" for i, length in enumerate(lengths) if length < MIN_LENGTH_M]
    alias = {i: i for i in range(len(lanes))}  # merged lanes -> the lane that replaces them
    for a, b in duplicate_pairs([lanes[i] for i in keep], keep):
        if alias[a] == a and alias[b] == b:
            alias[b] = a
            changes.append(f"merged lane {b} into lane {a} (duplicate)")
    keep = [i for i in keep if alias[i] == i]
    index = {old: new for new, old in enumerate(keep)}
    edges = {(alias[i], alias[j]) for i, j in graph.successors if alias[i] in index and alias[j] in index and
             alias[i] != alias[j]}
    kept = [lanes[i] for i in keep]
    old_edges = {(index[i], index[j]) for i, j in edges}
    joints = UnionFind(range(2 * len(kept)))  # 2i: start of kept lane i, 2i + 1: its end
    near = set()
    for a, b in old_edges | set(infer_successors(kept, MAX_GAP_M, MAX_TURN_DEG)):
        if np.linalg.norm(kept[a][-1] - kept[b][0]) <= MAX_GAP_M:
            joints.union(2 * a + 1, 2 * b)
            near.add((a, b))
    for members in joints.groups():
        points = [(kept[k // 2], 0 if k % 2 == 0 else -1) for k in members]
        mean = np.mean([line[e] for line, e in points], axis=0)
        moved = max(float(np.linalg.norm(line[e] - mean)) for line, e in points)
        if moved > 1e-3:
            for line, e in points:
                line[e] = mean
            names = ", ".join(f"lane {keep[k // 2]} {'start' if k % 2 == 0 else 'end'}" for k in members)
            changes.append(f"snapped {names} to ({mean[0]:.2f}, {mean[1]:.2f}) (moved up to {moved:.2f} m)")
    for a, b in sorted(near - old_edges):
        changes.append(f"linked lane {keep[a]} to lane {keep[b]} as its successor")
    new_edges = old_edges | near

    def pairs(found, order=lambda p: p):  # neighbour pairs in the kept lanes' numbering
        return None if found is None else sorted({order((index[alias[i]], index[alias[j]])) for i, j in found
                                                  if alias[i] in index and alias[j] in index and alias[i] != alias[j]})

    widths = None if graph.widths is None else [graph.widths[i] for i in keep]
    return replace(graph, lanes=kept, successors=sorted(new_edges), left_neighbors=pairs(graph.left_neighbors),
                   oncoming=pairs(graph.oncoming, order=lambda p: tuple(sorted(p))), widths=widths), changes


def duplicate_pairs(lines: list[np.ndarray], ids: list[int]) -> list[tuple[int, int]]:
    """Pairs ``(ids[p], ids[q])``, p < q, in order, of lines that duplicate each other: lengths within 20%, and
    within ``DUPLICATE_M`` on average over 20 points resampled along each. Only lines whose mean points lie that
    close are compared (the distance of the means is at most the mean distance), found with a KD-tree."""
    if len(lines) < 2:
        return []
    points = np.stack([resample(line, 20) for line in lines])
    lengths = np.array([polyline_length(line) for line in lines])
    out = []
    for p, q in sorted(cKDTree(points.mean(axis=1)).query_pairs(DUPLICATE_M)):
        la, lb = lengths[p], lengths[q]
        if min(la, lb) <= 0 or abs(la - lb) > 0.2 * max(la, lb):
            continue
        if float(np.linalg.norm(points[p] - points[q], axis=1).mean()) < DUPLICATE_M:
            out.append((ids[p], ids[q]))
    return out
