"""Derive an SD map from an HD map, as OpenStreetMap would draw it.

An OSM way is one polyline per road (not per lane) that runs on through intersections, tagged with
the total lane count and whether the road is one-way. We rebuild that from any :class:`HDMap`
(procedural or imported) in four steps:

1. **Carriageways**: road lanes (vehicle/bus lanes outside intersections) of one travel direction
   that belong together: linked as successor/predecessor or left/right neighbours, or lying side by
   side (heading within 30 degrees, centre distance at most the half widths + 0.75 m). Lanes with a
   ``road_id`` only join lanes of the same road. Connector lanes that do not lead from a road lane to
   a road lane (a road whose lanes are all flagged as intersection lanes and that dead-ends or leaves
   the map) count as road lanes that join only each other; the turns between them and a road stay
   connectors. A carriageway's line is its longest successor chain shifted to the middle of the lanes
   beside it; its lane count is the most common number of lanes across it. Lanes leaving it (a point
   farther from the line than a lane beside its outermost lane, or partly outside it and leading only
   into or out of such lanes) are split off into carriageways of their own.
2. **Road pieces**: opposite carriageways running antiparallel with at most ``PAIR_GAP_M`` between
   their outer lanes (medians included) form one two-way piece whose line is the midline between
   them, unless the median is wider than ``DIVIDED_GAP_M``: then, as OSM maps a divided road, each
   carriageway is a one-way piece of its own (its class from the lanes of both). A carriageway
   without a partner is a one-way piece in travel direction.
3. **Intersections**: the other connector lanes grouped by ``intersection_id``, or where that is
   missing, by touching geometry. Piece ends are attached to the intersections their lanes connect to.
4. **Roads**: pieces are chained through an intersection when a connector path leads from one to
   the other, the heading changes by less than ``THROUGH_MAX_DEG``, both pieces agree in lane count
   and one-way-ness, and each is the other's straightest continuation. Roads meet at shared nodes,
   as OSM ways do: roads running on through an intersection share the point where they cross, and
   a chain that stops at an intersection ends on that crossing (or on the nearest road running
   through, or at the intersection's centre when none does).

Road class, as mappers tag it (``classes="mapped"``, the default): ``service`` when the road's lanes are narrower
than ``SERVICE_WIDTH_M``, else drawn from :data:`MAPPED_CLASSES`, the classes that real OpenStreetMap ways with the
road's lane count and one-way status carry (measured by :func:`mapped_classes`; docs/data.md), seeded by the map's
seed and the road. Where the measurement holds too few such ways, and with ``classes="lanes"`` (for tests), the class
follows the lane count by a fixed rule: total lanes >= 6 -> ``primary``, 4-5 -> ``secondary``, 3 -> ``tertiary``,
else ``residential`` (or ``service``, narrow).
"""

from __future__ import annotations

from collections import Counter, defaultdict, deque
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.ndimage import median_filter

from cmtool.core.geometry import arc_length, headings, insert_vertex, polyline_length, resample_step, unit
from cmtool.core.unionfind import UnionFind
from cmtool.data.sd_jitter import SDJitter, apply_jitter
from cmtool.maps.hdmap import HDMap, Lane
from cmtool.maps.sdmap import Road, SDMap

ROAD_LANE_TYPES = ("vehicle", "bus")
SAMPLE_M = 2.0  # spacing of carriageway samples
PAIR_GAP_M = 8.0  # widest median between two directions of one road
DIVIDED_GAP_M = 1.5  # a wider median makes a divided road: two one-way ways, as OSM maps it
PARALLEL_DEG = 30.0  # heading tolerance for "side by side" and "antiparallel"
THROUGH_MAX_DEG = 35.0  # largest heading change of a road continuing through an intersection
SERVICE_WIDTH_M = 2.75
_END_REACH_M = 15.0  # a lane end this close to a piece end belongs to that end
_SEARCH_DEPTH = 8  # connector pieces followed through one intersection


@dataclass
class RoadPiece:
    """A road between two intersections (or a map edge): one or two carriageways."""

    line: np.ndarray  # (N, 2); travel direction for one-way pieces
    lanes: int  # total lane count
    oneway: bool
    width: float  # mean lane width (m)
    lane_ids: list[str]
    ends: list[str | None] = field(default_factory=lambda: [None, None])  # intersection at start/end
    road_lanes: int = 0  # lanes of the whole road (both carriageways of a divided road); 0: ``lanes``
    pair: int | None = None  # a divided road's carriageways share this number (and so their class)


