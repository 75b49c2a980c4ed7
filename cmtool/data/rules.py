"""A rule-based lane layout of an SD map: the baseline a learned map has to beat, and what it can start from.

What the rules do, road by road and junction by junction (as rule-based converters such as SUMO's
``netconvert`` do, written here from the SD map alone):

- **Roads into edges.** Roads are split where they meet: at shared points (OpenStreetMap nodes), where a
  road end stops on another road within ``SNAP_M``, and where roads of one ``layer`` cross. An edge end
  where three or more edge ends meet is a junction; junction nodes joined by an edge shorter than
  ``CLUSTER_M`` are one junction (the two carriageways of a divided road crossing a street), and such
  short edges get no lanes. Two edge ends alone are a join (the road goes on), one is a dead end.
- **Lanes.** A road's ``lanes`` tag (the total of both directions) when known, else its class's usual
  count (``LANES``); a one-way road has them all in its travel direction, a two-way road the larger half
  in the polyline's direction. Lanes are ``LANE_WIDTH_M`` of the class wide, side by side on the driving
  side of the centreline (centred on it when one-way), and end ``setback`` before a junction: the widest
  half of the other roads there plus ``MARGIN_M``, at least ``MIN_SETBACK_M``.
- **Connectors.** Through a junction, every lane of an arm leads straight on to the lanes of each arm
  within ``STRAIGHT_DEG`` of straight (lanes paired from the near side, spread when the counts differ);
  the near-side lane turns into the near-side lane of the arms to the near side, the far-side lane into
  the far-side lane of the arms to the far side; no U-turns (beyond ``UTURN_DEG``). A connector is the
  cubic Bézier curve between the two lane ends along their headings. At a join, lanes run on into the
  lanes of the next edge, paired the same way.
- **Turns a vehicle can drive** (``turn_radius_m``, off in the baseline): a road's bends are rounded to arcs that
  radius wider than its half width; where two roads meet end to end at a bend of more than ``BEND_DEG`` the node
  is a junction of two arms, every lane led on through it; lanes stop short of a junction by as much as its
  sharpest turn needs for the near-side lane to turn at that radius (the widest half road less half a lane, plus
  ``radius * tan(turn / 2)``, the tangent at most ``MAX_TURN_TAN``); a connector's Bézier handles reach towards the
  corner where its two lanes' lines meet (a near-circular arc); a connector still tighter than ``TIGHT`` times the
  radius is left out where both its lanes have another way on and in.

The result is an :class:`~cmtool.maps.hdmap.HDMap` (successors, lane-change neighbours, connector lanes
flagged as intersection lanes; points rounded to the millimetre, as map files store them), cropped into frames
like any HD map.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import shapely

from cmtool.core.geometry import (arc_length, insert_vertex, offset, polyline_length, resample, resample_step,
                                  rounded_corners, unit)
from cmtool.core.radius import min_radii
from cmtool.core.unionfind import UnionFind
from cmtool.maps.hdmap import HDMap, Lane, drives_on
from cmtool.maps.sdmap import Road, SDMap

# Lanes of both directions together when the SD map does not say: (two-way road, one-way road).
LANES = {"motorway": (4, 2), "trunk": (4, 2), "primary": (4, 2), "secondary": (2, 2), "tertiary": (2, 1),
         "unclassified": (2, 1), "residential": (2, 1), "service": (2, 1)}
LANE_WIDTH_M = {"motorway": 3.6, "trunk": 3.5, "primary": 3.4, "secondary": 3.3, "tertiary": 3.2,
                "unclassified": 3.1, "residential": 3.1, "service": 3.0}
SNAP_M = 3.0  # a road end this close to another road meets it there
CLUSTER_M = 20.0  # junction nodes joined by a shorter edge are one junction
MIN_SETBACK_M = 4.0
MARGIN_M = 1.5
STRAIGHT_DEG = 30.0
BEND_DEG = 30.0  # with a turn radius: two roads meeting end to end at a sharper bend meet at a junction
MAX_TURN_TAN = 1.0  # turns sharper than a right angle get a right angle's setback (longer ones cut the short roads
# between junctions to nothing: fewer valid maps on the Argoverse 2 frames of docs/baselines.md)
HEADING_M = 5.0  # a road's heading at a node: towards its point this far along
TIGHT = 0.8  # with a turn radius: a connector tighter than this share of it is too tight (the turns laid out for it
# come out within a few per cent of it)
UTURN_DEG = 150.0
CONNECTOR_POINTS = 20
BEZIER_REACH = 0.4
CORNER_REACH, CORNER_FAR = 0.55, 2.0  # 0.55: a quarter circle's handles
_STEP_M = 2.0  # resampling of centrelines before they are offset into lanes


def lane_counts(road: Road) -> tuple[int, int]:
    """Lanes (along, against) the road's travel direction (:meth:`Road.travel_polyline`)."""
    two_way, one_way = LANES.get(road.road_class, LANES["residential"])
    if road.oneway:
        return max(1, road.lanes or one_way), 0
    total = road.lanes or two_way
    along = max(1, math.ceil(total / 2))
    return along, max(1, total - along)


