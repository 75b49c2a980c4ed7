"""Derive an SD map from an HD map, as OpenStreetMap would draw it.

An OSM way is one polyline per road (not per lane) that runs on through intersections, tagged with
the total lane count and whether the road is one-way. We rebuild that from any :class:`HDMap`
(procedural or imported) in four steps:

1. **Carriageways**: road lanes (vehicle/bus lanes outside intersections) of one travel direction
   that belong together: linked as successor/predecessor or left/right neighbours, or lying side by
   side (heading within 30 degrees, centre distance at most the half widths + 0.75 m). Lanes with a
   ``road_id`` only join lanes of the same road. A carriageway's line is its longest successor chain
   shifted to the middle of the lanes beside it; its lane count is the most common number of lanes
   across it.
2. **Road pieces**: opposite carriageways running antiparallel with at most ``PAIR_GAP_M`` between
   their outer lanes (medians included) form one two-way piece whose line is the midline between
   them; a carriageway without a partner is a one-way piece in travel direction.
3. **Intersections**: connector lanes grouped by ``intersection_id``, or where that is missing, by
   touching geometry. Piece ends are attached to the intersections their lanes connect to.
4. **Roads**: pieces are chained through an intersection when a connector path leads from one to
   the other, the heading changes by less than ``THROUGH_MAX_DEG``, both pieces agree in lane count
   and one-way-ness, and each is the other's straightest continuation. Chain ends that stop at an
   intersection are extended to its centre, as OSM ways meet at a junction node.

Road class follows the lane count (a documented, deliberately simple rule): total lanes >= 6 ->
``primary``, 4-5 -> ``secondary``, 3 -> ``tertiary``, else ``residential``, or ``service`` when its
lanes are narrower than ``SERVICE_WIDTH_M``.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.ndimage import median_filter

from cmtool.data.hdmap import HDMap, Lane
from cmtool.data.sdmap import Road, SDMap
from cmtool.geometry import arc_length, from_frame, headings, polyline_length, resample_step, unit
from cmtool.unionfind import UnionFind

ROAD_LANE_TYPES = ("vehicle", "bus")
MINOR_CLASSES = ("residential", "service", "unclassified")
SAMPLE_M = 2.0  # spacing of carriageway samples
PAIR_GAP_M = 8.0  # widest median between two directions of one road
PARALLEL_DEG = 30.0  # heading tolerance for "side by side" and "antiparallel"
THROUGH_MAX_DEG = 35.0  # largest heading change of a road continuing through an intersection
SERVICE_WIDTH_M = 2.75
_END_REACH_M = 15.0  # a lane end this close to a piece end belongs to that end
_SEARCH_DEPTH = 8  # connector pieces followed through one intersection


@dataclass
class SDJitter:
    """Random perturbation of a derived SD map, to mimic real OSM/HD misalignment.

    ``offset_m``: translation of up to this many metres in a random direction; ``rotation_deg``:
    rotation of up to +-this about the map centre; ``drop_minor``: probability of dropping each
    minor road (residential, service, unclassified).
    """

    offset_m: float = 0.0
    rotation_deg: float = 0.0
    drop_minor: float = 0.0

    @property
    def enabled(self) -> bool:
        return self.offset_m > 0 or self.rotation_deg > 0 or self.drop_minor > 0


@dataclass
class RoadPiece:
    """A road between two intersections (or a map edge): one or two carriageways."""

    line: np.ndarray  # (N, 2); travel direction for one-way pieces
    lanes: int  # total lane count
    oneway: bool
    width: float  # mean lane width (m)
    lane_ids: list[str]
    ends: list[str | None] = field(default_factory=lambda: [None, None])  # intersection at start/end


@dataclass
class RoadNetwork:
    """Road pieces, intersection centres and the chains of pieces that make up each road."""

    pieces: list[RoadPiece]
    intersections: dict[str, np.ndarray]  # id -> centre (2,)
    chains: list[list[tuple[int, bool]]]  # per road: (piece index, traversed forward)


def derive_sd(hd: HDMap, jitter: SDJitter | None = None, seed: int = 0) -> SDMap:
    """The SD map of ``hd`` as OpenStreetMap would show it, optionally jittered (deterministic)."""
    sd = sd_from_network(road_network(hd), hd)
    if jitter is not None:
        sd = apply_jitter(sd, jitter, seed)
    return sd


def road_class(lanes: int, lane_width: float) -> str:
    """Road class from the total lane count and the mean lane width (rule in the module doc)."""
    if lanes >= 6:
        return "primary"
    if lanes >= 4:
        return "secondary"
    if lanes == 3:
        return "tertiary"
    return "service" if lane_width < SERVICE_WIDTH_M else "residential"


def sd_from_network(net: RoadNetwork, hd: HDMap) -> SDMap:
    """One SD road per chain of pieces (polylines simplified to within 0.1 m)."""
    roads = []
    for k, chain in enumerate(net.chains):
        parts, ends = [], []
        for idx, forward in chain:
            piece = net.pieces[idx]
            parts.append(piece.line if forward else piece.line[::-1])
            ends.append(piece.ends if forward else piece.ends[::-1])
        first, last = ends[0][0], ends[-1][1]
        if first is not None:
            parts.insert(0, net.intersections[first][None])
        if last is not None:
            parts.append(net.intersections[last][None])
        line = shapely.get_coordinates(shapely.simplify(shapely.LineString(_dedupe(np.concatenate(parts))), 0.1))
        pieces = [net.pieces[i] for i, _ in chain]
        lanes = pieces[0].lanes
        width = float(np.mean([p.width for p in pieces]))
        roads.append(Road(f"r{k}", line, road_class(lanes, width), min(lanes, 16), int(pieces[0].oneway)))
    return SDMap(city=hd.city, roads=roads, source=f"derived:{hd.source}" if hd.source else "derived")


def apply_jitter(sd: SDMap, jitter: SDJitter, seed: int = 0) -> SDMap:
    """Drop minor roads, rotate about the map centre and translate, all drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    direction, radius = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(0.0, 1.0) * jitter.offset_m
    angle = np.radians(rng.uniform(-1.0, 1.0) * jitter.rotation_deg)
    drop = rng.random(len(sd.roads)) < jitter.drop_minor
    kept = [r for r, d in zip(sd.roads, drop) if not (d and r.road_class in MINOR_CLASSES)]
    if not kept:
        return SDMap(sd.city, [], sd.source, dict(sd.meta))
    pts = np.concatenate([r.polyline for r in kept])
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    shift = radius * np.array([np.cos(direction), np.sin(direction)])
    roads = []
    for r in kept:
        moved = from_frame(r.polyline - centre, 0.0, 0.0, angle) + centre + shift
        roads.append(Road(r.id, moved, r.road_class, r.lanes, r.oneway))
    return SDMap(sd.city, roads, sd.source, dict(sd.meta))


