"""The road graph of an SD map: where roads meet, and which one-way roads are halves of a divided road.

Computed the same way for every SD source (OpenStreetMap, derived from an HD map, drawn by hand), so
frames of real and derived maps can be compared and classified alike.

- **Nodes.** OpenStreetMap ways meet at shared nodes. A point shared by roads (to within 1 cm), a
  road end that stops on another road within ``SNAP_M`` (hand-drawn and derived maps do not share
  points exactly), and a crossing of two roads on the same ``layer`` (not a bridge over the other)
  is a node; a road's end counts one arm there, a road passing through two. A node of three or
  more arms is a junction node; a node where exactly two road ends meet is a join (one road
  continued by another way).
- **Junctions.** Junction nodes closer than ``CLUSTER_M`` are one junction (the two carriageways of
  a divided road cross a street at two nodes). Its arms are counted where the roads cross a circle
  ``ARM_REACH_M`` beyond its outermost node, directions within ``ARM_MERGE_DEG`` counting once, and
  within twice that when one carriageway leads in and the other out (a divided road is one arm).
  Kinds: ``X`` (4 arms), ``multi`` (5 or more), ``T`` (3 arms, two of them within ``STRAIGHT_DEG``
  of straight through), ``Y`` (3 arms otherwise), ``fork`` (under 3 arms reach the circle: a
  carriageway split or a short stub).
- **Divided roads.** A one-way road is half of a divided road when, along at least half its
  length, a one-way road runs the other way beside it within ``DIVIDED_GAP_M``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from cmtool.core.unionfind import UnionFind
from cmtool.maps.sdmap import SDMap

SNAP_M = 5.0
CLUSTER_M = 15.0
ARM_REACH_M = 15.0
ARM_MERGE_DEG = 30.0
STRAIGHT_DEG = 35.0
DIVIDED_GAP_M = 30.0
_SAMPLE_M = 4.0  # spacing of the samples that test whether a one-way road has an opposite partner


@dataclass
class Junction:
    centre: np.ndarray  # (2,)
    arms: int
    kind: str  # T, Y, X, multi, fork


@dataclass
class RoadGraph:
    """Junctions and node-level facts of an SD map (road indices refer to ``sd.roads``)."""

    lines: np.ndarray  # shapely LineString per road
    junctions: list[Junction]
    passes: np.ndarray  # (K, 2) points where a road runs on through a junction node (splits it in two)
    joins: np.ndarray  # (M, 2) points where exactly two road ends meet (one road, two ways)
    dead_ends: np.ndarray  # (D, 2) road ends that meet nothing
    divided: np.ndarray  # (R,) bool: one-way half of a divided road

    @property
    def centres(self) -> np.ndarray:
        return np.array([j.centre for j in self.junctions]).reshape(-1, 2)


def road_graph(sd: SDMap) -> RoadGraph:
    """The road graph of ``sd`` (see the module doc)."""
    polylines = [np.asarray(r.polyline, np.float64) for r in sd.roads]
    lines = np.array([shapely.LineString(p) for p in polylines], dtype=object)
    nodes = _nodes(polylines, lines)
    nodes += _crossings(sd, lines, np.array([xy for xy, _, _ in nodes]).reshape(-1, 2))
    junction_nodes = [(xy, arms) for xy, arms, _ in nodes if arms >= 3]
    passes = [xy for xy, arms, through in nodes if arms >= 3 for _ in range(through)]
    joins = [xy for xy, arms, through in nodes if arms == 2 and through == 0]
    ends = {tuple(np.round(xy, 2)) for xy, _, _ in nodes}
    dead = [p[k] for p in polylines for k in (0, -1) if tuple(np.round(p[k], 2)) not in ends]
    return RoadGraph(lines, _junctions(junction_nodes, sd, lines), np.array(passes).reshape(-1, 2),
                     np.array(joins).reshape(-1, 2), np.array(dead).reshape(-1, 2), _divided(sd, lines))


def _nodes(polylines: list[np.ndarray], lines: np.ndarray) -> list[tuple[np.ndarray, int, int]]:
    """Every node: (position, arms, roads passing through it)."""
    if not polylines:
        return []
    pts = np.concatenate(polylines)
    road = np.repeat(np.arange(len(polylines)), [len(p) for p in polylines])
    last = np.concatenate([[False] * (len(p) - 1) + [True] for p in polylines])
    first = np.concatenate([[True] + [False] * (len(p) - 1) for p in polylines])
    is_end = first | last
    keys = np.round(pts * 100.0).astype(np.int64)
    _, group, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    nodes, snapped_ends = [], []
    for members in np.split(np.argsort(group, kind="stable"), np.cumsum(counts)[:-1]):
        if len(members) < 2:
            continue
        if len(members) == 2 and road[members[0]] == road[members[1]] and not is_end[members].all():
            continue  # a road touching itself mid-way is no node
        arms = int(np.sum(np.where(is_end[members], 1, 2)))
        nodes.append((pts[members[0]], arms, int(np.sum(~is_end[members]))))
    lone = np.flatnonzero(is_end & (counts[group] == 1))
    if len(lone):  # road ends that stop on another road without a shared point
        tree = shapely.STRtree(lines)
        points = shapely.points(pts[lone])
        hit_pt, hit_road = tree.query(points, predicate="dwithin", distance=SNAP_M)
        for k in np.unique(hit_pt):
            own = road[lone[k]]
            others = [int(r) for r in hit_road[hit_pt == k] if r != own]
            if not others:
                continue
            arms, through = 1, 0
            for r in others:
                at = shapely.line_locate_point(lines[r], points[k])
                interior = SNAP_M < at < shapely.length(lines[r]) - SNAP_M
                arms += 2 if interior else 1
                through += int(interior)
            snapped_ends.append((pts[lone[k]], arms, through))
    return nodes + snapped_ends


def _crossings(sd: SDMap, lines: np.ndarray, known: np.ndarray) -> list[tuple[np.ndarray, int, int]]:
    """Roads of one layer crossing mid-way where no node is yet (4 arms, 2 passing through)."""
    if len(lines) < 2:
        return []
    a, b = shapely.STRtree(lines).query(lines, predicate="crosses")
    keep = (a < b) & np.array([sd.roads[i].layer == sd.roads[j].layer for i, j in zip(a, b)], dtype=bool)
    if not keep.any():
        return []
    points = shapely.get_coordinates(shapely.intersection(lines[a[keep]], lines[b[keep]]))
    ends = np.array([p for r in sd.roads for p in (r.polyline[0], r.polyline[-1])])
    far = np.ones(len(points), dtype=bool)
    for ref, tol in ((known, 0.5), (ends, SNAP_M)):
        if len(ref):
            far &= shapely.STRtree(shapely.points(ref)).query_nearest(
                shapely.points(points), return_distance=True, all_matches=False)[1] > tol
    return [(p, 4, 2) for p in np.unique(np.round(points[far], 2), axis=0)]


def _junctions(nodes: list[tuple[np.ndarray, int]], sd: SDMap, lines: np.ndarray) -> list[Junction]:
    """Junction nodes clustered within CLUSTER_M, with their arms counted on a circle."""
    if not nodes:
        return []
    xy = np.array([p for p, _ in nodes])
    uf = UnionFind(range(len(nodes)))
    a, b = shapely.STRtree(shapely.points(xy)).query(shapely.points(xy), predicate="dwithin", distance=CLUSTER_M)
    for i, j in zip(a, b):
        uf.union(int(i), int(j))
    tree = shapely.STRtree(lines)
    out = []
    for group in uf.groups():
        pts = xy[group]
        centre = pts.mean(axis=0)
        radius = float(np.max(np.linalg.norm(pts - centre, axis=1))) + ARM_REACH_M
        ring = shapely.Point(centre).buffer(radius, quad_segs=16).exterior
        angles, flows = [], []
        for r in tree.query(ring, predicate="intersects"):
            hits = shapely.get_coordinates(shapely.intersection(lines[r], ring))
            angles += list(np.arctan2(hits[:, 1] - centre[1], hits[:, 0] - centre[0]))
            flows += list(_flow(sd.roads[r], lines[r], hits, centre))
        arms = _arms(np.array(angles), np.array(flows))
        out.append(Junction(centre, len(arms), _kind(arms)))
    return out


def _flow(road, line, points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Per point of a road: +1 where its travel leads away from ``centre``, -1 towards it, 0 two-way."""
    if road.oneway == 0 or len(points) == 0:
        return np.zeros(len(points))
    at = shapely.line_locate_point(line, shapely.points(points))
    outward = np.sum(_tangent(line, at) * (points - centre), axis=1) > 0
    return np.where(outward, 1.0, -1.0) * road.oneway


