"""One lane graph of an area from the lane graphs of overlapping tiles (scene frames placed in the area,
:mod:`cmtool.data.tiles`): each tile keeps the parts of its lanes and lights that belong to it (those within the
reach of a junction tile belong to that tile, the others to the tile whose centre is nearest), and a lane cut where
two tiles' parts meet is joined to the lane of the other tile that continues it.

A lane is cut exactly where it crosses the border of two tiles' parts (found by bisection), so two tiles that drew
one lane alike cut it at nearly one point: an end that leaves a tile's part is joined to a start that enters the
other within ``JOIN_M`` and ``JOIN_DEG`` (nearest pairs first), both moved to their middle (the move fading out
along each), and the two pieces become one lane where nothing else joins there. An end left over merges into (or a
start diverges from) the nearest other lane passing within ``JOIN_M`` and ``JOIN_DEG``, split there. A cut end
still left is a :class:`Seam`: the tiles disagree there. Lanes are cut off at the edge of the area's box too (no
seams). Last, lane ends that meet lane starts (by endpoint proximity, as each tile's map finds its successors) are
joined.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import shapely
import shapely.ops
from scipy.spatial import cKDTree

from cmtool.core.geometry import from_frame, moved_start, polyline_length, resample_step, unit
from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.maps.neighbours import find_neighbours, lane_widths

JOIN_M = 3.0  # a lane cut at a seam is continued by a lane of the other tile that starts within this distance
JOIN_DEG = 45.0  # ... heading within this angle of it
FADE_M = 10.0  # the ends joined at a seam move to their middle, the move fading out over this length of each lane
MIN_PIECE_M = 2.0  # shorter pieces of a cut lane are dropped
SAMPLE_M = 0.5  # lanes are cut between samples this far apart
SPLIT_M = 2.0  # an open end joins a lane this near its start (a merge) or end (a diverge) there, else splits it
CUT_STEPS = 24  # halvings that find where a lane crosses from one tile's part into another's (0.5 m / 2^24)


@dataclass
class Seam:
    """A lane end cut between two tiles' parts that no lane of the other tile continues."""

    point: tuple[float, float]  # area metres
    tile: int  # the tile whose lane it is
    other: int  # the tile across the seam
    leaving: bool  # the lane leaves its tile's part there (else it enters it)


@dataclass
class _Piece:
    points: np.ndarray
    tile: int
    enters: int | None  # the tile it comes from across a seam (None: the lane's own start; -1: the box's edge)
    leaves: int | None  # the tile it goes on into (None: the lane's own end; -1: the box's edge)


