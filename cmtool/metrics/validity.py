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
over their condensation, numbered within each weakly connected set, so memory grows with the largest of
those, not with the map). Crops of a city are mostly not routable end to end, so routability is
reported against the ground truth's, not scored.

Huge maps: in a weakly connected set of more than ``EXACT_COMPONENT`` lanes, routability is estimated
from ``SAMPLED_SOURCES`` lanes drawn with a fixed seed (the lanes each reaches, by breadth-first search);
crossings are tested exactly for up to ``MAX_CROSSING_TESTS`` candidate pairs (lane pairs whose boxes
overlap), beyond that on the pairs of a fixed-seed random share of the lanes, the count scaled up; at most
``MAX_LISTED`` problems of a kind are listed, the rest counted; lanes piled so thick that the neighbour search
refuses them (:class:`cmtool.maps.neighbours.Crowded`) get their routability without lane changes. Every such
estimate or cap is named in ``estimated`` / ``unlisted`` (and the JSON); maps below the caps get exact values.

Score: the share of lanes free of problems (a bad successor edge or a crossing counts against
both its lanes); 1.0 for a map without problems, and for an empty map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from cmtool.core.geometry import equal_count_batches, unit
from cmtool.core.memory import in_batches
from cmtool.core.radius import min_radii
from cmtool.maps.neighbours import Crowded, infer_neighbours, same_directions

MAX_GAP_M, MAX_TURN_DEG = 1.5, 60.0
MIN_LENGTH_M, MIN_RADIUS_M = 2.0, 4.0
BORDER_M = 1.0  # an endpoint this close to the frame edge touches the border
JUNCTION_REACH_M = 20.0
EXACT_COMPONENT = 20_000  # lanes: larger weakly connected sets get their routability from sampled sources
SAMPLED_SOURCES = 1_000
MAX_CROSSING_TESTS = 5_000_000  # candidate lane pairs tested for crossings; more: a random share of the lanes
MAX_LISTED = 100_000  # problems of one kind listed; more are counted in ``unlisted``
CHUNK_LANES = 2_048  # lanes per batch of the crossing search and of the kink check
SEED = 0


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
    routable_pairs: float | None = None  # None: not computed (``check(..., routes=False)``)
    routable_with_changes: float | None = None
    largest_scc: int | None = None
    unlisted: dict[str, int] = field(default_factory=dict)  # problems counted beyond ``MAX_LISTED``, per kind
    unlisted_lanes: set[int] = field(default_factory=set)  # the lanes of those
    estimated: dict[str, str] = field(default_factory=dict)  # quantity -> how it was estimated (huge maps)

    @property
    def score(self) -> float:
        if self.lanes == 0:
            return 1.0
        bad = {i for p in self.problems for i in p.lanes} | self.unlisted_lanes
        return 1.0 - len(bad) / self.lanes

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = dict(self.unlisted)
        for p in self.problems:
            out[p.kind] = out.get(p.kind, 0) + 1
        return out

    def to_json(self) -> dict:
        caps = {k: v for k, v in (("unlisted", self.unlisted), ("estimated", self.estimated)) if v}
        return {"score": round(self.score, 6), "lanes": self.lanes, "counts": self.counts(),
                "routable_pairs": round(self.routable_pairs, 6),
                "routable_with_changes": round(self.routable_with_changes, 6), "largest_scc": self.largest_scc,
                **caps, "problems": [p.to_json() for p in self.problems]}