@dataclass
class _Edge:
    road: Road
    line: np.ndarray  # in the road's travel direction
    nodes: tuple[int, int]  # node ids at the start and the end
    lanes: dict[int, list[str]] = field(default_factory=dict)  # node -> lanes arriving there, near side first
    leaving: dict[int, list[str]] = field(default_factory=dict)  # node -> lanes leaving from there, near side first


Counts = Callable[[Road], tuple[int, int]]
Movements = Callable[[list[list[np.ndarray]], list[list[np.ndarray]], dict[tuple[int, int], list[tuple[int, int]]]],
                     set[tuple[int, int]]]


def rule_layout(sd: SDMap, side: str | None = None, counts: Counts | None = None,
                movements: Movements | None = None, turn_radius_m: float | None = None) -> HDMap:
    """The rule-based HD map of ``sd`` (module doc); ``side``: "right" or "left" [default: the city's]. Decisions made
    elsewhere (:mod:`cmtool.sample.compose`): ``counts`` gives a road's lanes (along, against its travel direction)
    [default: :func:`lane_counts`]; ``movements`` picks a junction's movements from the legal ones, given the
    centrelines of the lanes arriving from each arm and leaving into each (near side first) and the legal (arm in,
    arm out) pairs with the lanes each joins (their places in the two arms) [default: every legal one];
    ``turn_radius_m``: the tightest turn (module doc) [default: none, as the baseline]."""
    counts = counts or lane_counts
    side = side or drives_on(sd.city)
    hd = HDMap(city=sd.city or "", drives_on=side, source=f"rules:{sd.source}" if sd.source else "rules",
               meta={"rules": "cmtool.data.rules"})
    edges = _edges(sd)
    at_node = _at_nodes(edges)
    junction = _junctions(edges, at_node, turn_radius_m is not None)
    setback = _setbacks(edges, at_node, junction, counts, turn_radius_m)
    for i, e in enumerate(edges):
        if turn_radius_m is not None:
            e.line = rounded_corners(e.line, turn_radius_m + _half_width(e.road, counts))
        if not (e.nodes[0] in junction and junction[e.nodes[0]] == junction.get(e.nodes[1])
                and polyline_length(e.line) < CLUSTER_M):
            _edge_lanes(hd, i, e, setback[i], side, counts(e.road))
    for node, ends in at_node.items():
        if node not in junction and len(ends) == 2:
            _join(hd, [edges[i] for i, _ in ends], node)
    groups = defaultdict(set)
    for node, j in junction.items():
        groups[j].add(node)
    for j, nodes in groups.items():
        bend = len(nodes) == 1 and len(at_node[next(iter(nodes))]) == 2
        _connect(hd, edges, nodes, f"j{j}", side, movements, turn_radius_m, bend)
    if turn_radius_m is not None:
        _drop_tight(hd, TIGHT * turn_radius_m)
    return hd


