"""Lane graphs as Lanelet2 maps (OSM XML, WGS84), loadable by Lanelet2 and by our own importer.

Every lane becomes a lanelet (``type=lanelet``, ``subtype=road``, ``one_way=yes``) whose left and
right bounds are ways half its width either side of the centerline (widths from the lane graph, else
from the spacing of neighbours, else ``lane_width``). Lanelet2 routing reads lanelet b as following a
where a's bounds end on the nodes b's start on, so lanes that go on to the same lanes end on one left
and one right node, which the starts of those lanes share; a lane that several such groups go on to
(lane 1 may go on to lane 2 but not to lane 3, which lane 0 forks into beside lane 2) gets a lanelet
for each group, the copies alike but for their start nodes and with the same ``cmtool:lane``. Where
Lanelet2's loader would read a lanelet's bounds the wrong way round (it judges by their middle points:
lanes shorter than wide, or kinked), they are drawn plainer between the same end nodes. Neighbours
(the lane graph's ``left_neighbors`` and ``oncoming``, found from the geometry when it has none) that
start and end abreast share one bound way: dashed between lane-change neighbours, so Lanelet2 routes
lane changes; solid as the centre line of oncoming lanes (their left bounds in right-hand traffic,
their right bounds in left-hand traffic). Each traffic-light line becomes a ``regulatory_element``
(``subtype=traffic_light``, its state as ``cmtool:state``) with a light way and a stop line across the
start of the lane it controls (:func:`~cmtool.maps.lanegraph.controlled_lanes`), referenced by that
lane's lanelets; a light that controls no lane stays, referenced by none. Lanelets carry the city label
as ``cmtool:city``, which cmtool's importer reads back. The scene frame's origin is placed at
``(lat0, lon0)`` with its forward axis pointing to the compass ``heading``.
"""

from __future__ import annotations

import os
from collections import defaultdict
from itertools import chain
from xml.sax.saxutils import quoteattr

import numpy as np

from cmtool.core.geo import scene_to_latlon
from cmtool.core.geometry import equal_count_batches, offset, padded, resample
from cmtool.core.jsonio import write_text_atomic
from cmtool.core.unionfind import UnionFind
from cmtool.maps.lanegraph import controlled_lanes, stop_line
from cmtool.maps.neighbours import (
    LANE_WIDTH_M,
    abreasts,
    graph_neighbours,
    lane_widths,
    side_of,
)

LEFT, RIGHT = 0, 1
START, END = 0, 1


class _Ways:
    """Nodes and ways, numbered from 1. Nodes are shared by name only (a way's end named by the bound corner it
    is joined to), never by position: Lanelet2 reads a shared node as a link, so two lanes that merely end at
    one point must not share one, or each would inherit the other's successors."""

    def __init__(self):
        self.named: dict[object, int] = {}
        self.nodes: list[np.ndarray] = []
        self.ways: list[tuple[list[int], dict]] = []

    def node(self, p: np.ndarray, name=None) -> int:
        if name is not None and name in self.named:
            return self.named[name]
        self.nodes.append(np.asarray(p, np.float64))
        if name is not None:
            self.named[name] = len(self.nodes)
        return len(self.nodes)

    def way(self, points: np.ndarray, start=None, end=None, **tags) -> int:
        """A way through ``points``; ``start``, ``end``: the names of its end nodes (None: nodes of its own)."""
        refs = [self.node(points[0], start), *(self.node(p) for p in points[1:-1]), self.node(points[-1], end)]
        self.ways.append((refs, tags))
        return len(self.ways)