def check(graph, routes: bool = True) -> Validity:
    """The validity report of one lane graph (``lanes``, ``successors``, ``frame_m``); ``routes``: False leaves out
    the routability figures (None), for callers that need only the problems and the score."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    n = len(lanes)
    report = Validity(n)
    if n == 0:
        if routes:
            report.routable_pairs, report.routable_with_changes, report.largest_scc = 1.0, 1.0, 0
        return report
    succ = [(int(i), int(j)) for i, j in graph.successors]
    joined = np.zeros(n, bool)
    joined[[k for edge in succ for k in edge]] = True
    half = graph.frame_m / 2.0
    ends = np.array([lane[[0, -1]] for lane in lanes])
    touches = np.any(np.abs(ends) >= half - BORDER_M, axis=(1, 2))
    shapes = _shapes(lanes)
    simple = shapely.is_simple(shapes)
    radius, where = min_radii(lanes)
    lengths = np.zeros(n)
    for which, batch in equal_count_batches(lanes):  # polyline_length of each, the same sums
        lengths[which] = np.linalg.norm(np.diff(batch, axis=1), axis=2).sum(axis=1)
    for i in np.flatnonzero(~joined | ~simple | (radius < MIN_RADIUS_M) | (lengths < MIN_LENGTH_M)).tolist():
        lane, length = lanes[i], lengths[i]
        if not joined[i] and not touches[i]:
            report.problems.append(Problem("dangling", [i], lane[len(lane) // 2].tolist()))
        if length < MIN_LENGTH_M:
            report.problems.append(Problem("short", [i], lane[0].tolist(), f"{length:.2f} m"))
        if len(lane) >= 3 and not simple[i]:
            report.problems.append(Problem("self_intersection", [i], lane[len(lane) // 2].tolist()))
        if radius[i] < MIN_RADIUS_M:
            report.problems.append(Problem("kink", [i], where[i].tolist(), f"radius {radius[i]:.2f} m"))
    gaps, turns = _joints(lanes, succ)
    for k in np.flatnonzero((gaps > MAX_GAP_M) | (turns > MAX_TURN_DEG)).tolist():
        (i, j), gap, turn = succ[k], float(gaps[k]), float(turns[k])
        report.problems.append(Problem("bad_successor", [i, j], lanes[i][-1].tolist(),
                                       f"gap {gap:.2f} m, turn {turn:.0f} deg"))
    _add_crossings(report, lanes, shapes, succ)
    if not routes:
        return report
    report.routable_pairs, report.largest_scc, sampled = _routability(n, succ)
    try:
        changes = lane_changes(graph)
    except Crowded as e:  # lanes piled on each other: no lane changes searched, and the report says so
        changes, report.estimated["routable_with_changes"] = [], f"without lane changes ({e})"
    report.routable_with_changes, _, sampled_changes = _routability(n, succ + changes)
    for key, done in (("routable_pairs", sampled), ("routable_with_changes", sampled_changes)):
        if done:
            report.estimated.setdefault(key, f"{SAMPLED_SOURCES} sources sampled (seed {SEED}) in each weakly "
                                             f"connected set of over {EXACT_COMPONENT:,} lanes")
    return report


def _shapes(lanes: list[np.ndarray]) -> np.ndarray:
    """The lanes as shapely LineStrings, made in one call."""
    return shapely.linestrings(np.concatenate(lanes), indices=np.repeat(np.arange(len(lanes)), [len(l) for l in lanes]))


def lane_changes(graph) -> list[tuple[int, int]]:
    """Lane-change edges, both ways between lane-change neighbours (the graph's ``left_neighbors``,
    found from the geometry when it records none)."""
    pairs = graph.left_neighbors
    if pairs is None:
        lanes = [np.asarray(l, np.float64) for l in graph.lanes]
        found = infer_neighbours(lanes, graph.widths)
        pairs = [(i, j) for (i, j), same in zip(found, same_directions(lanes, found)) if same]
    return [(int(i), int(j)) for i, j in pairs] + [(int(j), int(i)) for i, j in pairs]


def _joints(lanes: list[np.ndarray], succ: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """Of each successor edge (i, j): the gap (m) from the end of lane i to the start of lane j, and the angle (degrees)
    between their directions there (``np.vecdot`` takes ``np.dot`` of each pair: the numbers of one edge alone)."""
    ends = np.array([lane[[0, 1, -2, -1]] for lane in lanes])
    i, j = np.array(succ, np.int64).reshape(-1, 2).T
    gap = ends[i, 3] - ends[j, 0]
    out, into = unit(ends[i, 3] - ends[i, 2]), unit(ends[j, 1] - ends[j, 0])
    return np.sqrt(np.vecdot(gap, gap)), np.degrees(np.arccos(np.clip(np.vecdot(out, into), -1.0, 1.0)))


def _add_crossings(report: Validity, lanes: list[np.ndarray], shapes: np.ndarray, succ: list[tuple[int, int]]) -> None:
    """Add the crossings of lanes that are not joined by an edge, away from forks and merges: listed up to
    ``MAX_LISTED``, counted beyond; estimated on huge maps (:func:`_crossing_pairs`)."""
    n = len(lanes)
    out_deg = np.bincount([i for i, _ in succ], minlength=n)
    in_deg = np.bincount([j for _, j in succ], minlength=n)
    junction_points, exempt = [], np.zeros(n, bool)
    for i, j in succ:  # a fork (i has several successors) or a merge (j has several predecessors)
        if out_deg[i] > 1 or in_deg[j] > 1:
            exempt[[i, j]] = True
            junction_points.append(lanes[i][-1])
    linked = np.array(sorted({(min(e), max(e)) for e in succ}), np.int64).reshape(-1, 2)
    i, j, share = _crossing_pairs(shapes, exempt, linked[:, 0] * n + linked[:, 1])
    if junction_points:  # every crossing's point decides whether it is listed or counted
        at = _crossing_points(shapes, i, j)
        far = cKDTree(np.array(junction_points)).query(at)[0] > JUNCTION_REACH_M
        i, j, at = i[far], j[far], at[far]
    else:  # the points of the listed ones only: a dense map of 100,000 lanes has about a million crossings
        at = _crossing_points(shapes, i[:MAX_LISTED], j[:MAX_LISTED])
    report.problems += [Problem("crossing", [a, b], p) for a, b, p in
                        zip(i[:MAX_LISTED].tolist(), j[:MAX_LISTED].tolist(), at[:MAX_LISTED].tolist())]
    total = len(i) if share == 1.0 else int(round(len(i) / share))
    if total > MAX_LISTED:
        report.unlisted["crossing"] = total - min(len(i), MAX_LISTED)
        report.unlisted_lanes.update(i[MAX_LISTED:].tolist(), j[MAX_LISTED:].tolist())
    if share < 1.0:
        report.estimated["crossing"] = (f"over {MAX_CROSSING_TESTS:,} candidate pairs: the pairs of {share:.2%} of the "
                                        f"lanes (seed {SEED}) tested, the count scaled up; the score counts only "
                                        "the lanes of the crossings found")


def _crossing_pairs(shapes: np.ndarray, exempt: np.ndarray, linked: np.ndarray):
    """Lane pairs (i < j) that cross, neither ``exempt`` nor ``linked`` (keys ``i * n + j``), in order of i, then of
    the STR-tree. The lanes are taken in batches (:func:`cmtool.core.memory.in_batches`) in a fixed-seed random
    order; once ``MAX_CROSSING_TESTS`` candidate pairs (overlapping boxes) are tested, the rest are left: returns
    (i, j, the share of the lanes whose pairs were tested)."""
    n = len(shapes)
    tree, order = shapely.STRtree(shapes), np.random.default_rng(SEED).permutation(n)
    found, tested = [], [0]

    def search(lo: int, hi: int) -> int:
        batch = np.sort(order[lo:hi])
        q, j = tree.query(shapes[batch])
        i = batch[q]
        keep = (i < j) & ~exempt[i] & ~exempt[j]
        i, j = i[keep], j[keep]
        if len(linked):
            free = ~np.isin(i * n + j, linked)
            i, j = i[free], j[free]
        tested[0] += len(i)
        cross = shapely.crosses(shapes[i], shapes[j])
        found.append((i[cross], j[cross]))
        return len(q)

    done = in_batches(n, search, most=CHUNK_LANES, until=lambda: tested[0] >= MAX_CROSSING_TESTS)
    i = np.concatenate([f[0] for f in found]) if found else np.zeros(0, np.int64)
    j = np.concatenate([f[1] for f in found]) if found else np.zeros(0, np.int64)
    first = np.argsort(i, kind="stable")
    return i[first], j[first], done / n


def _crossing_points(shapes: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """A point of each crossing of lanes ``i[k]`` and ``j[k]``: the representative point of their intersection."""
    return shapely.get_coordinates(shapely.point_on_surface(shapely.intersection(shapes[i], shapes[j]))).reshape(-1, 2)


def _routability(n: int, succ: list[tuple[int, int]]) -> tuple[float, int, bool]:
    """Share of ordered lane pairs joined by a path, the largest strongly connected set, and whether the share was
    estimated: per strongly connected component, children first, the set of lanes it reaches as the bits of an
    integer (bits numbered within the weakly connected set, which paths never leave), so thousands of lanes cost
    milliseconds, not an all-pairs path search; weakly connected sets of over ``EXACT_COMPONENT`` lanes count the
    lanes reached from ``SAMPLED_SOURCES`` sampled sources instead."""
    if n < 2:
        return 1.0, n, False
    key = np.unique(np.array(succ, np.int64).reshape(-1, 2) @ [n, 1])  # each edge once, by row, then column
    adj = csr_matrix((np.ones(len(key)), key % n, np.r_[0, np.cumsum(np.bincount(key // n, minlength=n))]),
                     shape=(n, n))  # made from its rows directly (the canonical form csgraph needs), not via COO
    _, weak = connected_components(adj, directed=True, connection="weak")
    size = np.bincount(weak)
    huge = size[weak] > EXACT_COMPONENT
    order = np.argsort(weak, kind="stable")
    local = np.empty(n, np.int64)
    local[order] = np.arange(n) - (np.cumsum(size) - size)[weak[order]]
    count, labels = connected_components(adj, directed=True, connection="strong")
    pairs = _reach_pairs(count, labels, local, huge, succ) + (_sampled_pairs(adj, weak, huge) if huge.any() else 0)
    return pairs / (n * (n - 1)), int(np.bincount(labels).max()), bool(huge.any())


def _reach_pairs(count: int, labels: np.ndarray, local: np.ndarray, huge: np.ndarray, succ) -> int:
    """Ordered pairs joined by a path among the lanes not ``huge``: reachable sets as bitsets over the condensation
    (strongly connected components ``labels``; bit ``local[lane]``), children first."""
    members = [0] * count
    for lane, c in zip(np.flatnonzero(~huge).tolist(), labels[~huge].tolist()):
        members[c] |= 1 << int(local[lane])
    children: list[set[int]] = [set() for _ in range(count)]
    indegree = np.zeros(count, int)
    for i, j in succ:
        a, b = int(labels[i]), int(labels[j])
        if a != b and b not in children[a] and not huge[i]:
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
    return sum((reach[c].bit_count() - 1) * members[c].bit_count() for c in range(count) if members[c])


def _sampled_pairs(adj, weak: np.ndarray, huge: np.ndarray) -> float:
    """Ordered pairs joined by a path within each ``huge`` weakly connected set, estimated from the lanes that
    ``SAMPLED_SOURCES`` of its lanes (drawn with seed ``SEED``) reach."""
    rng, pairs = np.random.default_rng(SEED), 0.0
    for component in np.unique(weak[huge]):
        lanes = np.flatnonzero(weak == component)
        sources = rng.choice(lanes, min(SAMPLED_SOURCES, len(lanes)), replace=False)
        reached = [len(breadth_first_order(adj, int(s), return_predecessors=False)) - 1 for s in sources]
        pairs += float(np.mean(reached)) * len(lanes)
    return pairs