def _edges(sd: SDMap) -> list[_Edge]:
    """The SD roads split at every node (node ids: one per distinct point)."""
    roads = [r for r in sd.roads if len(r.polyline) >= 2 and polyline_length(r.polyline) > 0.5]
    lines = [np.asarray(r.travel_polyline(), np.float64) for r in roads]
    _snap_ends(roads, lines)
    _cross(roads, lines)
    keys = [np.round(l * 100.0).astype(np.int64) for l in lines]
    count = defaultdict(int)
    for k in keys:
        for key in {tuple(p) for p in k}:
            count[key] += 1
    ids: dict[tuple, int] = {}
    edges = []
    for road, line, k in zip(roads, lines, keys):
        cuts = [0] + [v for v in range(1, len(line) - 1) if count[tuple(k[v])] >= 2] + [len(line) - 1]
        for a, b in zip(cuts[:-1], cuts[1:]):
            piece = line[a:b + 1]
            if polyline_length(piece) < 0.05:
                continue
            nodes = tuple(ids.setdefault(tuple(k[v]), len(ids)) for v in (a, b))
            edges.append(_Edge(road, piece, nodes))
    return edges


def _at_nodes(edges: list[_Edge]) -> dict[int, list[tuple[int, int]]]:
    """Node -> [(edge index, which end: 0 start / 1 end)]."""
    at_node = defaultdict(list)
    for i, e in enumerate(edges):
        for end, node in enumerate(e.nodes):
            at_node[node].append((i, end))
    return at_node


def road_junctions(sd: SDMap) -> tuple[list[_Edge], dict[int, int]]:
    """The roads of ``sd`` split where they meet, as :func:`rule_layout` splits them (each edge's ``road``, its
    ``line`` in the travel direction and its (start, end) ``nodes``), and its junctions (junction node -> junction id;
    bends are no junctions, as in the baseline): what :mod:`cmtool.metrics.decisions` counts movements through."""
    edges = _edges(sd)
    return edges, _junctions(edges, _at_nodes(edges))


def _snap_ends(roads: list[Road], lines: list[np.ndarray]) -> None:
    """A road end within SNAP_M of another road (and on no point of it) ends on it: a shared vertex."""
    geoms = [shapely.LineString(l) for l in lines]
    tree = shapely.STRtree(geoms)
    for i in range(len(lines)):
        for end in (0, -1):
            p = lines[i][end]
            for j in tree.query(shapely.Point(p), predicate="dwithin", distance=SNAP_M):
                if j == i or roads[i].layer != roads[j].layer:
                    continue
                if np.min(np.linalg.norm(lines[j] - p, axis=1)) < 0.01:
                    break
                lines[j], q = insert_vertex(lines[j], p)
                lines[i][end] = q
                break


def _cross(roads: list[Road], lines: list[np.ndarray]) -> None:
    """Roads of one layer that cross without a shared point get one where they cross."""
    geoms = np.array([shapely.LineString(l) for l in lines], dtype=object)
    a, b = shapely.STRtree(geoms).query(geoms, predicate="crosses")
    for i, j in zip(a, b):
        if i < j and roads[i].layer == roads[j].layer:
            for p in shapely.get_coordinates(shapely.intersection(shapely.LineString(lines[i]),
                                                                  shapely.LineString(lines[j]))):
                lines[i], q = insert_vertex(lines[i], p, snap=0.01)
                lines[j], _ = insert_vertex(lines[j], q, snap=0.01)