def to_lanelet2(graph, lat0: float, lon0: float, heading: float = 0.0, lane_width: float = LANE_WIDTH_M) -> str:
    """The OSM XML text of ``graph`` (a LaneGraph) as a Lanelet2 map."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    left, oncoming = graph_neighbours(graph)
    widths = lane_widths(lanes, left, graph.widths, lane_width)
    lane_of, joins, allowed = _lanelets(len(lanes), {(int(i), int(j)) for i, j in graph.successors})
    lane_bounds = {}  # (lane, side) -> its bound, lanes of one vertex count at once
    for which, batch in equal_count_batches(lanes):
        for side, half in ((LEFT, 0.5), (RIGHT, -0.5)):
            lane_bounds.update(((k, side), line) for k, line in zip(which, offset(batch, half * widths[which])))
    bounds = {(u, side): lane_bounds[i, side] for u, i in enumerate(lane_of) for side in (LEFT, RIGHT)}
    corners = _Corners(len(lane_of), allowed)
    for (a, a_end), (b, b_end) in joins:
        corners.join([((a, side, a_end), (b, side, b_end)) for side in (LEFT, RIGHT)])
    shared = {}  # bound -> (the bound it shares a way with, whether that one runs against it)
    beside = [((i, LEFT), (j, RIGHT), True) for i, j in left]  # lane-change neighbours: i's left bound is j's right
    for i, j in oncoming:  # the centre line: the bound on the side where the other lane lies, for both
        side = LEFT if side_of(lanes, i, j) > 0 else RIGHT
        beside.append(((i, side), (j, side), False))
    fits = abreasts(lanes, [(mine[0], other[0]) for mine, other, _ in beside], [same for *_, same in beside])
    for (mine, other, same), fit in zip(beside, fits):
        if mine in shared or other in shared or not fit:
            continue
        ends = ((START, START), (END, END)) if same else ((START, END), (END, START))
        if corners.join([((*mine, a), (*other, b)) for a, b in ends]):
            shared[mine], shared[other] = (other, not same), (mine, not same)
    lines = _way_lines(bounds, shared, corners, len(lane_of))
    ways, way_of = _Ways(), {}
    for key, line in lines.items():
        partner = shared.get(key)
        way_of[key] = ways.way(line, corners.name((*key, START)), corners.name((*key, END)), type="line_thin",
                               subtype="dashed" if partner and not partner[1] else "solid")
        if partner is not None:
            way_of[partner[0]] = way_of[key]
    relations = []
    city = {"cmtool:city": graph.city or "none"}  # read back by cmtool's importer
    for u, i in enumerate(lane_of):
        relations.append(([("way", way_of[(u, LEFT)], "left"), ("way", way_of[(u, RIGHT)], "right")],
                          {"type": "lanelet", "subtype": "road", "location": "urban", "one_way": "yes",
                           "cmtool:lane": str(i), **city}))
    for state, line, k in controlled_lanes(graph, every=True):  # a light that controls no lane stays, unreferenced
        stop = stop_line(lanes[k], widths[k], at=line[0]) if k is not None else stop_line(line, lane_width)
        stop_way = ways.way(stop, type="stop_line")
        light_way = ways.way(line[:2], type="traffic_light", subtype="red_yellow_green")
        relations.append(([("way", light_way, "refers"), ("way", stop_way, "ref_line")],
                          {"type": "regulatory_element", "subtype": "traffic_light", "cmtool:state": state}))
        for u in (u for u, i in enumerate(lane_of) if i == k):
            relations[u][0].append(("relation", len(relations), "regulatory_element"))
    return _xml(ways, relations, lat0, lon0, heading)


def write_lanelet2(graph, path: str | os.PathLike, lat0: float, lon0: float, heading: float = 0.0,
                   lane_width: float = LANE_WIDTH_M) -> None:
    write_text_atomic(path, to_lanelet2(graph, lat0, lon0, heading, lane_width))


def _way_lines(bounds, shared, corners, count: int) -> dict:
    """Bound -> the points of its way (a shared way: under the bound that comes first), halfway to the bound it shares
    the way with, its ends on their nodes; plainer for each of the ``count`` lanelets whose bounds Lanelet2 would
    read the wrong way round."""
    lines = {}
    for key, line in bounds.items():
        if key in lines or (key in shared and shared[key][0] in lines):
            continue
        partner = shared.get(key)
        if partner is not None:
            twin = resample(bounds[partner[0]], len(line))
            line = 0.5 * (line + (twin[::-1] if partner[1] else twin))
        lines[key] = _pin_ends(line, corners.position(bounds, (*key, START)), corners.position(bounds, (*key, END)))
    keys = [[(key, False) if key in lines else shared[key] for key in ((u, LEFT), (u, RIGHT))] for u in range(count)]
    bounds_of = [[lines[k][::-1] if against else lines[k] for k, against in pair] for pair in keys]
    reversed_, changed = _reads_reversed(bounds_of), set()  # changed: the ways redrawn plainer
    for u in range(count):  # a lanelet whose ways an earlier one redrew is judged again
        if not reversed_[u] and not any(k in changed for k, _ in keys[u]):
            continue
        bound = [lines[k][::-1] if against else lines[k] for k, against in keys[u]]
        for n, pair in enumerate(chain([bound], _plain_bounds(bound[0][[0, -1]], bound[1][[0, -1]]))):
            if not _read_reversed(*pair):
                for (k, against), line in zip(keys[u], pair):
                    lines[k] = line[::-1] if against else line
                    changed.update([k] if n else [])
                break
    return lines


def _lanelets(n: int, successors: set[tuple[int, int]]):
    """Lanelets for ``n`` lanes such that shared end nodes link exactly the successor pairs: lanes that go on to the
    same lanes end on one pair of nodes, and a lane that several such groups go on to gets a lanelet for each (the
    copies end where the lane ends). Returns the lane of each lanelet (the lanes themselves first), the lanelet ends
    to join ((a, end), (b, end)) and the pairs of lanelets that may flow into each other."""
    after = defaultdict(set)
    for i, j in successors:
        after[i].add(j)
    lane_of, start_of, taken = list(range(n)), {}, set()  # start_of: (group, lane) -> its lanelet for that group
    for group in sorted({frozenset(s) for s in after.values()}, key=sorted):
        for j in sorted(group):
            if j in taken:
                lane_of.append(j)
            start_of[(group, j)] = len(lane_of) - 1 if j in taken else j
            taken.add(j)
    joins = [((i, END), (start_of[(frozenset(after[i]), j)], START)) for i in sorted(after) for j in sorted(after[i])]
    joins += [((u, END), (i, END)) for u, i in enumerate(lane_of) if u != i]
    allowed = {(a, start_of[(frozenset(after[i]), j)]) for a, i in enumerate(lane_of) for j in after.get(i, ())}
    return lane_of, joins, allowed


class _Corners:
    """The four corners of every lanelet's bounds, ``(lanelet, side, end)``, joined into shared nodes:
    lanelet ends with their successors' starts, neighbours' shared bound ends. Lanelet2 reads lanelet a as
    flowing into lanelet b where a's end corners are b's start corners, so a join is refused where it would
    make one lanelet's left and right corner at the same end one node (a lanelet of no width), or a corner at its
    start one node with a corner at its end (a lanelet of no length), or make a lanelet flow into one it may not
    (``allowed``: pairs of lanelets)."""

    def __init__(self, n: int, allowed: set[tuple[int, int]]):
        keys = [(i, side, end) for i in range(n) for side in (LEFT, RIGHT) for end in (START, END)]
        self.sets = UnionFind(keys)
        self.members = {k: {k} for k in keys}
        self.allowed = allowed

    def join(self, pairs) -> bool:
        """Join each pair of corners, all or none; whether they were joined."""
        trial = UnionFind(self.sets.find(k) for pair in pairs for k in pair)
        for a, b in pairs:
            trial.union(self.sets.find(a), self.sets.find(b))
        groups = [set().union(*(self.members[r] for r in group)) for group in trial.groups()]
        if any((i, 1 - side, end) in merged or (i, LEFT, 1 - end) in merged or (i, RIGHT, 1 - end) in merged
               for merged in groups for i, side, end in merged):
            return False
        new = {k: ("joined", n) for n, merged in enumerate(groups) for k in merged}

        def node(key):  # the node a corner would be after the join
            return new.get(key) or self.sets.find(key)

        for merged in groups:  # the lanes that would flow into each other through these nodes
            for a, side, end in merged:
                for b, other, start in merged:
                    if end == END and start == START and other == side and (a, b) not in self.allowed \
                            and node((a, 1 - side, END)) == node((b, 1 - side, START)):
                        return False
        for a, b in pairs:
            ra, rb = self.sets.find(a), self.sets.find(b)
            if ra != rb:
                self.sets.union(ra, rb)
                self.members[ra] |= self.members.pop(rb)
        return True

    def name(self, key):
        """The name of the node a corner is joined into (one per group of joined corners)."""
        return self.sets.find(key)

    def position(self, bounds, key) -> np.ndarray:
        """Where a corner's node lies: the mean of the bound ends joined to it."""
        members = self.members[self.sets.find(key)]
        return np.mean([bounds[(i, side)][0 if end == START else -1] for i, side, end in members], axis=0)


