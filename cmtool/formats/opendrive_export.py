"""Lane graphs as OpenDRIVE 1.6 maps (``.xodr``): east/north metres of a transverse Mercator frame at the scene origin.

Roads: lanes that are neighbours (the lane graph's ``left_neighbors`` and ``oncoming``, else found from the geometry)
and start and end abreast share a road of one lane section. Where the oncoming lanes
lie on the left, traffic is right-hand (``rule="RHT"``): one direction right of the reference line (lane ids -1, -2,
... outwards, driving along it), the oncoming one left of it (ids 1, 2, ..., driving against it). Where they lie on
the right, it is left-hand (``rule="LHT"``): ids 1, 2, ... drive along the reference line, -1, -2, ... against it.
One-way roads follow the side most oncoming pairs of the graph show (on a tie: left-hand in ``city`` "SGP"). The
reference line, written as ``line`` records, is the centre line between the two innermost opposite lanes, or the
edge of a one-way road's innermost lane (the left edge of its leftmost lane in RHT, the right edge of its rightmost
in LHT). Every lane is ``driving``, of constant width (the lane graph's, else its neighbours' spacing, else
``lane_width``), with a ``userData`` ``cmtool:lane`` holding its lane graph index. Lane links, like road links, are
along the reference line; the side of a lane tells its direction.

Links: the road ends that successor edges join (transitively) form joints. A joint of the ends of two roads where each
lane is joined to one lane is a direct road link with lane links. Every other joint belongs to a junction,
where each link must join a connecting road to a normal road: the roads linked at such joints are 2-coloured, per
connected group the colouring in which connecting road ends meet fewest other roads, so the roads leaving a fork or
entering a merge become connecting roads. Connecting roads at one joint or linked to each other share a junction;
normal roads link to it, and a normal road with both ends in one junction becomes connecting too (a reader cannot
tell which of its ends a junction's roads meet). Where no colouring exists (an odd cycle of forks and merges), the
downstream road of a normal-normal link becomes connecting too, and connecting roads may then link to each other
within their junction.

Readers such as CARLA follow a connecting road's own links (one road at each end) and keep one linked lane per lane
end, not the junction's other connections. So a connecting road is written as copies, alike but for their links,
such that every pair of a lane's predecessor and successor lanes is linked in one copy, each lane of a copy linked to
at most one lane at each end (free ends link to the road most linked there). A junction ``connection`` (contact point
on the connecting road, ``laneLink`` from the lane of the other road to the connecting road's) records each normal
road that traffic enters a copy from (the one its links name; the normal roads it touches when none enters it).

Each traffic-light line that controls a lane (:func:`~cmtool.maps.lanegraph.controlled_lanes`) becomes a dynamic ``signal`` (type
1000001, the German traffic light code used by esmini and CARLA) at the centre of that lane's start, valid for it,
facing its traffic and named by its state.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections import Counter, defaultdict
from dataclasses import dataclass, field, replace
from itertools import product

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import offset, resample
from cmtool.core.jsonio import write_text_atomic
from cmtool.core.unionfind import UnionFind
from cmtool.maps.lanegraph import controlled_lanes
from cmtool.maps.neighbours import (
    LANE_WIDTH_M,
    abreasts,
    graph_neighbours,
    lane_widths,
    same_directions,
    side_of,
)

START, END = "start", "end"
MIN_SEGMENT_M = 1e-6  # shorter reference line segments are dropped
MIN_TURN_RAD = 1e-5  # reference line points turning less are dropped


@dataclass
class _Road:
    along: list[int]  # lane indices from the reference line outwards, driving along it
    against: list[int]  # the same, driving against it
    lht: bool = False  # left-hand traffic: the lanes along the reference line lie on its left (positive ids)
    id: int = 0
    junction: int = -1
    points: np.ndarray | None = None  # the reference line, east/north metres
    links: dict = field(default_factory=dict)  # road end -> (elementType, elementId, contactPoint or None)
    signals: list = field(default_factory=list)  # (s, t, orientation, lane id, state)
    lane_links: dict = field(default_factory=lambda: defaultdict(list))  # (lane index, road end) -> linked lane ids

    def ids(self) -> dict[int, int]:
        """Lane index -> lane id."""
        sign = 1 if self.lht else -1
        return {k: sign * n for n, k in enumerate(self.along, 1)} | {k: -sign * n for n, k in enumerate(self.against, 1)}

    def runs_along(self, lane_id: int) -> bool:
        """Whether the lane of ``lane_id`` drives along the reference line."""
        return (lane_id > 0) == self.lht


def to_opendrive(graph, lat0: float, lon0: float, heading: float = 0.0, lane_width: float = LANE_WIDTH_M) -> str:
    """The OpenDRIVE 1.6 XML text of ``graph`` (a LaneGraph) with its origin at ``(lat0, lon0)`` and its forward
    axis pointing to the compass ``heading``."""
    lanes = _checked_lanes(graph.lanes)
    left, oncoming = graph_neighbours(graph)
    widths = lane_widths(lanes, left, graph.widths, lane_width)
    sides = {(i, j): side_of(lanes, i, j) for i, j in oncoming}
    pairs = left + [p for (i, j), side in sides.items() if side > 0 for p in ((i, j), (j, i))]
    right_pairs = [p for (i, j), side in sides.items() if side < 0 for p in ((i, j), (j, i))]
    roads = _roads(lanes, pairs, right_pairs, graph.city == "SGP")
    yaw = math.radians(90.0 - heading)
    to_east_north = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
    side = {}  # lane index -> (road index, lane id)
    for r, road in enumerate(roads):
        road.id = r + 1
        road.points = _straightened(_without_repeats(_reference_line(road, lanes, widths) @ to_east_north))
        side |= {k: (r, lane_id) for k, lane_id in road.ids().items()}
    links = [_ends(roads, side, i, j) for i, j in dict.fromkeys((int(i), int(j)) for i, j in graph.successors)]
    _place_lights(graph, roads, side, widths)
    junctions = _link(roads, side, links)
    return _xml(roads, junctions, widths, lat0, lon0)


def write_opendrive(graph, path: str | os.PathLike, lat0: float, lon0: float, heading: float = 0.0,
                    lane_width: float = LANE_WIDTH_M) -> None:
    write_text_atomic(path, to_opendrive(graph, lat0, lon0, heading, lane_width))


def _checked_lanes(lanes) -> list[np.ndarray]:
    """The lanes as float arrays without repeated points; an empty graph or a lane of no length is an error."""
    if len(lanes) == 0:
        raise CmtoolError("no lanes to export")
    out = []
    for k, lane in enumerate(lanes):
        lane = _without_repeats(np.asarray(lane, np.float64))
        if len(lane) < 2:
            raise CmtoolError(f"lane {k} has zero length")
        out.append(lane)
    return out


def _without_repeats(line: np.ndarray) -> np.ndarray:
    return line[np.r_[True, np.linalg.norm(np.diff(line, axis=0), axis=1) > MIN_SEGMENT_M]]


def _straightened(line: np.ndarray) -> np.ndarray:
    """``line`` without the points where it runs straight on (so that no two line records continue each other)."""
    heading = np.unwrap(np.arctan2(*np.diff(line, axis=0).T[::-1]))
    return line[np.r_[True, np.abs(np.diff(heading)) > MIN_TURN_RAD, True]]


def _roads(lanes, pairs, right_pairs, left_hand_city: bool) -> list[_Road]:
    """Lanes grouped into roads: chains of abreast same-direction neighbours (``pairs``: the lane on the left), and
    two chains whose innermost lanes are abreast oncoming neighbours on one road, the chain found first driving along
    the reference line: a right-hand road where they are on each other's left (``pairs``), else a left-hand one where
    they are on each other's right (``right_pairs``), trying the graph's side first. A chain without oncoming lanes
    takes the side that more oncoming pairs show (``left_hand_city`` decides a tie)."""
    left, right_of, oncoming, votes = {}, {}, ({}, {}), [0, 0]  # oncoming[lht]: lane -> oncoming lane on that side
    for lht, side_pairs in enumerate((pairs, right_pairs)):
        sames = same_directions(lanes, side_pairs)
        for (i, j), same, fit in zip(side_pairs, sames.tolist(), abreasts(lanes, side_pairs, sames).tolist()):
            votes[lht] += not same
            taken = left if same else oncoming[lht]
            if i == j or (lht and same) or i in taken or not fit:
                continue
            if not same:
                oncoming[lht][i] = j
            elif j not in right_of:
                left[i], right_of[j] = j, i
    graph_lht = votes[1] > votes[0] or (votes[1] == votes[0] and left_hand_city)
    chains, chain_of = [], {}
    for k in [k for k in range(len(lanes)) if k not in right_of] + list(range(len(lanes))):
        if k in chain_of:
            continue
        chain = [k]  # rightmost first
        while chain[-1] in left and left[chain[-1]] not in chain_of and left[chain[-1]] not in chain:
            chain.append(left[chain[-1]])
        chain_of |= {m: len(chains) for m in chain}
        chains.append(chain)

    def inward(c: int, lht: bool) -> list[int]:  # chain c from its lane next to oncoming traffic outwards
        return chains[c] if lht else chains[c][::-1]

    roads, placed = [], set()
    for c in range(len(chains)):
        if c in placed:
            continue
        for lht in (graph_lht, not graph_lht):
            inner = inward(c, lht)[0]
            other = chain_of.get(oncoming[lht].get(inner), c)
            if other != c and other not in placed and oncoming[lht].get(inward(other, lht)[0]) == inner:
                break
        else:
            other, lht = c, graph_lht
        placed |= {c, other}
        roads.append(_Road(inward(c, lht), inward(other, lht) if other != c else [], lht))
    return roads


def _reference_line(road: _Road, lanes, widths) -> np.ndarray:
    """The road's reference line (scene frame): between its innermost opposite lanes, else beside its first lane (on
    the left in RHT, on the right in LHT)."""
    inner = -1.0 if road.lht else 1.0  # the side of a lane along the reference line that faces oncoming traffic
    a = road.along[0]
    if not road.against:
        return offset(lanes[a], inner * 0.5 * widths[a])
    b = road.against[0]
    n = max(len(lanes[a]), len(lanes[b]))
    inner_edges = (offset(resample(lanes[a], n), inner * 0.5 * widths[a]),
                   offset(resample(lanes[b][::-1], n), -inner * 0.5 * widths[b]))
    return 0.5 * (inner_edges[0] + inner_edges[1])


def _ends(roads, side, i: int, j: int):
    """A successor edge as (the road end where lane i ends, the road end where lane j starts, i, j)."""
    (ri, ni), (rj, nj) = side[i], side[j]
    return (ri, END if roads[ri].runs_along(ni) else START), (rj, START if roads[rj].runs_along(nj) else END), i, j


def _link(roads, side, links):
    """Set the roads' links, lane links and junctions (see the module docstring), appending the copies of connecting
    roads; returns the junctions (id -> connections: (incoming road id, connecting road id, contact point,
    [(incoming lane id, connecting lane id)]))."""
    joints = UnionFind({e for a, b, _, _ in links for e in (a, b)})
    for a, b, _, _ in links:
        joints.union(a, b)
    groups = joints.groups()
    looped = {a for a, b, _, _ in links if a == b}
    used = Counter((i, a) for a, _, i, _ in links) + Counter((j, b) for _, b, _, j in links)
    fanned = {end for (_, end), n in used.items() if n > 1}  # road ends where a lane is joined to two lanes
    direct = {e for g in groups if len(g) == 2 and g[0][0] != g[1][0] and not (looped | fanned) & set(g) for e in g}
    conn = _connecting(links, direct)
    partners = defaultdict(lambda: defaultdict(list))  # road end -> partner end -> [(lane here, lane there, inflow)]
    for a, b, i, j in links:
        partners[a][b].append((i, j, False))
        if b != a:
            partners[b][a].append((j, i, True))
    junction_of = _junction_ids(conn, groups, first=0)
    met = [[{junction_of[q[0]] for q in partners.get((r, end), {}) if q[0] in conn} for end in (START, END)]
           for r in range(len(roads))]
    conn |= {r for r, (start, end) in enumerate(met) if r not in conn and start & end}  # both ends in one junction
    named = {e: max(others, key=lambda q: (len(others[q]), -q[0], q[1])) for e, others in partners.items()}
    fed = {side[j][0] for _, _, i, j in links if side[j][0] in conn and side[i][0] not in conn}
    original = list(range(len(roads)))  # road index -> the road it copies
    plans = {}  # road index -> ({road end: the partner end its links name there}, {(lane, road end): [lanes there]})
    for r in range(len(roads)):
        if r not in conn:  # an end that meets a connecting road links to its junction instead
            ends = {e: named[(r, e)] for e in (START, END)
                    if (r, e) in named and not any(q[0] in conn for q in partners[(r, e)])}
            lanes = defaultdict(list)
            for end, q in ends.items():
                for here, there, _ in partners[(r, end)][q]:
                    lanes[(here, end)].append(there)
            plans[r] = (ends, lanes)
            continue
        first, *more = _copies(roads[r], r, partners, named)
        plans[r] = first
        for plan in more:
            plans[len(roads)] = plan
            original.append(r)
            roads.append(replace(roads[r], links={}, signals=list(roads[r].signals), lane_links=defaultdict(list)))
    junction_of = _junction_ids(conn, groups, first=len(roads) + 1)
    junctions = defaultdict(list)
    for r, road in enumerate(roads):
        o, (ends, lanes) = original[r], plans[r]
        road.id, road.junction = r + 1, junction_of.get(o, -1)
        for (k, end), others in lanes.items():
            road.lane_links[(k, end)] = [side[there][1] for there in others]
        for end in (START, END):
            others = partners.get((o, end), {})
            if o not in conn and any(q[0] in conn for q in others):
                road.links[end] = ("junction", junction_of[next(q[0] for q in others if q[0] in conn)], None)
            elif end in ends:
                q = ends[end]
                road.links[end] = ("road", q[0] + 1, q[1])
                edges = [e for e in others[q] if e[1] in lanes.get((e[0], end), ())]
                if o in conn and q[0] not in conn and (any(e[2] for e in edges) or o not in fed):
                    pairs = [(side[there][1], side[here][1]) for here, there, _ in edges]
                    junctions[road.junction].append((q[0] + 1, road.id, end, pairs))
    return dict(sorted(junctions.items()))


def _copies(road: _Road, r: int, partners, named) -> list[tuple[dict, dict]]:
    """The copies connecting road ``r`` is written as, each ({road end: the partner end its links name there},
    {(lane, road end): [the one lane it links to there]}): each pair of a lane's predecessor and successor lanes is
    linked in one copy, and a lane links to one lane at each end of a copy (CARLA keeps only one). Free ends link to
    the most linked partner."""
    copies = []
    for k, lane_id in road.ids().items():
        entry, exit_ = (START, END) if road.runs_along(lane_id) else (END, START)
        ins = [(entry, q, there) for q, edges in partners.get((r, entry), {}).items()
               for here, there, inflow in edges if here == k and inflow]
        outs = [(exit_, q, there) for q, edges in partners.get((r, exit_), {}).items()
                for here, there, inflow in edges if here == k and not inflow]
        for a, b in product(ins or [None], outs or [None]):
            wants = [w for w in (a, b) if w]
            fit = next((c for c in copies if all(c[0].get(end, q) == q and c[1].get((k, end), [there]) == [there]
                                                 for end, q, there in wants)), None)
            if fit is None:
                fit = ({}, {})
                copies.append(fit)
            ends, lanes = fit
            for end, q, there in wants:
                ends[end], lanes[(k, end)] = q, [there]
    copies = copies or [({}, {})]
    for ends, lanes in copies:
        for end in (START, END):
            if (r, end) in named:
                q = ends.setdefault(end, named[(r, end)])
                for here, there, _ in partners[(r, end)][q]:
                    lanes.setdefault((here, end), [there])
    return copies


def _connecting(links, direct) -> set[int]:
    """The connecting roads: per connected group of roads linked at junction joints, the 2-colouring of least
    :func:`_cost`; then the downstream road of any normal-normal link left there."""
    adjacent = defaultdict(set)
    for a, b, _, _ in links:
        if a not in direct:
            adjacent[a[0]].add(b[0])
            adjacent[b[0]].add(a[0])
    cost = _Cost(links)
    conn: set[int] = set()
    for colours in _two_colourings(adjacent):
        conn |= min(colours, key=lambda c: cost(conn, c, colours[0] | colours[1]))
    return conn | {b[0] for a, b, _, _ in links if a not in direct and a[0] not in conn and b[0] not in conn}


def _two_colourings(adjacent):
    """For each connected group of roads: its two colour classes from a breadth-first 2-colouring."""
    colour = {}
    for start in adjacent:
        if start in colour:
            continue
        colour[start], queue = 0, [start]
        for r in queue:
            for q in sorted(adjacent[r]):
                if q not in colour:
                    colour[q] = 1 - colour[r]
                    queue.append(q)
        yield [{r for r in queue if colour[r] == c} for c in (0, 1)]


class _Cost:
    """How badly a choice of connecting roads fits OpenDRIVE: each connecting road end that meets several roads
    costs 1 (10 more when it leads into them), each link between two connecting roads 100. Called with the roads
    whose choice is open, it counts only their ends and links: the rest costs every choice alike, so the better
    choice is the same, and a map of many junctions is not scored whole once per junction."""

    def __init__(self, links):
        meets, leads = defaultdict(set), defaultdict(set)
        self.roads = [(a[0], b[0]) for a, b, _, _ in links]  # the roads each link joins
        self.links_of = defaultdict(set)  # road -> the links at its ends
        for k, (a, b, _, _) in enumerate(links):
            meets[a].add(b[0])
            meets[b].add(a[0])
            leads[a].add(b[0])
            self.links_of[a[0]].add(k)
            self.links_of[b[0]].add(k)
        self.end_cost = defaultdict(int)  # road -> what its ends cost when it connects
        for e, m in meets.items():
            self.end_cost[e[0]] += (len(m) > 1) + 10 * (len(leads.get(e, ())) > 1)

    def __call__(self, conn: set[int], more: set[int], roads: set[int]) -> int:
        """The cost of ``conn`` and ``more`` as the connecting roads, counted over the ends and links of ``roads``."""
        def connecting(r):
            return r in more or r in conn

        touching = {k for r in roads for k in self.links_of[r]}
        return (sum(self.end_cost[r] for r in roads if connecting(r))
                + 100 * sum(connecting(a) and connecting(b) for a, b in (self.roads[k] for k in touching)))


def _junction_ids(conn: set[int], joints, first: int) -> dict[int, int]:
    """Connecting road -> junction id (from ``first``): connecting roads at one joint share a junction."""
    groups = UnionFind(sorted(conn))
    for joint in joints:
        inside = sorted({e[0] for e in joint} & conn)
        for r in inside[1:]:
            groups.union(inside[0], r)
    return {r: first + n for n, group in enumerate(sorted(groups.groups(), key=min)) for r in group}


def _place_lights(graph, roads, side, widths) -> None:
    """Add a signal to the road of each lane a traffic-light line controls, at the start of that lane."""
    for state, _, k in controlled_lanes(graph):
        road, lane_id = roads[side[k][0]], side[k][1]
        along = road.runs_along(lane_id)
        s = 0.0 if along else _lengths(road.points)[1][-1]
        t = _lane_offsets(road, widths)[lane_id]
        road.signals.append((s, t, "+" if along else "-", lane_id, state))


def _lane_offsets(road: _Road, widths) -> dict[int, float]:
    """Lane id -> lateral offset of its centre from the reference line (positive to the left)."""
    ids, out = road.ids(), {}
    for lanes in (road.along, road.against):
        edge = 0.0
        for k in lanes:
            out[ids[k]] = math.copysign(edge + 0.5 * widths[k], ids[k])
            edge += widths[k]
    return out


def _lengths(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segment lengths, arc length at each point) of a polyline."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return lengths, np.r_[0.0, np.cumsum(lengths)]


def _xml(roads, junctions, widths, lat0: float, lon0: float) -> str:
    root = ET.Element("OpenDRIVE")
    header = _sub(root, "header", revMajor=1, revMinor=6, name="cmtool lane graph", vendor="cmtool")
    proj = f"+proj=tmerc +lat_0={lat0:.9f} +lon_0={lon0:.9f} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
    ET.SubElement(header, "geoReference").text = proj
    signal_ids = iter(range(len(roads) + len(junctions) + 1, 1 << 31))
    for road in roads:
        _road_xml(root, road, widths, signal_ids)
    for jid, connections in junctions.items():
        junction = _sub(root, "junction", id=jid, name=f"junction {jid}")
        for n, (incoming, connecting, contact, pairs) in enumerate(connections):
            connection = _sub(junction, "connection", id=n, incomingRoad=incoming, connectingRoad=connecting,
                              contactPoint=contact)
            for a, b in pairs:
                _sub(connection, "laneLink", **{"from": a, "to": b})
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode", xml_declaration=True)
    return text.replace(f">{proj}<", f"><![CDATA[{proj}]]><", 1) + "\n"


def _road_xml(root, road: _Road, widths, signal_ids) -> None:
    lengths, s = _lengths(road.points)
    element = _sub(root, "road", name=f"road {road.id}", length=_road_length(s[-2], lengths[-1]), id=road.id,
                   junction=road.junction, rule="LHT" if road.lht else "RHT")
    if road.links:
        link = _sub(element, "link")
        for end, tag in ((START, "predecessor"), (END, "successor")):
            if end in road.links:
                kind, ident, contact = road.links[end]
                _sub(link, tag, elementType=kind, elementId=ident, **({"contactPoint": contact} if contact else {}))
    plan = _sub(element, "planView")
    for k, (x, y) in enumerate(road.points[:-1]):
        dx, dy = road.points[k + 1] - road.points[k]
        ET.SubElement(_sub(plan, "geometry", s=s[k], x=x, y=y, hdg=math.atan2(dy, dx), length=lengths[k]), "line")
    section = _sub(_sub(element, "lanes"), "laneSection", s=0.0)
    every = sorted(road.ids().values(), reverse=True)
    for tag, ids in (("left", [n for n in every if n > 0]), ("center", [0]), ("right", [n for n in every if n < 0])):
        if ids:
            group = _sub(section, tag)
            for lane_id in ids:
                _lane_xml(group, road, lane_id, widths)
    if road.signals:
        group = _sub(element, "signals")
        for s_at, t, orientation, lane_id, state in road.signals:
            signal = _sub(group, "signal", s=s_at, t=t, id=next(signal_ids), name=f"traffic light {state}",
                          dynamic="yes", orientation=orientation, zOffset=0.0, country="DE", type="1000001",
                          subtype="-1")
            _sub(signal, "validity", fromLane=lane_id, toLane=lane_id)


def _lane_xml(group, road: _Road, lane_id: int, widths) -> None:
    if lane_id == 0:
        lane = _sub(group, "lane", id=0, type="none", level="false")
        _sub(lane, "roadMark", sOffset=0.0, type="solid", weight="standard", color="standard", width=0.12)
        return
    same_side = road.along if road.runs_along(lane_id) else road.against
    k = same_side[abs(lane_id) - 1]
    lane = _sub(group, "lane", id=lane_id, type="driving", level="false")
    ends = [(tag, end) for tag, end in (("predecessor", START), ("successor", END)) if (k, end) in road.lane_links]
    if ends:
        link = _sub(lane, "link")
        for tag, end in ends:
            for other in road.lane_links[(k, end)]:
                _sub(link, tag, id=other)
    _sub(lane, "width", sOffset=0.0, a=widths[k], b=0.0, c=0.0, d=0.0)
    outer = abs(lane_id) == len(same_side)
    _sub(lane, "roadMark", sOffset=0.0, type="solid" if outer else "broken", weight="standard", color="standard",
         width=0.12, laneChange="none" if outer else "both")
    _sub(lane, "userData", code="cmtool:lane", value=k)


def _road_length(last_s: float, last_length: float) -> float:
    """The road length to write: where its last geometry ends as the file states it, shortened by whole
    micrometres until it is shorter once read as a 32-bit float (as CARLA reads it: a road length a hair longer than
    its geometry, or a length a 32-bit float holds exactly, such as 64, makes the lookup at the end of a lane that
    leads nowhere fail, and the lane drops out of its topology)."""
    end = float(_text(last_s)) + float(_text(last_length))
    length = float(_text(end))
    while float(np.float32(length)) >= min(end, length):
        length = float(_text(length - 1e-6))
    return length


def _sub(parent, tag: str, **attrs) -> ET.Element:
    return ET.SubElement(parent, tag, {k: _text(v) for k, v in attrs.items()})


def _text(v) -> str:
    """Attribute text: numbers to 1e-6 without trailing zeros, anything else as ``str``."""
    if isinstance(v, (float, np.floating)):
        text = f"{float(v):.6f}".rstrip("0").rstrip(".")
        return "0" if text == "-0" else text
    return str(v)