def _junctions(edges: list[_Edge], at_node: dict, bends: bool = False) -> dict[int, int]:
    """Junction node -> junction id; nodes joined by a short edge share one; ``bends``: nodes where two edges meet at a
    bend of more than ``BEND_DEG`` are junctions too, each of its own."""
    cos = math.cos(math.radians(180.0 - BEND_DEG))
    meet = {n for n, ends in at_node.items() if len(ends) >= 3}
    uf = UnionFind(n for n, ends in at_node.items() if n in meet or (
        bends and len(ends) == 2 and float(_away(edges[ends[0][0]], ends[0][1]) @ _away(edges[ends[1][0]], ends[1][1]))
        > cos))
    for e in edges:
        a, b = e.nodes
        if a in meet and b in meet and polyline_length(e.line) < CLUSTER_M:
            uf.union(a, b)
    return {n: uf.find(n) for n in uf.parent}


def lane_width(road: Road) -> float:
    """The road class's lane width (a residential lane for a class without one)."""
    return LANE_WIDTH_M.get(road.road_class, LANE_WIDTH_M["residential"])


def _half_width(road: Road, counts: Counts) -> float:
    along, against = counts(road)
    width = lane_width(road)
    return (along + against) * width / 2.0 if against else along * width / 2.0


def _setbacks(edges: list[_Edge], at_node: dict, junction: dict[int, int], counts: Counts,
              turn_radius_m: float | None) -> list[tuple[float, float]]:
    """How far each edge's lanes stop short of its start and end node (0 where no junction is); ``turn_radius_m``: as
    far as the sharpest turn there needs (module doc)."""
    widest = defaultdict(float)  # junction -> widest half road
    ends = defaultdict(list)  # junction -> its edge ends
    for node, j in junction.items():
        for i, end in at_node[node]:
            widest[j] = max(widest[j], _half_width(edges[i].road, counts))
            ends[j].append((i, end))
    need = {}
    if turn_radius_m is not None:
        for j, here in ends.items():
            turn = _sharpest_turn(edges, here)
            if len(here) == 2:  # a bend: the whole road turns about its inner side
                need[j] = (turn_radius_m + widest[j]) * math.tan(turn / 2.0)
            else:  # the near-side lane, half a lane inside the widest half road, turns at the radius
                need[j] = max(MIN_SETBACK_M, widest[j] + MARGIN_M, widest[j] - LANE_WIDTH_M["residential"] / 2.0
                              + turn_radius_m * min(math.tan(turn / 2.0), MAX_TURN_TAN))
    out = []
    for e in edges:
        back = [(need[junction[n]] if turn_radius_m is not None else max(MIN_SETBACK_M, widest[junction[n]] + MARGIN_M))
                if n in junction else 0.0 for n in e.nodes]
        length = polyline_length(e.line)
        if sum(back) > length - 1.0 and sum(back) > 0:  # a short edge: both ends give way alike
            back = [b * max(length - 1.0, 0.0) / sum(back) for b in back]
        out.append((back[0], back[1]))
    return out


def _away(e: _Edge, end: int) -> np.ndarray:
    """The unit direction from the edge's node at ``end`` (0: start, 1: end) into the edge, towards its point
    ``HEADING_M`` along."""
    line = e.line if end == 0 else e.line[::-1]
    k = min(int(np.searchsorted(arc_length(line), HEADING_M)), len(line) - 1)
    return unit(line[k] - line[0])


def _sharpest_turn(edges: list[_Edge], ends: list[tuple[int, int]]) -> float:
    """The sharpest turn (radians, under ``UTURN_DEG``) that traffic can take from one of a junction's edge ends into
    another, one-way edges only their way; 0 where there is none."""
    arrive = [(i, -_away(edges[i], end)) for i, end in ends if end == 1 or not edges[i].road.oneway]
    leave = [(i, _away(edges[i], end)) for i, end in ends if end == 0 or not edges[i].road.oneway]
    turns = [math.acos(float(np.clip(a @ b, -1.0, 1.0))) for i, a in arrive for j, b in leave if i != j]
    return max([t for t in turns if t <= math.radians(UTURN_DEG)], default=0.0)