def stitch(graphs: list[LaneGraph], tiles: list, box: tuple[float, float, float, float] | None = None,
           centre: np.ndarray | None = None) -> tuple[LaneGraph, list[Seam]]:
    """The area's lane graph (area metres; ``centre``: subtracted from every point, default the origin) from each
    tile's lane graph ``graphs[t]`` in the frame of ``tiles[t]`` (a pose: x, y, yaw), cut off at the edge of ``box``
    (x0, y0, x1, y1) when given, and the seams left open."""
    centres = np.array([(t.x, t.y) for t in tiles], np.float64).reshape(-1, 2)
    owners = _Owners(centres, np.array([getattr(t, "reach", 0.0) for t in tiles], np.float64), box)
    pieces: list[_Piece] = []
    first: dict[tuple[int, int], int] = {}  # (tile, lane) -> its first piece, when that holds the lane's start
    last: dict[tuple[int, int], int] = {}  # (tile, lane) -> its last piece, when that holds the lane's end
    lights = {"green": [], "red": []}
    for t, (graph, pose) in enumerate(zip(graphs, tiles)):
        for k, lane in enumerate(graph.lanes):
            line = from_frame(np.asarray(lane, np.float64), pose.x, pose.y, pose.yaw)
            for piece in _own_pieces(line, t, owners):
                if polyline_length(piece.points) < MIN_PIECE_M:
                    continue
                if piece.enters is None:
                    first[(t, k)] = len(pieces)
                if piece.leaves is None:
                    last[(t, k)] = len(pieces)
                pieces.append(piece)
        for state, lines in (("green", graph.green_lights), ("red", graph.red_lights)):
            for line in lines:
                line = from_frame(np.asarray(line, np.float64), pose.x, pose.y, pose.yaw)
                if owners.query(line.mean(axis=0)[None])[0] == t:
                    lights[state].append(line)
    successors = {(last[(t, i)], first[(t, j)]) for t, g in enumerate(graphs) for i, j in g.successors
                  if (t, i) in last and (t, j) in first}
    joins, open_ends = _join_seams(pieces)
    open_ends = _join_nearby(pieces, open_ends, successors, joins)
    seams = [Seam(tuple(map(float, pieces[k].points[-1 if leaving else 0])), pieces[k].tile,
                  pieces[k].leaves if leaving else pieces[k].enters, leaving) for k, leaving in open_ends]
    lanes, successors = _merge(pieces, successors, joins)
    successors |= set(infer_successors(lanes))  # ends that meet across tiles, found as each tile's own map finds them
    shift = np.zeros(2) if centre is None else np.asarray(centre, np.float64)
    lanes = [np.round(l - shift, 3) for l in lanes]
    left, oncoming = find_neighbours(lanes)
    extent = float(2 * max((np.abs(l).max() for l in lanes), default=1.0) + 2.0)
    city = next((g.city for g in graphs if g.city), None)
    graph = LaneGraph(lanes=lanes, successors=sorted(successors), left_neighbors=left, oncoming=oncoming,
                      widths=lane_widths(lanes, left).round(2).tolist(),
                      green_lights=[np.round(l - shift, 3) for l in lights["green"]],
                      red_lights=[np.round(l - shift, 3) for l in lights["red"]], city=city, frame_m=extent)
    for seam in seams:
        seam.point = (round(seam.point[0] - float(shift[0]), 3), round(seam.point[1] - float(shift[1]), 3))
    return graph, seams


class _Owners:
    """The tile a point belongs to: the junction tile whose ``reach`` holds it (the nearest, if several do), else the
    tile whose centre is nearest; -1 outside the box."""

    def __init__(self, centres: np.ndarray, reach: np.ndarray, box):
        self.centres, self.reach, self.box, self.tree = centres, reach, box, cKDTree(centres)
        self.hubs = np.flatnonzero(reach > 0)
        self.hub_tree = cKDTree(centres[self.hubs]) if len(self.hubs) else None

    def query(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, np.float64).reshape(-1, 2)
        owner = self.tree.query(points)[1]
        if self.hub_tree is not None:
            d, k = self.hub_tree.query(points)
            hub = self.hubs[k]
            owner = np.where(d <= self.reach[hub], hub, owner)
        if self.box is not None:
            x, y = points.T
            owner = np.where((x >= self.box[0]) & (x <= self.box[2]) & (y >= self.box[1]) & (y <= self.box[3]),
                             owner, -1)
        return owner

    def cut(self, p: np.ndarray, q: np.ndarray, a: int, b: int) -> np.ndarray:
        """Where the segment p-q goes from tile a's part into tile b's (either may be -1: outside the box)."""
        if a >= 0 and b >= 0:
            lo, hi = 0.0, 1.0  # the border of two tiles' parts, a line or a junction tile's circle, by bisection
            for _ in range(CUT_STEPS):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if self._nearer(p + mid * (q - p), a, b) else (lo, mid)
            return p + 0.5 * (lo + hi) * (q - p)
        lo, hi = np.array(self.box[:2]), np.array(self.box[2:])
        inside, outside = (p, q) if a >= 0 else (q, p)
        d = outside - inside
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d > 0, (hi - inside) / d, np.where(d < 0, (lo - inside) / d, np.inf))
        return inside + float(np.clip(t.min(), 0.0, 1.0)) * d

    def _nearer(self, x: np.ndarray, a: int, b: int) -> bool:
        """Whether ``x`` belongs to tile a rather than tile b."""
        da, db = (float(np.linalg.norm(x - self.centres[t])) for t in (a, b))
        held_a, held_b = da <= self.reach[a], db <= self.reach[b]
        return held_a and (not held_b or da <= db) if held_a or held_b else da <= db


