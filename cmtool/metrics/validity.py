"""Is a lane graph usable by a planner or simulator? Problems, routability and one score.

Problems (each names its lanes and a position, ego-frame metres):

- ``dangling``: a lane with neither predecessor nor successor that does not touch the frame border;
- ``bad_successor``: a successor edge whose end-to-start gap exceeds 1.5 m or whose heading
  changes by more than 60 degrees;
- ``crossing``: two lanes that cross away from any intersection (a crossing counts as inside an
  intersection when one of the lanes starts or ends at a fork or merge of the graph, or the
  crossing lies within 20 m of one);
- ``self_intersection``, ``short`` (under 2 m) and ``kink`` (a turn radius under 4 m: at each
  vertex, the mean length of its segments (the shorter one at a corner of over 45 degrees) over
  the angle it turns, on vertices thinned to at least 2 m apart, corners always kept).

Routability: the share of ordered lane pairs (i, j), i != j, with a path from i to j along
successor edges, the same share when lane changes between same-direction neighbours are allowed
(as a simulator routes; see :mod:`cmtool.maps.neighbours`), and the size of the largest strongly
connected set of lanes (scipy's csgraph for the strongly connected sets, reachable lanes as bitsets
over their condensation). Crops of a city are mostly not routable end to end, so routability is
reported against the ground truth's, not scored.

Score: the share of lanes free of problems (a bad successor edge or a crossing counts against
both its lanes); 1.0 for a map without problems, and for an empty map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from shapely import STRtree
from shapely.geometry import LineString

from cmtool.core.geometry import polyline_length, unit
from cmtool.maps.neighbours import infer_neighbours, same_direction

MAX_GAP_M, MAX_TURN_DEG = 1.5, 60.0
MIN_LENGTH_M, MIN_RADIUS_M = 2.0, 4.0
STEP_M = 0.01  # vertices closer than this to the one before carry no direction for the kink check
BORDER_M = 1.0  # an endpoint this close to the frame edge touches the border
JUNCTION_REACH_M = 20.0


@dataclass
class Problem:
    kind: str
    lanes: list[int]
    at: list[float]  # [x, y] metres
    detail: str = ""

    def to_json(self) -> dict:
        return {"kind": self.kind, "lanes": self.lanes, "at": [round(v, 2) for v in self.at], "detail": self.detail}


@dataclass
class Validity:
    lanes: int
    problems: list[Problem] = field(default_factory=list)
    routable_pairs: float = 1.0
    routable_with_changes: float = 1.0
    largest_scc: int = 0

    @property
    def score(self) -> float:
        if self.lanes == 0:
            return 1.0
        bad = {i for p in self.problems for i in p.lanes}
        return 1.0 - len(bad) / self.lanes

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for p in self.problems:
            out[p.kind] = out.get(p.kind, 0) + 1
        return out

    def to_json(self) -> dict:
        return {"score": round(self.score, 6), "lanes": self.lanes, "counts": self.counts(),
                "routable_pairs": round(self.routable_pairs, 6),
                "routable_with_changes": round(self.routable_with_changes, 6), "largest_scc": self.largest_scc,
                "problems": [p.to_json() for p in self.problems]}


def check(graph) -> Validity:
    """The validity report of one lane graph (``lanes``, ``successors``, ``frame_m``)."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    n = len(lanes)
    report = Validity(n)
    if n == 0:
        return report
    succ = [(int(i), int(j)) for i, j in graph.successors]
    has_pred = np.zeros(n, bool)
    has_succ = np.zeros(n, bool)
    for i, j in succ:
        has_succ[i] = has_pred[j] = True
    half = graph.frame_m / 2.0
    for i, lane in enumerate(lanes):
        length = polyline_length(lane)
        touches = bool(np.any(np.abs(lane[[0, -1]]) >= half - BORDER_M))
        if not has_pred[i] and not has_succ[i] and not touches:
            report.problems.append(Problem("dangling", [i], lane[len(lane) // 2].tolist()))
        if length < MIN_LENGTH_M:
            report.problems.append(Problem("short", [i], lane[0].tolist(), f"{length:.2f} m"))
        if len(lane) >= 3 and not LineString(lane).is_simple:
            report.problems.append(Problem("self_intersection", [i], lane[len(lane) // 2].tolist()))
        radius, where = _min_radius(lane)
        if radius < MIN_RADIUS_M:
            report.problems.append(Problem("kink", [i], where.tolist(), f"radius {radius:.2f} m"))
    for i, j in succ:
        gap = float(np.linalg.norm(lanes[i][-1] - lanes[j][0]))
        turn = _turn_deg(lanes[i], lanes[j])
        if gap > MAX_GAP_M or turn > MAX_TURN_DEG:
            report.problems.append(Problem("bad_successor", [i, j], lanes[i][-1].tolist(),
                                           f"gap {gap:.2f} m, turn {turn:.0f} deg"))
    report.problems += _crossings(lanes, succ)
    report.routable_pairs, report.largest_scc = _routability(n, succ)
    report.routable_with_changes = _routability(n, succ + lane_changes(graph))[0]
    return report


def lane_changes(graph) -> list[tuple[int, int]]:
    """Lane-change edges, both ways between lane-change neighbours (the graph's ``left_neighbors``,
    found from the geometry when it records none)."""
    pairs = graph.left_neighbors
    if pairs is None:
        lanes = [np.asarray(l, np.float64) for l in graph.lanes]
        pairs = [(i, j) for i, j in infer_neighbours(lanes, graph.widths) if same_direction(lanes, i, j)]
    return [(int(i), int(j)) for i, j in pairs] + [(int(j), int(i)) for i, j in pairs]


def _min_radius(lane: np.ndarray) -> tuple[float, np.ndarray]:
    """Smallest turn radius along the lane: at each vertex, the mean length of its two segments (the
    shorter one at a corner) over the angle it turns by, on the vertices thinned to at least 2 m
    apart with corners (turns over 45 degrees) always kept, so sparse and dense samplings of one
    curve measure alike and a corner reads as sharp however long its sides."""
    corner = np.radians(45.0)
    p = _thinned(lane, 2.0, corner)
    if len(p) < 3:
        return float("inf"), lane[0]
    turn, seg = _turns(p)
    legs = np.where(turn > corner, np.minimum(seg[:-1], seg[1:]), (seg[:-1] + seg[1:]) / 2.0)
    with np.errstate(divide="ignore"):
        radius = np.where(turn > 1e-9, legs / turn, np.inf)
    k = int(np.argmin(radius))
    return float(radius[k]), p[k + 1]


def _turns(line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angle each interior vertex turns by, and the segment lengths."""
    d = np.diff(line, axis=0)
    seg = np.linalg.norm(d, axis=1)
    cos = np.einsum("ij,ij->i", d[:-1], d[1:]) / np.maximum(seg[:-1] * seg[1:], 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0)), seg


def _thinned(line: np.ndarray, spacing: float, corner: float) -> np.ndarray:
    """The vertices of ``line`` with each kept one at least ``spacing`` from the one before, except
    that vertices turning by more than ``corner`` are always kept; the last vertex replaces a kept
    one closer than that. Steps under ``STEP_M`` go first: they have no direction worth measuring, and
    rounding a file's coordinates to the millimetre must not change the judgement."""
    line = _spaced(line, STEP_M, np.zeros(len(line), bool))
    sharp = np.r_[False, _turns(line)[0] > corner, False] if len(line) >= 3 else np.zeros(len(line), bool)
    return _spaced(line, spacing, sharp)


def _spaced(line: np.ndarray, spacing: float, kept: np.ndarray) -> np.ndarray:
    """The vertices of ``line`` at least ``spacing`` from the one kept before, and those ``kept`` marks; the last
    vertex replaces a kept one closer than that (unless marked)."""
    keep = [0]
    for i in range(1, len(line)):
        if kept[i] or np.linalg.norm(line[i] - line[keep[-1]]) >= spacing:
            keep.append(i)
    if keep[-1] != len(line) - 1:
        if len(keep) > 1 and not kept[keep[-1]]:
            keep[-1] = len(line) - 1
        else:
            keep.append(len(line) - 1)
    return line[keep]


def _turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    da, db = unit(a[-1] - a[max(-2, -len(a))]), unit(b[min(1, len(b) - 1)] - b[0])
    return float(np.degrees(np.arccos(np.clip(np.dot(da, db), -1.0, 1.0))))


def _crossings(lanes: list[np.ndarray], succ: list[tuple[int, int]]) -> list[Problem]:
    """Crossings of lanes that are not joined by an edge, away from forks and merges."""
    n = len(lanes)
    out_deg = np.bincount([i for i, _ in succ], minlength=n)
    in_deg = np.bincount([j for _, j in succ], minlength=n)
    junction_points = []
    junction_lanes = set()
    for i, j in succ:  # a fork (i has several successors) or a merge (j has several predecessors)
        if out_deg[i] > 1 or in_deg[j] > 1:
            junction_lanes.update((i, j))
            junction_points.append(lanes[i][-1])
    junction_points = np.array(junction_points).reshape(-1, 2)
    linked = {frozenset(e) for e in succ}
    shapes = [LineString(l) for l in lanes]
    tree = STRtree(shapes)
    problems = []
    for i, j in zip(*tree.query(shapes, predicate="crosses")):
        if i >= j or frozenset((i, j)) in linked or i in junction_lanes or j in junction_lanes:
            continue
        point = shapes[i].intersection(shapes[j]).representative_point()
        at = np.array([point.x, point.y])
        if len(junction_points) and np.min(np.linalg.norm(junction_points - at, axis=1)) <= JUNCTION_REACH_M:
            continue
        problems.append(Problem("crossing", [int(i), int(j)], at.tolist()))
    return problems


def _routability(n: int, succ: list[tuple[int, int]]) -> tuple[float, int]:
    """Share of ordered lane pairs joined by a path, and the largest strongly connected set: per strongly
    connected component, children first, the set of lanes it reaches as the bits of an integer, so
    thousands of lanes cost milliseconds, not an all-pairs path search."""
    if n < 2:
        return 1.0, n
    adj = csr_matrix((np.ones(len(succ)), ([i for i, _ in succ], [j for _, j in succ])), shape=(n, n))
    count, labels = connected_components(adj, directed=True, connection="strong")
    members = [0] * count
    for lane, c in enumerate(labels.tolist()):
        members[c] |= 1 << lane
    children: list[set[int]] = [set() for _ in range(count)]
    indegree = np.zeros(count, int)
    for i, j in succ:
        a, b = int(labels[i]), int(labels[j])
        if a != b and b not in children[a]:
            children[a].add(b)
            indegree[b] += 1
    order, stack = [], [c for c in range(count) if indegree[c] == 0]  # topological order (Kahn)
    while stack:
        c = stack.pop()
        order.append(c)
        for k in children[c]:
            indegree[k] -= 1
            if indegree[k] == 0:
                stack.append(k)
    reach = members[:]
    for c in reversed(order):
        for k in children[c]:
            reach[c] |= reach[k]
    pairs = sum((reach[c].bit_count() - 1) * members[c].bit_count() for c in range(count))
    return pairs / (n * (n - 1)), int(np.bincount(labels).max())