def _cut(line: np.ndarray, start: float, end: float) -> np.ndarray | None:
    """The part of ``line`` from arc length ``start`` to ``end`` before its end, resampled every _STEP_M."""
    s = arc_length(line)
    if s[-1] - start - end < 0.5:
        return None
    ts = np.linspace(start, s[-1] - end, max(2, int(np.ceil((s[-1] - start - end) / _STEP_M)) + 1))
    return np.stack([np.interp(ts, s, line[:, 0]), np.interp(ts, s, line[:, 1])], axis=1)


def _edge_lanes(hd: HDMap, i: int, e: _Edge, back: tuple[float, float], side: str, count: tuple[int, int]) -> None:
    """The edge's lanes (``count``: along, against its travel direction), registered at its nodes near side first."""
    centre = _cut(e.line, *back)
    if centre is None:
        return
    along, against = count
    width = lane_width(e.road)
    right = 1.0 if side == "right" else -1.0  # lanes of the travel direction lie to this side (as -left offsets)
    groups = []  # (direction +1 along / -1 against, [lateral position to the left of the polyline])
    if against == 0:
        groups.append((1, [((along - 1) / 2.0 - k) * width for k in range(along)]))
    else:
        groups.append((1, [-right * (k + 0.5) * width for k in range(along)]))
        groups.append((-1, [right * (k + 0.5) * width for k in range(against)]))
    a, b = e.nodes
    for direction, lateral in groups:
        ids = []
        for k, d in enumerate(lateral):
            line = offset(centre, d) if direction > 0 else offset(centre, d)[::-1]
            lane = hd.add_lane(Lane(f"e{i}_{'f' if direction > 0 else 'b'}{k}", np.round(line, 3), width,
                                    road_id=f"e{i}"))
            ids.append((d * direction, lane.id))  # lateral position to the left of its own travel
        near_first = [lid for _, lid in sorted(ids, reverse=side == "left")]
        for x, y in zip(near_first[:-1], near_first[1:]):  # y lies farther from the near side than x
            left, right_ = (y, x) if side == "right" else (x, y)
            hd.lanes[left].right_neighbor, hd.lanes[right_].left_neighbor = right_, left
        start, end = (a, b) if direction > 0 else (b, a)
        e.leaving[start], e.lanes[end] = near_first, near_first


def _pairs(incoming: list[str], outgoing: list[str]) -> list[tuple[str, str]]:
    """Lanes paired from the near side, spread evenly when the counts differ (every lane gets one)."""
    n, m = len(incoming), len(outgoing)
    if not n or not m:
        return []
    if n >= m:
        return [(incoming[k], outgoing[round(k * (m - 1) / max(n - 1, 1))]) for k in range(n)]
    return [(incoming[round(k * (n - 1) / max(m - 1, 1))], outgoing[k]) for k in range(m)]


def _join(hd: HDMap, pair: list[_Edge], node: int) -> None:
    for e1, e2 in (pair, pair[::-1]):
        for a, b in _pairs(e1.lanes.get(node, []), e2.leaving.get(node, [])):
            hd.lanes[a].successors.append(b)
            hd.lanes[b].predecessors.append(a)


def _heading(line: np.ndarray, at_end: bool) -> np.ndarray:
    return unit(line[-1] - line[-2]) if at_end else unit(line[1] - line[0])