def _own_pieces(line: np.ndarray, t: int, owners: _Owners) -> list[_Piece]:
    """The pieces of ``line`` (area metres) nearer tile ``t``'s centre than any other, cut where it crosses the
    line halfway between ``t``'s centre and the other tile's (or the box's edge: ``enters``/``leaves`` -1)."""
    dense = resample_step(line, SAMPLE_M) if polyline_length(line) > SAMPLE_M else line
    owner = owners.query(dense)
    mine = owner == t
    pieces, k = [], 0
    while k < len(dense):
        if not mine[k]:
            k += 1
            continue
        end = k
        while end + 1 < len(dense) and mine[end + 1]:
            end += 1
        points = [dense[k:end + 1]]
        enters = leaves = None
        if k > 0:
            enters = int(owner[k - 1])
            points.insert(0, owners.cut(dense[k - 1], dense[k], enters, t)[None])
        if end + 1 < len(dense):
            leaves = int(owner[end + 1])
            points.append(owners.cut(dense[end], dense[end + 1], t, leaves)[None])
        points = np.concatenate(points)
        repeated = np.r_[np.linalg.norm(np.diff(points, axis=0), axis=1) <= 1e-6, False]  # a cut on a sample
        pieces.append(_Piece(points[~repeated], t, enters, leaves))
        k = end + 1
    return pieces


def _join_seams(pieces: list[_Piece]) -> tuple[list[tuple[int, int]], list[tuple[int, bool]]]:
    """Pairs (piece that leaves, piece that enters) joined across seams, their ends moved to their middle; the cut
    ends left open, as (piece, whether it leaves there)."""
    out = [i for i, p in enumerate(pieces) if p.leaves is not None and p.leaves >= 0]
    into = [j for j, p in enumerate(pieces) if p.enters is not None and p.enters >= 0]
    joins = []
    if out and into:
        ends = np.array([pieces[i].points[-1] for i in out])
        starts = np.array([pieces[j].points[0] for j in into])
        end_dir = unit(np.array([pieces[i].points[-1] - pieces[i].points[-2] for i in out]))
        start_dir = unit(np.array([pieces[j].points[1] - pieces[j].points[0] for j in into]))
        candidates = []
        for a, near in enumerate(cKDTree(starts).query_ball_point(ends, JOIN_M)):
            for b in near:
                i, j = out[a], into[b]
                if pieces[i].tile != pieces[j].tile and end_dir[a] @ start_dir[b] >= np.cos(np.radians(JOIN_DEG)):
                    candidates.append((float(np.linalg.norm(ends[a] - starts[b])), i, j))
        used_out, used_in = set(), set()
        for _, i, j in sorted(candidates):
            if i not in used_out and j not in used_in:
                used_out.add(i)
                used_in.add(j)
                joins.append((i, j))
                middle = 0.5 * (pieces[i].points[-1] + pieces[j].points[0])
                pieces[i].points = moved_start(pieces[i].points[::-1], middle, FADE_M)[::-1]
                pieces[j].points = moved_start(pieces[j].points, middle, FADE_M)
    joined_out, joined_in = {i for i, _ in joins}, {j for _, j in joins}
    return joins, [(i, True) for i in out if i not in joined_out] + [(j, False) for j in into if j not in joined_in]