def _read_reversed(left: np.ndarray, right: np.ndarray) -> bool:
    """Whether Lanelet2's loader might turn either bound of a lanelet round: it inverts the left bound unless the
    middle point of the right one lies on its right, then the right bound unless the middle of the left lies on
    its left (``lanelet::geometry::align``), each side taken at the nearest segment (any of them on a tie)."""
    return bool((_sides(left, _middle(right)) >= 0.0).any() or (_sides(right, _middle(left)) <= 0.0).any())


def _reads_reversed(bounds: list[list[np.ndarray]]) -> np.ndarray:
    """:func:`_read_reversed` of each lanelet's [left, right] bounds, the same numbers in padded arrays: bounds of
    like vertex counts in batches, so 100,000 lanelets take a loop over batches, not over lanelets."""
    out = np.zeros(len(bounds), bool)
    order = sorted(range(len(bounds)), key=lambda u: (len(bounds[u][0]), len(bounds[u][1])))
    for start in range(0, len(order), 4096):
        batch = order[start:start + 4096]
        left, right = ([bounds[u][side] for u in batch] for side in (LEFT, RIGHT))
        value, near = _sides_padded(left, np.array([_middle(r) for r in right]))
        wrong = ((value >= 0.0) & near).any(axis=1)
        value, near = _sides_padded(right, np.array([_middle(l) for l in left]))
        out[batch] = wrong | ((value <= 0.0) & near).any(axis=1)
    return out