@dataclass
class RoadNetwork:
    """Road pieces, intersection centres and the chains of pieces that make up each road."""

    pieces: list[RoadPiece]
    intersections: dict[str, np.ndarray]  # id -> centre (2,)
    chains: list[list[tuple[int, bool]]]  # per road: (piece index, traversed forward)


CLASS_RULES = ("mapped", "lanes")  # how a derived road's class is chosen (module doc)
# P(class | lanes, one-way) of real OSM ways, non-link ways of drivable classes with at least MIN_WAYS ways a bin:
# mapped_classes(read_osm("../shared/data/osm/finland_test.osm.pbf")) (tests/test_sd_derive.py measures it again)
MAPPED_CLASSES = {
    (1, True): {"secondary": 0.5, "tertiary": 0.5},
    (2, False): {"residential": 0.731, "secondary": 0.018, "service": 0.205, "tertiary": 0.041,
                 "unclassified": 0.006},
    (2, True): {"secondary": 0.667, "tertiary": 0.333},
}
MIN_WAYS = 3
IMPLIED_LANES = 2  # a two-way way without a lanes tag has two lanes (OSM's default); untagged one-way ways are left out


def mapped_classes(sd: SDMap) -> dict[tuple[int, bool], dict[str, float]]:
    """The share of each class among the roads of ``sd`` (real OSM) with a lane count and one-way status: (lanes,
    one-way) -> class -> share, by number of ways, without links (a derived road is never one), for bins of at least
    ``MIN_WAYS`` ways; a two-way road without a lane tag counts as ``IMPLIED_LANES`` lanes."""
    counts: dict[tuple[int, bool], Counter] = defaultdict(Counter)
    for road in sd.roads:
        lanes = road.lanes if road.lanes is not None or road.oneway else IMPLIED_LANES
        if lanes is not None and not road.link:
            counts[lanes, bool(road.oneway)][road.road_class] += 1
    return {key: {c: round(n / sum(seen.values()), 3) for c, n in sorted(seen.items())}
            for key, seen in sorted(counts.items()) if sum(seen.values()) >= MIN_WAYS}


def derive_sd(hd: HDMap, jitter: SDJitter | None = None, seed: int = 0, classes: str = "mapped") -> SDMap:
    """The SD map of ``hd`` as OpenStreetMap would show it (road classes as ``classes`` says: module doc), optionally
    jittered (deterministic)."""
    sd = sd_from_network(road_network(hd), hd, seed, classes)
    if jitter is not None:
        sd = apply_jitter(sd, jitter, seed)
    return sd


def road_class(lanes: int, lane_width: float, oneway: bool = False, way_lanes: int | None = None,
               rng: np.random.Generator | None = None) -> str:
    """A road's class from its lane count (``lanes`` in all, ``way_lanes`` on its way: one carriageway of a divided
    road; default ``lanes``), one-way status and mean lane width: drawn with ``rng`` as mappers tag, else by the fixed
    rule (module doc)."""
    mapped = MAPPED_CLASSES.get((way_lanes or lanes, oneway)) if rng is not None else None
    if lane_width < SERVICE_WIDTH_M and lanes < 3:
        return "service"
    if mapped:
        return str(rng.choice(list(mapped), p=np.array(list(mapped.values())) / sum(mapped.values())))
    if lanes >= 6:
        return "primary"
    if lanes >= 4:
        return "secondary"
    if lanes == 3:
        return "tertiary"
    return "service" if lane_width < SERVICE_WIDTH_M else "residential"