def _join_nearby(pieces: list[_Piece], open_ends: list[tuple[int, bool]], successors: set, joins: list) -> list:
    """Join each cut end that no cut end of the other tile continues to the nearest other lane passing within
    ``JOIN_M`` at a heading within ``JOIN_DEG`` (nearest first): a leaving end merges into it, an entering start
    diverges from it; that lane is split there (its parts appended to ``pieces``, the edges of ``successors`` and
    ``joins`` that leave its end moved to its last part). Returns the ends still open."""
    if not open_ends:
        return []
    lines = [shapely.LineString(p.points) for p in pieces]
    tree = shapely.STRtree(lines)
    candidates = []
    for k, leaving in open_ends:
        end, inner = (pieces[k].points[-1], pieces[k].points[-2]) if leaving else (pieces[k].points[0],
                                                                                    pieces[k].points[1])
        heading = unit((end - inner) if leaving else (inner - end))
        for j in tree.query(shapely.Point(end), predicate="dwithin", distance=JOIN_M):
            if j == k:
                continue
            at = float(lines[j].project(shapely.Point(end)))
            a, b = (shapely.get_coordinates(lines[j].interpolate(v))[0]
                    for v in (max(at - 0.5, 0.0), min(at + 0.5, lines[j].length)))
            inside = at < lines[j].length - SPLIT_M if leaving else at > SPLIT_M  # not merging where it ends, ...
            if inside and unit(b - a) @ heading >= np.cos(np.radians(JOIN_DEG)):
                candidates.append((float(lines[j].distance(shapely.Point(end))), k, leaving, int(j), at))
    done, cuts = set(), defaultdict(list)  # cuts: piece -> [(where along it, the open end's piece, leaving)]
    for _, k, leaving, j, at in sorted(candidates):
        if k not in done:
            done.add(k)
            cuts[j].append((at, k, leaving))
    parts, splits = {}, {}  # piece -> its parts in order; piece -> where it was split (metres along it)
    for j, marks in cuts.items():
        splits[j] = sorted({round(at, 3) for at, _, _ in marks if SPLIT_M < at < lines[j].length - SPLIT_M})
        parts[j] = [j] + list(range(len(pieces), len(pieces) + len(splits[j])))
        bounds = [0.0, *splits[j], lines[j].length]
        for n, part in enumerate(parts[j]):
            points = shapely.get_coordinates(shapely.ops.substring(lines[j], bounds[n], bounds[n + 1]))
            if part == j:
                pieces[j].points = points
            else:
                pieces.append(_Piece(points, pieces[j].tile, None, None))
        pieces[j].leaves, pieces[parts[j][-1]].leaves = None, pieces[j].leaves
        _move_tail(successors, joins, j, parts[j][-1])
        successors |= set(zip(parts[j][:-1], parts[j][1:]))
    for j, marks in cuts.items():
        for at, k, leaving in marks:
            if round(at, 3) in splits[j]:  # merge into the part that begins there, diverge from the one that ends there
                n = splits[j].index(round(at, 3))
                here = parts[j][n + 1] if leaving else parts[j][n]
            else:  # at the piece's start (a merge) or end (a diverge)
                here = parts[j][0] if leaving else parts[j][-1]
            if leaving:
                k = parts.get(k, [k])[-1]
                pieces[k].points = moved_start(pieces[k].points[::-1], pieces[here].points[0], FADE_M)[::-1]
                successors.add((k, here))
            else:
                pieces[k].points = moved_start(pieces[k].points, pieces[here].points[-1], FADE_M)
                successors.add((here, k))
    return [(parts.get(k, [k])[-1] if leaving else k, leaving) for k, leaving in open_ends if k not in done]


def _move_tail(successors: set, joins: list, old: int, new: int) -> None:
    """Edges that leave piece ``old``'s end leave ``new``'s (its last part) instead."""
    for edge in [e for e in successors if e[0] == old]:
        successors.discard(edge)
        successors.add((new, edge[1]))
    joins[:] = [(new if a == old else a, b) for a, b in joins]


def _merge(pieces: list[_Piece], successors: set, joins: list) -> tuple[list[np.ndarray], set]:
    """Pieces joined across a seam become one lane where nothing else joins there (the one leaves only into the
    other, which nothing else enters); returns the lanes and their successor edges."""
    edges = set(successors) | set(joins)
    outs, ins = defaultdict(int), defaultdict(int)
    for i, j in edges:
        outs[i] += 1
        ins[j] += 1
    after = {i: j for i, j in joins if outs[i] == 1 and ins[j] == 1 and i != j}
    before = {j: i for i, j in after.items()}
    lanes, lane_of = [], {}
    for start in [k for k in range(len(pieces)) if k not in before] + list(range(len(pieces))):
        if start in lane_of:
            continue
        chain = [start]
        while chain[-1] in after and after[chain[-1]] not in lane_of and after[chain[-1]] != start:
            chain.append(after[chain[-1]])
        for k in chain:
            lane_of[k] = len(lanes)
        lanes.append(np.concatenate([pieces[chain[0]].points] + [pieces[k].points[1:] for k in chain[1:]]))
    return lanes, {(lane_of[i], lane_of[j]) for i, j in edges if lane_of[i] != lane_of[j]}