# ----------------------------------------------------------------------------- the network


def road_network(hd: HDMap) -> RoadNetwork:
    """Build carriageways, road pieces, intersections and road chains from ``hd``."""
    usable = {i: l for i, l in hd.lanes.items()
              if l.lane_type in ROAD_LANE_TYPES and polyline_length(l.centerline) > 0.1}
    road = {i: l for i, l in usable.items() if not l.in_intersection}
    conn = {i: l for i, l in usable.items() if l.in_intersection}
    intersections, lane_ix = _intersections(conn)
    carriageways = [_carriageway([road[i] for i in group]) for group in _carriageway_groups(road)]
    pieces = _pair(carriageways)
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


def _pair(cws: list[_Carriageway]) -> list[RoadPiece]:
    """Pair antiparallel carriageways into two-way pieces; the rest become one-way pieces."""
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
    pieces, piece_of = [], {}
    for k, c in enumerate(cws):
        if k in absorbed or k in piece_of:
            continue
        if k in paired:
            o = cws[paired[k]]
            lanes = c.lanes + o.lanes
            line = _midline(c.line, o.line, half[k] + half[paired[k]] + PAIR_GAP_M)
            pieces.append(RoadPiece(line, lanes, False, (c.width * c.lanes + o.width * o.lanes) / lanes,
                                    c.lane_ids + o.lane_ids))
            piece_of[paired[k]] = len(pieces) - 1
        else:
            pieces.append(RoadPiece(c.line, c.lanes, True, c.width, list(c.lane_ids)))
        piece_of[k] = len(pieces) - 1
    for k, o in absorbed.items():
        pieces[piece_of[o]].lane_ids += cws[k].lane_ids
    return pieces


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