def sd_from_network(net: RoadNetwork, hd: HDMap, seed: int = 0, classes: str = "mapped") -> SDMap:
    """One SD road per chain of pieces (polylines simplified to within 0.1 m), meeting at shared
    junction nodes (:func:`_share_nodes`), classed as ``classes`` says (module doc)."""
    if classes not in CLASS_RULES:
        raise ValueError(f"classes: expected one of {CLASS_RULES}, got {classes!r}")
    lines, ends, through = [], [], defaultdict(list)
    for k, chain in enumerate(net.chains):
        parts, piece_ends = [], []
        for idx, forward in chain:
            piece = net.pieces[idx]
            parts.append(piece.line if forward else piece.line[::-1])
            piece_ends.append(piece.ends if forward else piece.ends[::-1])
        for (_, out_of), (into, _) in zip(piece_ends[:-1], piece_ends[1:]):
            if out_of is not None and out_of == into:
                through[out_of].append(k)
        first, last = piece_ends[0][0], piece_ends[-1][1]
        if first is not None:
            parts.insert(0, net.intersections[first][None])
        if last is not None:
            parts.append(net.intersections[last][None])
        line = shapely.simplify(shapely.LineString(_dedupe(np.concatenate(parts))), 0.1)
        lines.append(shapely.get_coordinates(line))
        ends.append((first, last))
    _share_nodes(lines, ends, through, net.intersections)
    roads = []
    for k, (chain, line) in enumerate(zip(net.chains, lines)):
        pieces = [net.pieces[i] for i, _ in chain]
        lanes = pieces[0].lanes
        width = float(np.mean([p.width for p in pieces]))
        draw = [k] if pieces[0].pair is None else [len(net.chains), pieces[0].pair]  # one class for both carriageways
        rng = np.random.default_rng([seed, *draw]) if classes == "mapped" else None
        cls = road_class(pieces[0].road_lanes or lanes, width, pieces[0].oneway, lanes, rng)
        roads.append(Road(f"r{k}", line, cls, min(lanes, 16), int(pieces[0].oneway)))
    return SDMap(city=hd.city, roads=roads, source=f"derived:{hd.source}" if hd.source else "derived")


def _share_nodes(lines: list[np.ndarray], ends: list[tuple], through: dict[str, list[int]],
                 centres: dict[str, np.ndarray]) -> None:
    """Make roads meet at shared points, as OSM ways meet at nodes (``lines`` edited in place): roads
    running on through an intersection get a vertex where they cross each other, and roads ending
    there end on the crossing nearest its centre, or else on the nearest road running through. Roads
    still crossing elsewhere get a shared vertex there too."""
    for ix, centre in centres.items():
        runs = sorted(set(through.get(ix, [])))
        crossings = []
        for a, b in ((a, b) for i, a in enumerate(runs) for b in runs[i + 1:]):
            hit = shapely.intersection(shapely.LineString(lines[a]), shapely.LineString(lines[b]))
            pts = shapely.get_coordinates(hit)
            if len(pts):
                p = pts[np.argmin(np.linalg.norm(pts - centre, axis=1))]
                lines[a], p = insert_vertex(lines[a], p)
                lines[b], p = insert_vertex(lines[b], p)
                crossings.append(p)
        node = centre
        if crossings:
            node = min(crossings, key=lambda p: float(np.linalg.norm(p - centre)))
        elif runs:
            near = min(runs, key=lambda r: shapely.distance(shapely.LineString(lines[r]), shapely.Point(centre)))
            lines[near], node = insert_vertex(lines[near], centre)
        for k, (first, last) in enumerate(ends):
            if first == ix:
                lines[k][0] = node
            if last == ix:
                lines[k][-1] = node
    geoms = _linestrings(lines)
    for a, b in zip(*shapely.STRtree(geoms).query(geoms, predicate="crosses")):
        if a < b:
            for p in shapely.get_coordinates(shapely.intersection(shapely.LineString(lines[a]),
                                                                  shapely.LineString(lines[b]))):
                lines[a], p = insert_vertex(lines[a], p)
                lines[b], _ = insert_vertex(lines[b], p)


# ----------------------------------------------------------------------------- the network


def road_network(hd: HDMap, split_divided: bool = True) -> RoadNetwork:
    """Build carriageways, road pieces, intersections and road chains from ``hd``; ``split_divided``
    False keeps a divided road as one two-way piece (as the style statistics count roads)."""
    usable = {i: l for i, l in hd.lanes.items()
              if l.lane_type in ROAD_LANE_TYPES and polyline_length(l.centerline) > 0.1}
    conn = {i: l for i, l in usable.items() if l.in_intersection}
    dead = _dead_end_connectors(usable, conn)
    conn = {i: l for i, l in conn.items() if i not in dead}
    road = {i: l for i, l in usable.items() if i not in conn}
    intersections, lane_ix = _intersections(conn)
    groups = _carriageway_groups({i: l for i, l in road.items() if i not in dead})
    groups += _carriageway_groups({i: l for i, l in road.items() if i in dead})
    pieces = _pair(_carriageways(groups, road), split_divided)
    lane_piece = {lid: k for k, p in enumerate(pieces) for lid in p.lane_ids}
    _attach_ends(pieces, road, lane_ix)
    links = _through_links(pieces, road, conn, lane_piece)
    return RoadNetwork(pieces, intersections, _chains(len(pieces), links))