def _arms(angles: np.ndarray, flows: np.ndarray) -> np.ndarray:
    """Road directions leaving a junction: crossings within ``ARM_MERGE_DEG`` of each other, or within
    twice that when one leads in and the other out (the two carriageways of a divided road), are one
    arm. Returns the arms' mean directions."""
    if len(angles) == 0:
        return angles
    order = np.argsort(np.mod(angles, 2 * np.pi))
    a, f = np.mod(angles, 2 * np.pi)[order], flows[order]
    gaps = np.diff(np.append(a, a[0] + 2 * np.pi))
    tol = np.radians(ARM_MERGE_DEG)
    joined = (gaps <= tol) | ((gaps <= 2 * tol) & (f * np.roll(f, -1) < 0))  # gap k joins crossing k and k + 1
    if joined.all():
        return a[:1]
    start = int(np.argmin(joined)) + 1  # begin after a gap that separates arms
    a, joined = np.roll(a, -start), np.roll(joined, -start)
    a[a < a[0]] += 2 * np.pi
    return np.array([np.mean(part) for part in np.split(a, np.flatnonzero(~joined[:-1]) + 1)])


def _kind(arms: np.ndarray) -> str:
    n = len(arms)
    if n >= 5:
        return "multi"
    if n == 4:
        return "X"
    if n < 3:
        return "fork"
    diff = np.abs((arms[:, None] - arms[None, :] + np.pi) % (2 * np.pi) - np.pi)
    return "T" if np.any(diff >= np.radians(180.0 - STRAIGHT_DEG)) else "Y"