def _sides_padded(lines: list[np.ndarray], p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_sides` of each line and point ``p[k]`` at once: (m, S) side values at every segment and whether the
    segment is one :func:`_sides` reports (nearest within 1 mm; padding never)."""
    points, count = padded(lines)
    a, ab, q = points[:, :-1], np.diff(points, axis=1), p[:, None, :]
    t = np.clip(np.sum((q - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=2), 1e-18), 0.0, 1.0)
    distance = np.linalg.norm(a + t[:, :, None] * ab - q, axis=2)
    real = np.arange(ab.shape[1])[None, :] < (count - 1)[:, None]
    distance[~real] = np.inf
    near = real & (distance <= distance.min(axis=1, keepdims=True) + 1e-3)
    return ab[..., 0] * (q - a)[..., 1] - ab[..., 1] * (q - a)[..., 0], near


def _plain_bounds(left: np.ndarray, right: np.ndarray):
    """Simpler (left, right) bounds between the same end points (``left``, ``right``: each bound's two ends):
    straight lines; then three-point lines whose middles lie half a lane either side of one point, along a direction
    in which both bounds advance past it; last, for ends that twist the lanelet, bounds that pass along two 1 m
    tracks 0.2 m apart in its middle (in one of eight directions), which Lanelet2 reads by the tracks."""
    yield (np.array([left[0], left.mean(axis=0), left[1]]), np.array([right[0], right.mean(axis=0), right[1]]))
    centre = 0.25 * (left.sum(axis=0) + right.sum(axis=0))
    half = 0.25 * (np.linalg.norm(left[0] - right[0]) + np.linalg.norm(left[1] - right[1]))
    ahead = [v / max(float(np.linalg.norm(v)), 1e-9) for v in (left[1] - left[0], right[1] - right[0])]
    for d in (ahead[0] + ahead[1], 0.5 * (left[1] + right[1] - left[0] - right[0])):
        d = d / max(float(np.linalg.norm(d)), 1e-9)
        n = np.array([-d[1], d[0]])
        low, high = max(left[0] @ d, right[0] @ d), min(left[1] @ d, right[1] @ d)
        if high > low:
            middle = centre + (0.5 * (low + high) - centre @ d) * d
            yield (np.array([left[0], middle + half * n, left[1]]), np.array([right[0], middle - half * n, right[1]]))
    for angle in np.arange(8) * np.pi / 4:
        d = np.array([np.cos(angle), np.sin(angle)])
        n, track = np.array([-d[1], d[0]]), centre + np.outer([-0.5, 0.0, 0.5], d)
        yield (np.vstack([left[0], track + 0.1 * n, left[1]]), np.vstack([right[0], track - 0.1 * n, right[1]]))


def _middle(line: np.ndarray) -> np.ndarray:
    return line[len(line) // 2] if len(line) > 2 else 0.5 * (line[0] + line[-1])


def _sides(line: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The side of ``line`` that ``p`` lies on (positive: left) at each segment nearest it (within 1 mm)."""
    a, ab = line[:-1], np.diff(line, axis=0)
    t = np.clip(np.sum((p - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-18), 0.0, 1.0)
    distance = np.linalg.norm(a + t[:, None] * ab - p, axis=1)
    near = distance <= distance.min() + 1e-3
    return ab[near, 0] * (p - a[near])[:, 1] - ab[near, 1] * (p - a[near])[:, 0]


def _pin_ends(line: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """``line`` with its ends moved to ``start`` and ``end``, each move fading linearly along it."""
    t = np.linspace(0.0, 1.0, len(line))[:, None]
    return line + (1.0 - t) * (start - line[0]) + t * (end - line[-1])


def _xml(ways: _Ways, relations, lat0: float, lon0: float, heading: float) -> str:
    latlon = scene_to_latlon(np.array(ways.nodes).reshape(-1, 2), lat0, lon0, heading)
    quoted: dict[str, str] = {}  # tag keys and values are few but for the lane numbers: quote each once

    def quote(text: str) -> str:
        if text not in quoted:
            quoted[text] = quoteattr(text)
        return quoted[text]

    def tag_lines(tags: dict) -> str:
        return "".join(f"    <tag k={quote(t)} v={quote(v)}/>\n" for t, v in tags.items())

    out = ['<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="cmtool">\n']
    node = '  <node id="%d" lat="%.10f" lon="%.10f" version="1"/>\n'
    for start in range(0, len(latlon), 65536):  # one formatting call per batch of nodes ("%.10f" is f"{:.10f}")
        part = latlon[start:start + 65536]
        ids = np.arange(start + 1, start + 1 + len(part))
        out.append((node * len(part)) % tuple(_interleave(ids, part)))
    for k, (refs, tags) in enumerate(ways.ways, start=1):
        out.append(f'  <way id="{k}" version="1">\n' + ('    <nd ref="%d"/>\n' * len(refs)) % tuple(refs)
                   + tag_lines(tags) + "  </way>\n")
    for k, (members, tags) in enumerate(relations, start=1):
        out.append(f'  <relation id="{k}" version="1">\n'
                   + "".join(f'    <member type="{kind}" ref="{ref}" role="{role}"/>\n' for kind, ref, role in members)
                   + tag_lines(tags) + "  </relation>\n")
    out.append("</osm>\n")
    return "".join(out)


def _interleave(ids: np.ndarray, latlon: np.ndarray) -> list:
    """[id, lat, lon, id, lat, lon, ...] as Python ints and floats."""
    out: list = [None] * (3 * len(ids))
    out[0::3], out[1::3], out[2::3] = ids.tolist(), latlon[:, 0].tolist(), latlon[:, 1].tolist()
    return out