@dataclass
class _Carriageway:
    line: np.ndarray  # middle of the lanes, travel direction
    lanes: int
    width: float  # mean lane width
    lane_ids: list[str]
    road_id: str | None


def _dead_end_connectors(usable: dict[str, Lane], conn: dict[str, Lane]) -> set[str]:
    """Connector lanes that do not lead from a road lane to a road lane (dead ends, lanes leading out of
    the map), less the turns between a road lane and such lanes: these lanes form roads of their own."""
    road = usable.keys() - conn.keys()
    dead = set(conn) - (_reaching_road(road, conn, forward=True) & _reaching_road(road, conn, forward=False))
    turns = {i for i in dead
             if not road.isdisjoint(conn[i].predecessors) and not dead.isdisjoint(conn[i].successors)
             or not road.isdisjoint(conn[i].successors) and not dead.isdisjoint(conn[i].predecessors)}
    return dead - turns


def _reaching_road(road: set[str], conn: dict[str, Lane], forward: bool) -> set[str]:
    """Connector lanes from which a lane in ``road`` is reached through connectors, along successors
    (``forward``) or predecessors."""
    ahead, behind = ("successors", "predecessors") if forward else ("predecessors", "successors")
    found = {i for i, l in conn.items() if not road.isdisjoint(getattr(l, ahead))}
    todo = list(found)
    while todo:
        for j in getattr(conn[todo.pop()], behind):
            if j in conn and j not in found:
                found.add(j)
                todo.append(j)
    return found