def _divided(sd: SDMap, lines: np.ndarray) -> np.ndarray:
    """Per road: one-way with an opposite one-way road beside it along half its length or more."""
    out = np.zeros(len(sd.roads), dtype=bool)
    oneway = np.flatnonzero([r.oneway != 0 for r in sd.roads])
    if len(oneway) < 2:
        return out
    travel = np.array([shapely.LineString(sd.roads[k].travel_polyline()) for k in oneway], dtype=object)
    tree = shapely.STRtree(travel)
    for i, line in enumerate(travel):
        length = shapely.length(line)
        at = np.linspace(0.0, length, max(2, int(length / _SAMPLE_M) + 1))
        pts = shapely.line_interpolate_point(line, at)
        own = _tangent(line, at)
        beside = np.zeros(len(at), dtype=bool)
        for j in tree.query(line, predicate="dwithin", distance=DIVIDED_GAP_M):
            if j == i:
                continue
            other = travel[j]
            near = shapely.distance(pts, other) <= DIVIDED_GAP_M
            theirs = _tangent(other, shapely.line_locate_point(other, pts))
            beside |= near & (np.sum(own * theirs, axis=1) < -np.cos(np.radians(STRAIGHT_DEG)))
        out[oneway[i]] = beside.mean() >= 0.5
    return out


def _tangent(line, at: np.ndarray) -> np.ndarray:
    """Unit tangent of ``line`` at arc lengths ``at`` (over +-2 m)."""
    p0 = shapely.get_coordinates(shapely.line_interpolate_point(line, np.maximum(at - 2.0, 0.0)))
    p1 = shapely.get_coordinates(shapely.line_interpolate_point(line, at + 2.0))
    d = p1 - p0
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
