"""A lane graph made to agree with what its SD map states: lanes stop where SD roads end (:func:`trim`), lanes that
only lead into (or come from) known breaks go (:func:`prune`), and wherever a reference layout of the same roads
(the rule layout of the SD map) lets traffic go on and the graph does not, a piece of the reference is lent to the
graph, joined to the graph's lanes where it meets them (:func:`complete`).

**Trimming.** Past a dead end of the SD map (a road end that meets no other road), the parts of lanes that run on
farther than ``BEYOND_M`` beyond it, within ``BEYOND_LATERAL_M`` of the road's line and that far from every other
road, are cut off.

**Completing.** Each reference lane is followed in samples ``SAMPLE_M`` apart. A sample's *image* is the set of the
graph's lanes passing within ``NEAR_M`` of it at a heading within ``NEAR_DEG``. Traffic that follows the reference
starts on the image of its first sample (or where the traffic of a reference lane before it arrived, followed once
from each) and goes on from sample to sample: into the next image's lanes that its lanes lead into in at most
``CHAIN`` successor joins and lane changes, or on along a lane it is on while that passes within ``KEEP_M``; through
a connector (a junction's lane), from its start to its end at once. Where it finds no such lane, the graph does not
serve the reference there: the stretch is lent, from the last sample served to the next one with an image (the
whole connector). A lent end on a lane of the graph joins it (the lane is split there, the piece diverging from it
or merging into it, its end moved onto the lane with the move fading out over ``FADE_M``); a lent end at the
reference lane's own start (end) joins the lent pieces of the reference lanes before (after) it instead, where
there are any.

**Stranded traffic.** Followed lane by lane, traffic can be taken to follow a reference lane where it cannot (a turn
lane passing close to the straight-on reference lane). :func:`stranded` follows the traffic that enters the graph
at given points through the lanes it really reaches, and names the reference lanes where it gets stuck, for
:func:`complete` to lend.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import shapely
import shapely.ops
from scipy.spatial import cKDTree

from cmtool.core.geometry import moved_start, polyline_length, unit
from cmtool.core.reach import reachable_from
from cmtool.maps.hdmap import HDMap
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.neighbours import find_neighbours, relaned
from cmtool.maps.roadgraph import road_graph
from cmtool.maps.sdmap import SDMap

SAMPLE_M = 2.0  # reference lanes are followed in samples this far apart
NEAR_M = 3.0  # a graph lane this near a sample, ...
NEAR_DEG = 35.0  # ... at a heading within this angle of the reference lane's, is in the sample's image
KEEP_M = 4.5  # traffic on a graph lane stays on it while it passes this near the samples
ROUNDS = 4  # at most this many rounds over the reference lanes, until the lanes traffic reaches settle
CHAIN = 4  # traffic goes on into lanes its lanes lead into in at most this many successor joins and lane changes
FADE_M = 10.0  # a lent end moved onto a graph lane: the move fades out over this length of the piece
SPLIT_M = 2.0  # a lent end this near a graph lane's start or end, or a split, joins it there (no part is shorter)
BEYOND_M = 2.0  # lanes stop this far past a dead end of the SD map at most
BEYOND_LATERAL_M = 6.0  # ... where they run within this distance of the road's line, away from other roads
BEYOND_REACH_M = 60.0  # ... this far past it
MIN_PART_M = 1.0  # parts of a trimmed lane shorter than this are dropped


@dataclass
class _Ref:
    line: np.ndarray
    connector: bool
    before: list[int]  # reference lanes that flow into this one
    after: list[int]


@dataclass
class _Lent:
    ref: int
    first: int  # the first and last sample of the reference lane the piece runs between
    last: int
    points: np.ndarray
    start_on: tuple[int, float] | None  # the graph lane (and metres along it) the piece diverges from
    end_on: tuple[int, float] | None  # ... merges into


def complete(graph: LaneGraph, reference: HDMap, box=None, shift=None,
             entries: tuple[np.ndarray, float] | None = None) -> tuple[LaneGraph, int]:
    """``graph`` with the pieces of ``reference`` it lacks (module doc), and how many pieces were lent. ``box``
    (x0, y0, x1, y1, the reference's metres): only the reference's lanes inside it count, cut at its edge;
    ``shift``: subtracted from the reference's points to put them in the graph's metres. ``entries`` (points, a
    radius): lend only where the traffic that enters at those points is stranded (:func:`stranded`), each reference
    lane from the last sample that traffic reaches on to its end, leaving from the lane it is on there."""
    view = _View(graph, reference, box, shift)
    if not view.refs or not view.lanes:
        return graph, 0
    if entries is not None:
        lent = []
        for k, (first, leaving) in sorted(_stranded(view, *entries).items()):
            points, near = view.samples[k][0][first:], view.near(k)
            lent.append(_Lent(k, first, len(near) - 1, points, _onto(view.lines, leaving, points[0]),
                              _onto(view.lines, near[-1], points[-1])))
    else:
        reached: dict[int, tuple[frozenset, bool]] = {}  # reference lane -> the graph lanes its traffic is on at its
        # end, and whether it ends on a lent piece that joins no graph lane there
        order = _order(view.refs)
        for _ in range(ROUNDS):  # joins around loops: the lanes before come round again
            lent, before = [], dict(reached)
            for k in order:
                lent += _follow(view, k, reached)
            if reached == before:
                break
    if not lent:
        return graph, 0
    return _lend(graph, view.lanes, view.lines, view.refs, view.images, lent), len(lent)


def stranded(graph: LaneGraph, reference: HDMap, points: np.ndarray, radius: float, box=None,
             shift=None) -> dict[int, tuple[int, set[int]]]:
    """Where traffic that enters ``graph`` on a lane starting within ``radius`` of one of ``points`` cannot follow
    the reference: following the reference's lanes from those that start there, the first of each way whose start
    the traffic reaches but whose end it does not, with its last sample the traffic reaches (a connector's first;
    its start, where traffic arrives at it but reaches none of its samples) and the graph lanes it is on there."""
    view = _View(graph, reference, box, shift)
    return _stranded(view, points, radius) if view.refs and view.lanes else {}


def _stranded(view: _View, points: np.ndarray, radius: float) -> dict[int, tuple[int, set[int]]]:
    out: dict[int, tuple[int, set[int]]] = {}
    edges = [(i, j) for i in view.after for j in view.after[i]]
    for point in np.asarray(points, np.float64).reshape(-1, 2):
        starts = [k for k, line in enumerate(view.lanes) if np.linalg.norm(line[0] - point) <= radius]
        on_way = reachable_from(len(view.lanes), edges, starts)  # the lanes traffic from there reaches
        queue = [(k, set(starts)) for k, r in enumerate(view.refs) if np.linalg.norm(r.line[0] - point) <= radius]
        seen = {k for k, _ in queue}
        while queue:
            k, arriving = queue.pop()  # arriving: the lanes traffic is on where reference lane k starts
            near = view.near(k)
            if near[-1] & on_way:
                for j in view.refs[k].after:
                    if j not in seen:
                        seen.add(j)
                        queue.append((j, near[-1] & on_way))
                continue
            on = [n for n, lanes in enumerate(near) if lanes & on_way]
            first = (on[0] if view.refs[k].connector else on[-1]) if on else 0
            lanes = near[first] & on_way if on else arriving
            if lanes:
                out[k] = (first, out[k][1] | lanes if k in out and out[k][0] == first else lanes)
    return out


class _View:
    """A graph seen along a reference: the reference's lanes, the graph's lanes, their successor joins and lane
    changes (``after``), the reference lanes' samples and their images."""

    def __init__(self, graph: LaneGraph, reference: HDMap, box, shift):
        self.refs = _references(reference, box, np.zeros(2) if shift is None else np.asarray(shift, np.float64))
        self.lanes = [np.asarray(l, np.float64) for l in graph.lanes]
        self.lines = [shapely.LineString(l) for l in self.lanes]
        self.after = defaultdict(set)
        for i, j in graph.successors:
            self.after[int(i)].add(int(j))
        for i, j in graph.left_neighbors if graph.left_neighbors is not None else find_neighbours(self.lanes)[0]:
            self.after[int(i)].add(int(j))
            self.after[int(j)].add(int(i))
        self.samples = [_samples(r.line) for r in self.refs]
        self._near: dict[int, list[set[int]]] = {}
        self.images = _images(shapely.STRtree(self.lines), self.lines, self.samples) if self.refs and self.lanes \
            else []  # per reference lane and sample: lane -> its distance

    def near(self, k: int) -> list[set[int]]:
        """The image of each sample of reference lane ``k``: the lanes within ``NEAR_M``."""
        if k not in self._near:
            self._near[k] = [{j for j, d in lanes.items() if d <= NEAR_M} for lanes in self.images[k]]
        return self._near[k]


def _follow(view: _View, k: int, reached: dict) -> list[_Lent]:
    """Follow reference lane ``k`` through the graph, once from where the traffic of each reference lane before it
    is (``reached``, which gets this lane's), so that traffic from one is not taken for traffic from another: the
    pieces to lend where the graph does not lead on. Where traffic before it comes on a lent piece that joins no
    graph lane, the lent stretch starts at this lane's start, so that it goes on from that piece."""
    ref, image, points, after, lines = view.refs[k], view.images[k], view.samples[k][0], view.after, view.lines
    near = view.near(k)
    steps = [len(image) - 1] if ref.connector else list(range(1, len(image)))
    sources = {reached[r] for r in ref.before if r in reached} or {(frozenset(near[0]), False)}
    lent, ends = {}, []
    for came, loose in sorted(sources, key=lambda s: (sorted(s[0]), s[1])):
        here, n, last, piece = set(came) or near[0], 0, 0, None
        while n < len(steps):
            nxt = (_reach(after, here) & near[steps[n]]) | (here & set(image[steps[n]]))  # a lane it is on: KEEP_M
            if nxt and not (loose and n == 0):
                here, last, n = nxt, steps[n], n + 1
                continue
            m = n  # the broken stretch runs on to the first sample the graph serves again
            while m + 1 < len(steps) and not near[steps[m]]:
                m += 1
            stretch = points[last:steps[m] + 1]
            piece = _Lent(k, last, steps[m], stretch, _onto(lines, here, stretch[0]), _onto(lines, near[steps[m]],
                                                                                              stretch[-1]))
            piece = lent.setdefault((last, steps[m], piece.start_on, piece.end_on), piece)
            here = {piece.end_on[0]} if piece.end_on else set()  # the piece merges into that lane
            last, n = steps[m], m + 1
        ends.append((here, piece is not None and piece.last == len(image) - 1 and piece.end_on is None))
    reached[k] = (frozenset().union(*(e[0] for e in ends)), any(e[1] for e in ends))
    return list(lent.values())


def _references(hd: HDMap, box, shift: np.ndarray) -> list[_Ref]:
    """The reference's lanes (cut at the box's edge, their joins kept where both ends stay inside)."""
    ids = list(hd.lanes)
    index = {lid: k for k, lid in enumerate(ids)}
    area = shapely.box(*box) if box is not None else None
    refs, first_piece, last_piece = [], {}, {}
    for lid in ids:
        lane = hd.lanes[lid]
        line = np.asarray(lane.centerline, np.float64)
        pieces = [line]
        if area is not None:
            clipped = shapely.intersection(shapely.LineString(line), area)
            pieces = [shapely.get_coordinates(p) for p in getattr(clipped, "geoms", [clipped])
                      if isinstance(p, shapely.LineString) and not p.is_empty and p.length > 0.5]
        for p in pieces:
            if np.allclose(p[0], line[0]):
                first_piece[index[lid]] = len(refs)
            if np.allclose(p[-1], line[-1]):
                last_piece[index[lid]] = len(refs)
            refs.append(_Ref(p - shift, lane.in_intersection, [], []))
    for lid in ids:
        i = index[lid]
        for s in hd.lanes[lid].successors:
            j = index.get(s)
            if i in last_piece and j in first_piece:
                refs[last_piece[i]].after.append(first_piece[j])
                refs[first_piece[j]].before.append(last_piece[i])
    return refs


def _samples(line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points about ``SAMPLE_M`` apart along ``line`` (its ends included) and the unit heading at each."""
    geom = shapely.LineString(line)
    at = np.linspace(0.0, geom.length, max(2, int(np.ceil(geom.length / SAMPLE_M)) + 1))
    points = shapely.get_coordinates(shapely.line_interpolate_point(geom, at))
    ahead = shapely.get_coordinates(shapely.line_interpolate_point(geom, np.minimum(at + 0.5, geom.length)))
    behind = shapely.get_coordinates(shapely.line_interpolate_point(geom, np.maximum(at - 0.5, 0.0)))
    return points, unit(ahead - behind)


def _images(tree, lines, samples) -> list[list[dict[int, float]]]:
    """For each reference lane's samples (points, unit headings), the graph lanes passing within ``KEEP_M`` of each at a
    heading within ``NEAR_DEG`` of its heading, and their distances."""
    points = np.concatenate([p for p, _ in samples])
    headings = np.concatenate([h for _, h in samples])
    at_point, lane = tree.query(shapely.points(points), predicate="dwithin", distance=KEEP_M)
    geoms, where = np.asarray(lines, dtype=object)[lane], shapely.points(points[at_point])
    along, length = shapely.line_locate_point(geoms, where), shapely.length(geoms)
    a = shapely.get_coordinates(shapely.line_interpolate_point(geoms, np.maximum(along - 0.5, 0.0)))
    b = shapely.get_coordinates(shapely.line_interpolate_point(geoms, np.minimum(along + 0.5, length)))
    ok = np.sum(unit(b - a) * headings[at_point], axis=1) >= np.cos(np.radians(NEAR_DEG))
    flat = [{} for _ in points]
    for k, j, d in zip(at_point[ok], lane[ok], shapely.distance(geoms[ok], where[ok])):
        flat[k][int(j)] = float(d)
    bounds = np.cumsum([0] + [len(p) for p, _ in samples])
    return [flat[bounds[n]:bounds[n + 1]] for n in range(len(samples))]


def _reach(after, sources: set[int], steps: int = CHAIN) -> set[int]:
    """The lanes that ``sources`` lead into in at most ``steps`` joins (``sources`` included)."""
    frontier, seen = set(sources), set(sources)
    for _ in range(steps):
        frontier = {j for i in frontier for j in after[i]} - seen
        seen |= frontier
    return seen


def _order(refs: list[_Ref]) -> list[int]:
    """The reference lanes breadth first along their joins, from the lanes that nothing flows into (then from the
    rest: loops)."""
    order, seen = [], set()
    for root in [k for k, r in enumerate(refs) if not r.before] + list(range(len(refs))):
        if root in seen:
            continue
        seen.add(root)
        queue = [root]
        while queue:
            k = queue.pop(0)
            order.append(k)
            for j in refs[k].after:
                if j not in seen:
                    seen.add(j)
                    queue.append(j)
    return order


def _lend(graph: LaneGraph, lanes, lines, refs, images, lent: list[_Lent]) -> LaneGraph:
    """The graph with the ``lent`` pieces added, joined to each other and split into the graph's lanes."""
    ends_at = defaultdict(list)  # reference lane -> lent pieces that end at its end
    starts_at = defaultdict(list)
    for n, piece in enumerate(lent):
        if piece.last == len(images[piece.ref]) - 1:
            ends_at[piece.ref].append(n)
        if piece.first == 0:
            starts_at[piece.ref].append(n)
    joins = set()  # (piece, piece) between lent pieces
    for n, piece in enumerate(lent):
        ref = refs[piece.ref]
        ahead = [m for r in ref.after for m in starts_at[r]] if piece.last == len(images[piece.ref]) - 1 else []
        joins |= {(n, m) for m in ahead}
        if piece.first == 0 and any(ends_at[r] for r in ref.before):
            piece.start_on = None  # it goes on from the lent pieces before it
        if ahead:
            piece.end_on = None
    cuts = defaultdict(set)  # graph lane -> where it is split (metres along it)
    for n, piece in enumerate(lent):
        for end, on in (("start_on", piece.start_on), ("end_on", piece.end_on)):
            if on is None or not SPLIT_M < on[1] < lines[on[0]].length - SPLIT_M:
                continue
            near = [c for c in cuts[on[0]] if abs(c - on[1]) < SPLIT_M]
            at = near[0] if near else round(on[1], 3)  # splits this near each other are one
            cuts[on[0]].add(at)
            setattr(piece, end, (on[0], at))
    parts = {}  # graph lane -> [(from metres, to metres, index)]
    out = list(lanes)
    successors = {(int(i), int(j)) for i, j in graph.successors}
    for j, marks in cuts.items():
        bounds = [0.0, *sorted(marks), lines[j].length]
        index = [j] + list(range(len(out), len(out) + len(marks)))
        for k in range(len(index)):
            points = shapely.get_coordinates(shapely.ops.substring(lines[j], bounds[k], bounds[k + 1]))
            if k == 0:
                out[j] = points
            else:
                out.append(points)
        successors = {(index[-1] if a == j else a, b) for a, b in successors}  # what followed j follows its last part
        successors |= set(zip(index[:-1], index[1:]))
        parts[j] = list(zip(bounds[:-1], bounds[1:], index))
    base = len(out)
    for n, piece in enumerate(lent):
        points = piece.points
        if piece.start_on is not None:
            at, froms = _attach(parts, lines, successors, *piece.start_on, diverge=True)
            points = moved_start(points, at, FADE_M)
            successors |= {(f, base + n) for f in froms}
        if piece.end_on is not None:
            at, intos = _attach(parts, lines, successors, *piece.end_on, diverge=False)
            points = moved_start(points[::-1], at, FADE_M)[::-1]
            successors |= {(base + n, t) for t in intos}
        out.append(points)
    successors |= {(base + a, base + b) for a, b in joins}
    return relaned(graph, *_bypass([np.round(l, 3) for l in out], successors, base))


def _bypass(lanes: list[np.ndarray], successors: set, first: int) -> tuple[list[np.ndarray], list]:
    """Lanes from index ``first`` on shorter than ``MIN_PART_M`` (lent pieces whose ends were moved together) left
    out, the lanes before each joined to the lanes after it."""
    short = {k for k in range(first, len(lanes)) if polyline_length(lanes[k]) < MIN_PART_M}
    if not short:
        return lanes, sorted(successors)
    before, after = defaultdict(set), defaultdict(set)
    for i, j in successors:
        after[i].add(j)
        before[j].add(i)
    edges = {(i, j) for i, j in successors if i not in short and j not in short}
    edges |= {(i, j) for k in short for i in before[k] - short for j in after[k] - short}
    keep = [k for k in range(len(lanes)) if k not in short]
    new = {k: n for n, k in enumerate(keep)}
    return [lanes[k] for k in keep], sorted((new[i], new[j]) for i, j in edges)


def _onto(lines, image: set[int], point: np.ndarray) -> tuple[int, float] | None:
    """The lane of ``image`` nearest ``point`` and the metres along it nearest ``point``."""
    if not image:
        return None
    j = min(image, key=lambda k: lines[k].distance(shapely.Point(point)))
    return j, float(lines[j].project(shapely.Point(point)))


def _attach(parts, lines, successors, j: int, at: float, diverge: bool) -> tuple[np.ndarray, list[int]]:
    """Where a lent piece that diverges from (else merges into) graph lane ``j`` at ``at`` metres joins it: the point
    and the lanes it leaves from (flows into). Near the lane's own start or end it joins there, not splitting it: a
    diverge at the lane's start leaves from its predecessors, a merge at its end flows into its successors."""
    line = lines[j]
    pieces = parts.get(j, [(0.0, line.length, j)])
    first, last = pieces[0][2], pieces[-1][2]
    point = lambda v: shapely.get_coordinates(line.interpolate(v))[0]  # noqa: E731
    if at <= SPLIT_M:
        return point(0.0), ([a for a, b in successors if b == first] if diverge else [first])
    if at >= line.length - SPLIT_M:
        return point(line.length), ([last] if diverge else [b for a, b in successors if a == last])
    cut = round(at, 3)
    for lo, hi, index in pieces:
        if diverge and abs(hi - cut) < 1e-6:
            return point(hi), [index]
        if not diverge and abs(lo - cut) < 1e-6:
            return point(lo), [index]
    raise AssertionError(f"lane {j} was not split at {cut}")


def trim(graph: LaneGraph, sd: SDMap, shift=None) -> tuple[LaneGraph, int]:
    """``graph`` without the parts of lanes that run on past the dead ends of ``sd`` (module doc; ``shift``: subtracted
    from the SD map's points to put them in the graph's metres), and how many lanes were cut. A lane cut in the
    middle keeps its joins before and after at its first and last part."""
    shift = np.zeros(2) if shift is None else np.asarray(shift, np.float64)
    roads = [np.asarray(r.polyline, np.float64) - shift for r in sd.roads if len(r.polyline) >= 2]
    dead = road_graph(sd).dead_ends - shift if roads else np.zeros((0, 2))
    if not len(dead) or not graph.lanes:
        return graph, 0
    geoms = np.array([shapely.LineString(r) for r in roads], dtype=object)
    regions = []
    for d in dead:
        k = int(np.argmin(shapely.distance(geoms, shapely.Point(d))))
        road = roads[k]
        inner = road[-2] if np.linalg.norm(road[-1] - d) < np.linalg.norm(road[0] - d) else road[1]
        u = unit(d - inner)
        n = np.array([-u[1], u[0]])
        a, b = d + BEYOND_M * u, d + BEYOND_REACH_M * u
        region = shapely.Polygon([a + BEYOND_LATERAL_M * n, b + BEYOND_LATERAL_M * n, b - BEYOND_LATERAL_M * n,
                                  a - BEYOND_LATERAL_M * n])
        others = [g for j, g in enumerate(geoms) if j != k and shapely.intersects(g, region.buffer(BEYOND_LATERAL_M))]
        if others:
            region = region.difference(shapely.union_all([g.buffer(BEYOND_LATERAL_M) for g in others]))
        if not region.is_empty:
            regions.append(region)
    if not regions:
        return graph, 0
    beyond = shapely.union_all(regions)
    lanes, index, cut = [], {}, 0  # index: old lane -> (its first part, its last part)
    for i, lane in enumerate(graph.lanes):
        line = shapely.LineString(np.asarray(lane, np.float64))
        if not shapely.intersects(line, beyond):
            index[i] = (len(lanes), len(lanes))
            lanes.append(np.asarray(lane, np.float64))
            continue
        cut += 1
        kept = shapely.difference(line, beyond)
        parts = [shapely.get_coordinates(p) for p in getattr(kept, "geoms", [kept])
                 if isinstance(p, shapely.LineString) and p.length >= MIN_PART_M]
        parts = sorted(parts, key=lambda q: line.project(shapely.Point(q[0])))
        if parts:
            index[i] = (len(lanes), len(lanes) + len(parts) - 1)
            lanes += parts
    successors = set()
    for i, j in graph.successors:
        if int(i) in index and int(j) in index:
            a, b = index[int(i)][1], index[int(j)][0]
            if np.linalg.norm(lanes[a][-1] - lanes[b][0]) <= 2.0:  # still meeting where they joined
                successors.add((a, b))
    return relaned(graph, [np.round(l, 3) for l in lanes], successors), cut


def prune(graph: LaneGraph, ends: np.ndarray) -> tuple[LaneGraph, int]:
    """``graph`` without the lanes whose every way on ends at one of the points ``ends`` (a lane ending there with
    no successor), or whose every way in starts at one (a lane starting there with no predecessor): traffic on them
    could only run into such a point, or come from one. Returns the graph and the number of lanes dropped."""
    ends = np.asarray(ends, np.float64).reshape(-1, 2)
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    if not len(ends) or not lanes:
        return graph, 0
    edges = [(int(i), int(j)) for i, j in graph.successors]
    has_succ, has_pred = {i for i, _ in edges}, {j for _, j in edges}
    tree = cKDTree(ends)
    at_end = {i for i, l in enumerate(lanes) if i not in has_succ and tree.query_ball_point(l[-1], 0.01)}
    at_start = {i for i, l in enumerate(lanes) if i not in has_pred and tree.query_ball_point(l[0], 0.01)}
    back = [(j, i) for i, j in edges]
    exits = [i for i in range(len(lanes)) if i not in has_succ and i not in at_end]
    entries = [i for i in range(len(lanes)) if i not in has_pred and i not in at_start]
    gone = (reachable_from(len(lanes), back, at_end) - reachable_from(len(lanes), back, exits)) | \
        (reachable_from(len(lanes), edges, at_start) - reachable_from(len(lanes), edges, entries))
    if not gone:
        return graph, 0
    keep = [i for i in range(len(lanes)) if i not in gone]
    new = {i: k for k, i in enumerate(keep)}
    return relaned(graph, [np.round(lanes[i], 3) for i in keep],
                   [(new[i], new[j]) for i, j in edges if i in new and j in new]), len(gone)


def open_ends(graph: LaneGraph, ends: np.ndarray) -> np.ndarray:
    """The points of ``ends`` where a lane of ``graph`` ends with no successor or starts with no predecessor."""
    ends = np.asarray(ends, np.float64).reshape(-1, 2)
    if not len(ends) or not graph.lanes:
        return ends[:0]
    has_succ, has_pred = {int(i) for i, _ in graph.successors}, {int(j) for _, j in graph.successors}
    loose = [l[-1] for i, l in enumerate(graph.lanes) if i not in has_succ]
    loose += [l[0] for i, l in enumerate(graph.lanes) if i not in has_pred]
    if not loose:
        return ends[:0]
    near = cKDTree(np.asarray(loose, np.float64)).query(ends)[0] < 0.01
    return ends[near]