def _intersections(conn: dict[str, Lane]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Intersection centres and the intersection of each connector lane."""
    uf = UnionFind(conn)
    by_id = defaultdict(list)
    for i, lane in conn.items():
        if lane.intersection_id is not None:
            by_id[lane.intersection_id].append(i)
    for ids in by_id.values():
        for i in ids[1:]:
            uf.union(ids[0], i)
    loose = [i for i, l in conn.items() if l.intersection_id is None]
    if loose:  # group connectors without an id by touching geometry
        lines = _linestrings([conn[i].centerline for i in loose])
        a, b = shapely.STRtree(lines).query(lines, predicate="dwithin", distance=1.0)
        for x, y in zip(a, b):
            uf.union(loose[x], loose[y])
    centres, lane_ix = {}, {}
    for group in uf.groups():
        ids = sorted({conn[i].intersection_id for i in group if conn[i].intersection_id is not None})
        key = ids[0] if ids else f"x{len(centres)}"
        centres[key] = np.array(shapely.MultiLineString([conn[i].centerline for i in group]).centroid.coords[0])
        lane_ix.update({i: key for i in group})
    return centres, lane_ix


def _carriageway_groups(road: dict[str, Lane]) -> list[list[str]]:
    """Road lanes of one direction that belong together (see the module doc)."""
    uf = UnionFind(road)

    def same_road(a: Lane, b: Lane) -> bool:
        return a.road_id is None or b.road_id is None or a.road_id == b.road_id

    for lane in road.values():
        for other in lane.successors:
            if other in road and same_road(lane, road[other]):
                uf.union(lane.id, other)
        for other in (lane.left_neighbor, lane.right_neighbor):
            if other in road and same_road(lane, road[other]) and _same_direction(lane, road[other]):
                uf.union(lane.id, other)
    ids = list(road)
    if len(ids) > 1:
        lines = _linestrings([road[i].centerline for i in ids])
        reach = max(l.width for l in road.values()) + 0.75
        a, b = shapely.STRtree(lines).query(lines, predicate="dwithin", distance=reach)
        keep = a < b
        a, b = a[keep], b[keep]
        side = _side_by_side(lines, np.array([road[i].width for i in ids]), a, b)
        side |= _side_by_side(lines, np.array([road[i].width for i in ids]), b, a)
        for x, y in zip(a[side], b[side]):
            if same_road(road[ids[x]], road[ids[y]]):
                uf.union(ids[x], ids[y])
    return uf.groups()


def _same_direction(a: Lane, b: Lane) -> bool:
    da, db = a.centerline[-1] - a.centerline[0], b.centerline[-1] - b.centerline[0]
    return float(da @ db) > 0.0


def _side_by_side(lines, widths, a, b) -> np.ndarray:
    """Whether the middle of line ``a[k]`` lies beside line ``b[k]`` (interior, parallel, close)."""
    if len(a) == 0:
        return np.zeros(0, dtype=bool)
    la, lb = shapely.length(lines[a]), shapely.length(lines[b])
    mid = shapely.line_interpolate_point(lines[a], 0.5 * la)
    dist = shapely.distance(mid, lines[b])
    at = shapely.line_locate_point(lines[b], mid)
    interior = (at > 0.05) & (at < lb - 0.05)
    da = _direction(lines[a], 0.5 * la)
    db = _direction(lines[b], at)
    parallel = np.sum(da * db, axis=1) > np.cos(np.radians(PARALLEL_DEG))
    return interior & parallel & (dist <= (widths[a] + widths[b]) / 2.0 + 0.75)


def _direction(lines, at) -> np.ndarray:
    """Unit tangent of each line at arc length ``at`` (finite difference over +-0.5 m)."""
    p0 = shapely.get_coordinates(shapely.line_interpolate_point(lines, np.maximum(at - 0.5, 0.0)))
    p1 = shapely.get_coordinates(shapely.line_interpolate_point(lines, at + 0.5))
    d = p1 - p0
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


def _carriageways(groups: list[list[str]], road: dict[str, Lane]) -> list[_Carriageway]:
    """One carriageway per group; lanes straying from its line are split off and grouped anew."""
    out, todo = [], deque(groups)
    while todo:
        group = todo.popleft()
        cw = _carriageway([road[i] for i in group])
        strays = _strays(cw, [road[i] for i in group])
        if 0 < len(strays) < len(group):
            todo.append([i for i in group if i not in strays])
            todo += _carriageway_groups({i: road[i] for i in group if i in strays})
        else:
            out.append(cw)
    return out


def _strays(cw: _Carriageway, lanes: list[Lane]) -> set[str]:
    """Lanes leaving the carriageway: a point farther from ``cw.line`` than a lane beside its outermost lane
    (see :func:`_side_by_side`), or lying partly outside its edge and leading only into (or coming only from)
    such lanes."""
    line = shapely.LineString(cw.line)
    half = cw.lanes * cw.width / 2.0
    far = {l.id: float(shapely.distance(shapely.points(l.centerline), line).max()) for l in lanes}
    strays = {i for i, d in far.items() if d > half + cw.width / 2.0 + 0.75}
    while True:
        more = {l.id for l in lanes if l.id not in strays and far[l.id] > half
                and (_only_into(l.successors, far, strays) or _only_into(l.predecessors, far, strays))}
        if not more:
            return strays
        strays |= more


def _only_into(links: list[str], group, strays: set[str]) -> bool:
    """Whether ``links`` name lanes of ``group`` and all of those are ``strays``."""
    inside = [i for i in links if i in group]
    return bool(inside) and all(i in strays for i in inside)


def _carriageway(lanes: list[Lane]) -> _Carriageway:
    spine = _dedupe(np.concatenate([l.centerline for l in _longest_chain(lanes)]))
    samples = resample_step(spine, SAMPLE_M) if polyline_length(spine) > 0 else spine
    h = headings(samples)
    d = np.stack([np.cos(h), np.sin(h)], axis=1)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    a = np.concatenate([l.centerline[:-1] for l in lanes])
    b = np.concatenate([l.centerline[1:] for l in lanes])
    lat, ok = _slice(samples, n, a, b)
    ok &= (np.abs(lat) < 15.0) & ((d @ unit(b - a).T) > np.cos(np.radians(PARALLEL_DEG)))
    offsets, counts = np.zeros(len(samples)), np.ones(len(samples), dtype=int)
    for m in range(len(samples)):
        lats = np.sort(lat[m, ok[m]])
        if len(lats):
            offsets[m] = (lats[0] + lats[-1]) / 2.0
            counts[m] = 1 + int(np.sum(np.diff(lats) > 1.5))
    tally = np.bincount(counts)
    count = int(len(tally) - 1 - np.argmax(tally[::-1]))  # most common, ties to the larger count
    typical = np.flatnonzero(counts == count)  # elsewhere (lane ends, pockets) the offset is held
    offsets = np.interp(np.arange(len(samples)), typical, offsets[typical])
    if len(samples) > 2:
        offsets = median_filter(offsets, size=min(11, len(samples)), mode="reflect")
    lengths = np.array([polyline_length(l.centerline) for l in lanes])
    width = float(np.average([l.width for l in lanes], weights=lengths + 1e-6))
    road_ids = {l.road_id for l in lanes}
    return _Carriageway(samples + offsets[:, None] * n, count, width, [l.id for l in lanes],
                        road_ids.pop() if len(road_ids) == 1 else None)


def _longest_chain(lanes: list[Lane]) -> list[Lane]:
    """The longest successor path among ``lanes`` (cycles broken at the first revisit); lanes with a
    neighbour count double, so the chain follows the main road rather than a merging ramp."""
    by_id = {l.id: l for l in lanes}
    weight = {l.id: 2.0 if (l.left_neighbor in by_id or l.right_neighbor in by_id) else 1.0 for l in lanes}
    succ = {l.id: [s for s in l.successors if s in by_id] for l in lanes}
    order, seen = [], set()
    for start in by_id:  # iterative depth-first post-order
        if start in seen:
            continue
        seen.add(start)
        stack = [(start, iter(succ[start]))]
        while stack:
            node, it = stack[-1]
            nxt = next((s for s in it if s not in seen), None)
            if nxt is None:
                order.append(node)
                stack.pop()
            else:
                seen.add(nxt)
                stack.append((nxt, iter(succ[nxt])))
    best, after = {}, {}
    for node in order:  # successors come first in post-order (back edges are ignored)
        length = weight[node] * polyline_length(by_id[node].centerline)
        options = [(best[s], s) for s in succ[node] if s in best]
        tail, nxt = max(options, default=(0.0, None))
        best[node], after[node] = length + tail, nxt
    node = max(by_id, key=lambda k: best[k])
    chain = []
    while node is not None and len(chain) < len(lanes):
        chain.append(by_id[node])
        node = after[node]
    return chain


def _slice(p: np.ndarray, n: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut segments ``a[k]->b[k]`` with the normal line through each point ``p[m]`` (direction
    ``n[m]``): the signed offset along the normal and whether the line crosses the segment."""
    ab = b - a
    r = a[None] - p[:, None, :]  # (M, K, 2)
    den = n[:, None, 0] * ab[None, :, 1] - n[:, None, 1] * ab[None, :, 0]  # cross(n, ab)
    safe = np.where(np.abs(den) > 1e-9, den, 1.0)
    lat = (r[..., 0] * ab[None, :, 1] - r[..., 1] * ab[None, :, 0]) / safe  # cross(r, ab) / den
    t = (r[..., 0] * n[:, None, 1] - r[..., 1] * n[:, None, 0]) / safe  # cross(r, n) / den
    return lat, (np.abs(den) > 1e-9) & (t >= 0.0) & (t <= 1.0)


def _pair(cws: list[_Carriageway], split_divided: bool = True) -> list[RoadPiece]:
    """Pair antiparallel carriageways into two-way pieces, or, across a median wider than
    ``DIVIDED_GAP_M`` (when ``split_divided``), into the two one-way pieces of a divided road; the
    rest become one-way pieces."""
    half = np.array([c.lanes * c.width / 2.0 for c in cws])
    scores = []
    if len(cws) > 1:
        lines = _linestrings([c.line for c in cws])
        a, b = shapely.STRtree(lines).query(lines, predicate="dwithin", distance=2.0 * half.max() + PAIR_GAP_M)
        for x, y in zip(a, b):
            if x < y and (cws[x].road_id is None or cws[y].road_id is None or cws[x].road_id == cws[y].road_id):
                mx = _matched(cws[x].line, cws[y].line, half[x] + half[y] + PAIR_GAP_M)
                my = _matched(cws[y].line, cws[x].line, half[x] + half[y] + PAIR_GAP_M)
                share = max(mx.mean(), my.mean())
                if share >= 0.5:
                    scores.append((-share, int(x), int(y)))
    paired, absorbed = {}, {}
    for _, x, y in sorted(scores):
        if x not in paired and y not in paired:
            paired[x], paired[y] = y, x
    for _, x, y in sorted(scores):  # a second partner that an existing pair already covers
        for k, o in ((x, y), (y, x)):
            if k not in paired and k not in absorbed and o in paired:
                if _matched(cws[k].line, cws[o].line, half[k] + half[o] + PAIR_GAP_M).mean() >= 0.7:
                    absorbed[k] = o
    divided = {k for k, o in paired.items()
               if split_divided and _median(cws[k], cws[o], half[k], half[o]) > DIVIDED_GAP_M}
    pieces, piece_of = [], {}
    for k, c in enumerate(cws):
        if (k in absorbed and absorbed[k] not in divided) or k in piece_of:
            continue
        if k in paired and k not in divided:
            o = cws[paired[k]]
            lanes = c.lanes + o.lanes
            line = _midline(c.line, o.line, half[k] + half[paired[k]] + PAIR_GAP_M)
            pieces.append(RoadPiece(line, lanes, False, (c.width * c.lanes + o.width * o.lanes) / lanes,
                                    c.lane_ids + o.lane_ids))
            piece_of[paired[k]] = len(pieces) - 1
        else:
            partner = paired.get(k, absorbed.get(k))
            road_lanes = c.lanes + (cws[partner].lanes if partner is not None else 0)
            pieces.append(RoadPiece(c.line, c.lanes, True, c.width, list(c.lane_ids), road_lanes=road_lanes,
                                    pair=None if partner is None else min(k, partner)))
        piece_of[k] = len(pieces) - 1
    for k, o in absorbed.items():
        if o not in divided:
            pieces[piece_of[o]].lane_ids += cws[k].lane_ids
    return pieces


def _median(c: _Carriageway, o: _Carriageway, half_c: float, half_o: float) -> float:
    """Typical gap (m) between the outer lanes of two opposite carriageways: the median strip."""
    ok, lat = _across(c.line, o.line, half_c + half_o + PAIR_GAP_M)
    return float(np.median(np.abs(lat[ok]))) - half_c - half_o if ok.any() else 0.0


def _across(line: np.ndarray, other: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point of ``line``: whether ``other`` runs antiparallel beside it within ``reach``, and its
    nearest signed offset along the left normal."""
    h = headings(line)
    d = np.stack([np.cos(h), np.sin(h)], axis=1)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    a, b = other[:-1], other[1:]
    lat, ok = _slice(line, n, a, b)
    ok &= ((d @ unit(b - a).T) < -np.cos(np.radians(PARALLEL_DEG))) & (np.abs(lat) <= reach)
    near = np.argmin(np.where(ok, np.abs(lat), np.inf), axis=1)
    rows = np.arange(len(line))
    return ok[rows, near], lat[rows, near]


def _matched(line: np.ndarray, other: np.ndarray, reach: float) -> np.ndarray:
    return _across(line, other, reach)[0]


def _midline(line: np.ndarray, other: np.ndarray, reach: float) -> np.ndarray:
    """Midline between ``line`` and its opposite ``other``; past ``other``'s ends the shift is held."""
    ok, lat = _across(line, other, reach)
    h = headings(line)
    shift = 0.5 * lat[:, None] * np.stack([-np.sin(h), np.cos(h)], axis=1)
    idx = np.flatnonzero(ok)
    k = np.arange(len(line))
    held = np.stack([np.interp(k, idx, shift[idx, 0]), np.interp(k, idx, shift[idx, 1])], axis=1)
    return line + held


def _attach_ends(pieces: list[RoadPiece], road: dict[str, Lane], lane_ix: dict[str, str]) -> None:
    """Set each piece's ``ends`` to the intersection its lanes connect to at that end."""
    for piece in pieces:
        votes = [Counter(), Counter()]
        for lid in piece.lane_ids:
            lane = road[lid]
            for point, links in ((lane.centerline[-1], lane.successors), (lane.centerline[0], lane.predecessors)):
                hits = [lane_ix[c] for c in links if c in lane_ix]
                if hits:
                    end, dist = _nearest_end(piece.line, point)
                    if dist <= _END_REACH_M:
                        votes[end].update(hits)
        piece.ends = [v.most_common(1)[0][0] if v else None for v in votes]


def _nearest_end(line: np.ndarray, point: np.ndarray) -> tuple[int, float]:
    d0, d1 = np.linalg.norm(line[0] - point), np.linalg.norm(line[-1] - point)
    return (0, float(d0)) if d0 <= d1 else (1, float(d1))


def _through_links(pieces, road, conn, lane_piece) -> dict[tuple[int, int], tuple[int, int]]:
    """Mutually straightest continuations (piece, end) <-> (piece, end) through intersections."""
    candidates = defaultdict(dict)
    for lid, lane in road.items():
        p = lane_piece.get(lid)
        if p is None:
            continue
        e, _ = _nearest_end(pieces[p].line, lane.centerline[-1])
        frontier, seen = list(lane.successors), set()
        for _ in range(_SEARCH_DEPTH):
            reached = []
            for s in frontier:
                if s in seen:
                    continue
                seen.add(s)
                if s in conn:
                    reached += conn[s].successors
                elif lane_piece.get(s, p) != p:
                    q = lane_piece[s]
                    f, _ = _nearest_end(pieces[q].line, road[s].centerline[0])
                    angle = _turn(pieces[p], e, pieces[q], f)
                    if angle < THROUGH_MAX_DEG and _compatible(pieces[p], e, pieces[q], f):
                        candidates[(p, e)][(q, f)] = angle
                        candidates[(q, f)][(p, e)] = angle
            frontier = reached
    best = {k: min(v, key=lambda t: (v[t], t)) for k, v in candidates.items()}
    return {k: b for k, b in best.items() if best.get(b) == k}


def _compatible(p: RoadPiece, e: int, q: RoadPiece, f: int) -> bool:
    if p.lanes != q.lanes or p.oneway != q.oneway:
        return False
    return not p.oneway or e != f  # one-way: leave by one's end, enter by the other's start


def _outward(line: np.ndarray, end: int) -> np.ndarray:
    """Unit direction leaving ``line`` at ``end`` (0 start, 1 end), over its last ~10 m."""
    pts = line if end == 1 else line[::-1]
    cum = arc_length(pts)
    k = int(np.searchsorted(cum, cum[-1] - 10.0, side="right")) - 1
    d = pts[-1] - pts[max(0, min(k, len(pts) - 2))]
    return d / max(float(np.linalg.norm(d)), 1e-9)


def _turn(p: RoadPiece, e: int, q: RoadPiece, f: int) -> float:
    """Heading change (degrees) from leaving ``p`` at ``e`` to entering ``q`` at ``f``; also checks that
    ``q`` lies ahead."""
    out, inward = _outward(p.line, e), -_outward(q.line, f)
    angle = np.degrees(np.arccos(np.clip(out @ inward, -1.0, 1.0)))
    gap = (q.line[0] if f == 0 else q.line[-1]) - (p.line[-1] if e == 1 else p.line[0])
    if np.linalg.norm(gap) > 3.0:
        ahead = np.degrees(np.arccos(np.clip(out @ gap / np.linalg.norm(gap), -1.0, 1.0)))
        angle = max(angle, ahead * THROUGH_MAX_DEG / 45.0)  # the gap may deviate up to 45 degrees
    return float(angle)


def _chains(n: int, links: dict[tuple[int, int], tuple[int, int]]) -> list[list[tuple[int, bool]]]:
    """Walk linked pieces into chains; open chains start at a free end, cycles anywhere."""
    chains, used = [], set()

    def walk(start: int, forward: bool) -> list[tuple[int, bool]]:
        chain, piece = [], start
        while piece not in used:
            used.add(piece)
            chain.append((piece, forward))
            nxt = links.get((piece, 1 if forward else 0))
            if nxt is None:
                break
            piece, forward = nxt[0], nxt[1] == 0
        return chain

    for k in range(n):
        if k not in used and ((k, 0) not in links or (k, 1) not in links):
            chains.append(walk(k, (k, 0) not in links))
    for k in range(n):
        if k not in used:
            chains.append(walk(k, True))
    return [_travel_order(c) for c in chains]


def _travel_order(chain: list[tuple[int, bool]]) -> list[tuple[int, bool]]:
    """A chain traversed backwards flipped round, so one-way roads run in travel direction."""
    if chain[0][1]:
        return chain
    return [(p, not f) for p, f in reversed(chain)]


def _linestrings(lines: list[np.ndarray]) -> np.ndarray:
    return np.array([shapely.LineString(line) for line in lines], dtype=object)


def _dedupe(points: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate points."""
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-6
    return points[keep]