def _connect(hd: HDMap, edges: list[_Edge], nodes: set[int], jid: str, side: str, movements: Movements | None,
             turn_radius_m: float | None, bend: bool = False) -> None:
    """Connector lanes through one junction (module doc); ``movements``: :func:`rule_layout`'s; ``bend``: a junction
    of two edges, every lane led on."""
    arms_in = [lanes for e in edges for n, lanes in e.lanes.items() if n in nodes and lanes]
    arms_out = [lanes for e in edges for n, lanes in e.leaving.items() if n in nodes and lanes]
    near = -1.0 if side == "right" else 1.0  # the sign of a turn towards the near side
    legal = {}  # (arm in, arm out) -> lane pairs
    for a, into in enumerate(arms_in):
        h_in = _heading(hd.lanes[into[0]].centerline, True)
        for b, out in enumerate(arms_out):
            h_out = _heading(hd.lanes[out[0]].centerline, False)
            turn = math.degrees(math.atan2(h_in[0] * h_out[1] - h_in[1] * h_out[0], float(h_in @ h_out)))
            if abs(turn) > UTURN_DEG:
                continue
            if abs(turn) <= STRAIGHT_DEG or bend:
                legal[(a, b)] = _pairs(into, out)
            elif turn * near > 0:
                legal[(a, b)] = [(into[0], out[0])]
            else:
                legal[(a, b)] = [(into[-1], out[-1])]
    if movements is not None and legal:
        lines = [[[hd.lanes[k].centerline for k in arm] for arm in arms] for arms in (arms_in, arms_out)]
        places = {(a, b): [(arms_in[a].index(i), arms_out[b].index(j)) for i, j in pairs]
                  for (a, b), pairs in legal.items()}
        chosen = movements(*lines, places)
        legal = {m: pairs for m, pairs in legal.items() if m in chosen}
    count = 0
    for a, b in (pair for pairs in legal.values() for pair in pairs):
        line = np.round(_bezier(hd.lanes[a].centerline, hd.lanes[b].centerline, turn_radius_m is not None), 3)
        lane = hd.add_lane(Lane(f"{jid}_c{count}", line, hd.lanes[a].width, successors=[b], predecessors=[a],
                                is_intersection=True, intersection_id=jid))
        hd.lanes[a].successors.append(lane.id)
        hd.lanes[b].predecessors.append(lane.id)
        count += 1


def _bezier(into: np.ndarray, out: np.ndarray, to_corner: bool = False) -> np.ndarray:
    """The cubic Bézier curve from the end of ``into`` to the start of ``out``, tangent to both: handles
    ``BEZIER_REACH`` of the distance between the ends long or, ``to_corner``, ``CORNER_REACH`` of the way to the
    point where the two lanes' lines meet (where they meet ahead of both within ``CORNER_FAR`` times that distance)."""
    p0, p3 = into[-1], out[0]
    h0, h3 = _heading(into, True), _heading(out, False)
    chord = float(np.linalg.norm(p3 - p0))
    reach = (BEZIER_REACH * chord,) * 2
    if to_corner and abs(np.linalg.det(np.stack([h0, h3], axis=1))) > 0.2:  # the lines are not near parallel
        a, b = np.linalg.solve(np.stack([h0, h3], axis=1), p3 - p0)  # p0 + a h0 = p3 - b h3
        if 0 < a <= CORNER_FAR * chord and 0 < b <= CORNER_FAR * chord:
            reach = (CORNER_REACH * a, CORNER_REACH * b)
    p1, p2 = p0 + reach[0] * h0, p3 - reach[1] * h3
    t = np.linspace(0.0, 1.0, CONNECTOR_POINTS)[:, None]
    curve = (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2 + t ** 3 * p3
    return resample(resample_step(curve, 0.5), CONNECTOR_POINTS) if len(curve) > 2 else curve


def _drop_tight(hd: HDMap, radius: float) -> None:
    """Connectors tighter than ``radius`` left out, the tightest first, where both their lanes have another way on
    and in."""
    ids = [k for k, lane in hd.lanes.items() if lane.in_intersection]
    radii, _ = min_radii([np.asarray(hd.lanes[k].centerline, np.float64) for k in ids])
    for r, k in sorted(zip(radii, ids)):
        if r >= radius:
            break
        a, b = hd.lanes[hd.lanes[k].predecessors[0]], hd.lanes[hd.lanes[k].successors[0]]
        if len(a.successors) > 1 and len(b.predecessors) > 1:
            a.successors.remove(k)
            b.predecessors.remove(k)
            del hd.lanes[k]
