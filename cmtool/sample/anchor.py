"""Lane geometry from the SD map, decisions from the model: a generated lane that follows an SD road takes its shape
from that road.

Each lane, sampled every ``STEP_M``, is matched point by point to the nearest SD road piece that runs along it
(within ``ALIGN_DEG``, and within the road's reach: one lane more than its tagged or usual count per direction).
A stretch of at least ``MIN_RUN_M`` on one road, one way, is a run. The runs on one road and direction are
settled into lane slots a lane width apart (the road class's width, :data:`cmtool.data.rules.LANE_WIDTH_M`),
laid out as the rules lay them out (two-way roads: the travel direction's lanes side by side from the
centreline on the driving side; one-way roads: centred). How many slots a direction has is the ``lanes`` tag's
count where the SD map has one, else the number of distinct lanes the model drew there (runs whose offsets lie
more than ``SAME_LANE`` lane widths apart are distinct lanes): the model decides what the SD map leaves open.
A run farther than ``MAX_MOVE`` lane widths from its slot is not a lane of that road as it lies, and stays.
Each run is replaced by its slot's line, the road's own polyline offset sideways, from where the model's lane
starts along the road to where it ends (where a lane goes from one road's line to another's, ``TURN_M`` of its
own points stay between them, bent to meet both). Slots the model left empty stay empty here: the guarantee
lends the rules' lanes where a road has none (:mod:`cmtool.sample.guarantee`).

What no run covers keeps the model's points (junction connectors keep their curve; a lane no SD road explains
keeps the decoder's points), moved where it meets an anchored run so that it joins it without a step, the move
fading out along ``FADE_M``; a successor link whose one end was anchored draws the other end to it the same way.
The model's successor links are kept where their ends still meet (within ``JOIN_GAP_M``); laid ends are joined
anew by endpoint proximity.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np

from cmtool.core.geometry import arc_length, moved_start, offset, resample_step, to_frame, unit
from cmtool.data.rules import LANE_WIDTH_M, lane_counts
from cmtool.maps.lanegraph import LaneGraph, infer_successors
from cmtool.maps.neighbours import relaned
from cmtool.maps.sdmap import Road, SDMap

STEP_M = 1.0  # lanes are matched to roads at points this far apart
ROAD_STEP_M = 2.0  # road polylines are densified to this before matching and offsetting
ALIGN_DEG = 25.0  # a lane point follows a road whose direction is within this of the lane's
MIN_RUN_M = 6.0  # shorter stretches along a road keep the model's points
SAME_LANE = 0.6  # runs of one road and direction closer than this many lane widths are one lane
MAX_MOVE = 0.8  # a lane farther than this many lane widths from its slot is not anchored
MAX_LANES = 4  # lanes per direction at most, where the SD map does not say
TURN_M = 6.0  # a lane laid on one line, then another, keeps this much of its own points between them
FADE_M = 8.0  # a kept piece joined to an anchored run bends over this length
MARGIN_M = 24.0  # roads this far beyond the frame still anchor the lanes near its edge
GAP_POINTS = 3  # a lane's points matched elsewhere (or nowhere) between two stretches on one road join them
JOIN_M = 4.0  # a successor link whose ends lie farther apart is not drawn together
JOIN_GAP_M = 1.5  # a successor link whose ends still lie farther apart is dropped; anchored ends join anew


@dataclass
class _Run:
    lane: int
    first: int  # sample indices of the run in its lane, inclusive
    last: int
    piece: int
    sign: int  # +1: along the piece's polyline, -1: against it
    s: np.ndarray  # arc length on the piece of each of its samples
    offset: float  # median lateral position, metres left of the piece's polyline
    slot: float | None = None  # the lateral position it is laid at (None: not anchored)

    def trimmed(self, first: int, last: int) -> None:
        self.s = self.s[first - self.first:len(self.s) - (self.last - last)]
        self.first, self.last = first, last


def frame_roads(sd_map: SDMap, pose, frame_m: float = 64.0) -> list[Road]:
    """The roads of ``sd_map`` near the frame at ``pose`` (x, y, yaw), in the frame's metres, densified every
    ``ROAD_STEP_M``: one :class:`Road` per stretch within ``MARGIN_M`` of the frame (travel direction kept)."""
    half = frame_m / 2.0 + MARGIN_M
    out = []
    for road in sd_map.roads:
        line = to_frame(np.asarray(road.polyline, np.float64), *pose)
        lo, hi = line.min(axis=0), line.max(axis=0)
        if (lo > half).any() or (hi < -half).any() or len(line) < 2:
            continue
        line = resample_step(line, ROAD_STEP_M)
        inside = (np.abs(line) <= half).all(axis=1)
        inside |= np.r_[inside[1:], False] | np.r_[False, inside[:-1]]  # one point beyond each edge
        cuts = np.flatnonzero(np.diff(np.r_[0, inside.astype(np.int8), 0]))
        for a, b in zip(cuts[::2], cuts[1::2]):
            if b - a >= 2:
                out.append(Road(road.id, line[a:b], road.road_class, road.lanes, road.oneway, road.link, road.layer))
    return out


def anchor(graph: LaneGraph, roads: list[Road], side: str) -> LaneGraph:
    """``graph`` with its lanes along the SD ``roads`` (the frame's, :func:`frame_roads`) laid on them (module doc);
    ``side``: "right" or "left", the driving side. ``meta.anchored``: lanes laid, metres laid. A laid map's lane
    neighbours are left unrecorded: the guarantee changes it again and finds them once, at its end."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    if not lanes or not roads:
        return graph
    samples = [_samples(l) for l in lanes]
    runs = _runs(samples, roads)
    if not runs:
        return graph
    _slots(runs, roads, side)
    by_lane: dict[int, list[_Run]] = defaultdict(list)
    for run in runs:
        if run.slot is not None:
            by_lane[run.lane].append(run)
    new, anchored_end = list(lanes), {}
    for k, mine in by_lane.items():
        mine = _apart(sorted(mine, key=lambda r: r.first))
        pieces = [(r, line) for r in mine if (line := _slot_line(roads[r.piece], r.slot, r.s[0], r.s[-1], r.sign))
                  is not None]
        if pieces:
            new[k], anchored_end[(k, 0)], anchored_end[(k, 1)] = _rebuilt(samples[k], pieces)
    met = [(i, j) for i, j in graph.successors if np.linalg.norm(lanes[i][-1] - lanes[j][0]) <= JOIN_GAP_M]
    new = _joined(new, met, anchored_end)
    moved = {k for k in range(len(new)) if new[k] is not lanes[k]}
    successors = [(i, j) for i, j in graph.successors if np.linalg.norm(new[i][-1] - new[j][0]) <= JOIN_GAP_M]
    successors += [(i, j) for i, j in infer_successors(new) if i in moved or j in moved]
    metres = sum(r.last - r.first for mine in by_lane.values() for r in mine) * STEP_M
    meta = dict(graph.meta) | {"anchored": {"lanes": len(by_lane), "metres": round(metres, 1)}}
    return relaned(graph, new, successors, meta, found=False)


def _samples(line: np.ndarray) -> np.ndarray:
    return resample_step(line, STEP_M) if len(line) >= 2 else line


def _runs(samples: list[np.ndarray], roads: list[Road], reach: int | None = None) -> list[_Run]:
    """Every lane's stretches along one road piece (module doc); ``reach``: this many lane widths from each road's
    line instead of its own reach."""
    a = np.concatenate([r.polyline[:-1] for r in roads])
    b = np.concatenate([r.polyline[1:] for r in roads])
    piece = np.repeat(np.arange(len(roads)), [len(r.polyline) - 1 for r in roads])
    s0 = np.concatenate([arc_length(r.polyline)[:-1] for r in roads])
    seg = b - a
    seg_len = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    seg_dir = seg / seg_len[:, None]
    reach = np.array([_reach(r) if reach is None else reach * _width(r) for r in roads])[piece]
    runs = []
    for k, pts in enumerate(samples):
        if len(pts) < 2:
            continue
        tangent = unit(np.gradient(pts, axis=0))
        rel = pts[:, None, :] - a[None]  # (P, S, 2)
        t = np.clip(np.einsum("psk,sk->ps", rel, seg_dir), 0.0, seg_len[None])
        foot = a[None] + t[..., None] * seg_dir[None]
        dist = np.linalg.norm(pts[:, None, :] - foot, axis=2)
        along = tangent @ seg_dir.T  # (P, S) cosine of the angle between the lane and the segment
        ok = (np.abs(along) >= math.cos(math.radians(ALIGN_DEG))) & (dist <= reach[None])
        dist = np.where(ok, dist, np.inf)
        best = np.argmin(dist, axis=1)
        found = np.isfinite(dist[np.arange(len(pts)), best])
        key = _filled(np.where(found, piece[best] * 2 + (along[np.arange(len(pts)), best] < 0), -1))
        d, r = seg_dir[best], rel[np.arange(len(pts)), best]
        lateral = d[:, 0] * r[:, 1] - d[:, 1] * r[:, 0]  # left of the road
        s = s0[best] + t[np.arange(len(pts)), best]
        for first, last in _stretches(key):
            if key[first] < 0 or (last - first) * STEP_M < MIN_RUN_M:
                continue
            p, sign = int(key[first] // 2), -1 if key[first] % 2 else 1
            if roads[p].oneway and sign != (1 if roads[p].oneway == 1 else -1):
                continue  # against a one-way road: left to the guarantee
            runs.append(_Run(k, int(first), int(last), p, sign, s[first:last + 1],
                             float(np.median(lateral[first:last + 1]))))
    return runs


def _filled(key: np.ndarray) -> np.ndarray:
    """``key`` with stretches of at most ``GAP_POINTS`` between two stretches of one key given that key."""
    key = key.copy()
    spans = _stretches(key)
    for (a0, a1), (b0, b1), (c0, c1) in zip(spans, spans[1:], spans[2:]):
        if key[a0] >= 0 and key[a0] == key[c0] and b1 - b0 + 1 <= GAP_POINTS:
            key[b0:b1 + 1] = key[a0]
    return key


def _stretches(key: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each stretch of equal keys."""
    cuts = np.flatnonzero(np.diff(key)) + 1
    starts = np.r_[0, cuts]
    return list(zip(starts, np.r_[cuts - 1, len(key) - 1]))


def _width(road: Road) -> float:
    return LANE_WIDTH_M.get(road.road_class, LANE_WIDTH_M["residential"])


def _reach(road: Road) -> float:
    """How far from the road's line a lane of it may lie: one lane beyond its count per direction."""
    return (max(lane_counts(road)) + 1) * _width(road)


def _slot_offsets(road: Road, sign: int, n: int, side: str) -> np.ndarray:
    """Lateral positions (left of the piece's polyline) of ``n`` lanes running ``sign`` along it, nearest the
    centreline first (two-way) or left to right of travel (one-way), as the rules lay them."""
    w = _width(road)
    if road.oneway:
        return sign * ((n - 1) / 2.0 - np.arange(n)) * w
    right = 1.0 if side == "right" else -1.0
    return -right * sign * (np.arange(n) + 0.5) * w


def _slots(runs: list[_Run], roads: list[Road], side: str) -> None:
    """Lay each run at its slot (``run.slot``; None where none is near enough)."""
    groups: dict[tuple[int, int], list[_Run]] = defaultdict(list)
    for run in runs:
        groups[(run.piece, run.sign)].append(run)
    for (p, sign), members in groups.items():
        road = roads[p]
        place = {id(r): _outward(road, sign, r.offset, side) for r in members}
        clusters, last = [], None
        for run in sorted(members, key=lambda r: place[id(r)]):
            if last is None or place[id(run)] - last > SAME_LANE:  # distinct lanes
                clusters.append([])
            clusters[-1].append(run)
            last = place[id(run)]
        if road.lanes is not None:
            n = lane_counts(road)[0 if sign == 1 or road.oneway else 1]
        else:
            n = _drawn(road, list(place.values()), len(clusters))
        slots = _slot_offsets(road, sign, max(n, 1), side)
        places = np.array([_outward(road, sign, o, side) for o in slots])
        for k, cluster in enumerate(clusters):
            u = float(np.mean([place[id(r)] for r in cluster]))
            pick = k if road.oneway and len(clusters) == len(slots) else int(np.argmin(np.abs(places - u)))
            if abs(places[pick] - u) > MAX_MOVE:  # not a lane of this road as it lies: the model's points stand
                continue
            for run in cluster:
                run.slot = float(slots[pick])


def _drawn(road: Road, places: list[float], clusters: int) -> int:
    """How many lanes one direction of a road has as drawn: one-way roads, the distinct lanes; two-way roads, as
    many as the farthest lane from the centreline (``places``: in slot numbers, :func:`_outward`)."""
    if road.oneway:
        return clusters
    return int(np.clip(np.round(max(places)), 0, MAX_LANES - 1)) + 1


def drawn_lane_counts(graph: LaneGraph, roads: list[Road], side: str) -> dict[tuple[int, int], int]:
    """The lanes a lane graph draws along each of the frame's ``roads`` (:func:`frame_roads`), per (road index, +1
    along its polyline / -1 against it), counted as anchoring counts them where the SD map has no ``lanes`` tag
    (every road read as untagged, lanes matched up to ``MAX_LANES`` a direction out)."""
    wide = [replace(r, lanes=None) for r in roads]
    runs = _runs([_samples(np.asarray(l, np.float64)) for l in graph.lanes], wide, reach=MAX_LANES + 1) \
        if graph.lanes and roads else []
    groups: dict[tuple[int, int], list[_Run]] = defaultdict(list)
    for run in runs:
        groups[(run.piece, run.sign)].append(run)
    out = {}
    for (p, sign), members in groups.items():
        places = sorted(_outward(wide[p], sign, r.offset, side) for r in members)
        out[(p, sign)] = _drawn(wide[p], places, 1 + int(np.sum(np.diff(places) > SAME_LANE)))
    return out


def _apart(runs: list[_Run]) -> list[_Run]:
    """A lane's anchored runs (in order) trimmed so that at least ``TURN_M`` of the model's points lie between two
    that are laid on different lines, for the lane to bend from one to the other; runs trimmed away are dropped."""
    need = int(math.ceil(TURN_M / STEP_M))
    for a, b in zip(runs, runs[1:]):
        gap = b.first - a.last - 1
        if (a.piece, a.slot) != (b.piece, b.slot) and gap < need:
            cut = need - gap
            a.trimmed(a.first, a.last - cut // 2 - cut % 2)
            b.trimmed(b.first + cut // 2, b.last)
    return [r for r in runs if r.last - r.first >= 1 and len(r.s) >= 2]


def _outward(road: Road, sign: int, lateral: float, side: str) -> float:
    """A lateral position in lane widths, counted the way slots are (0 for the first slot, 1 for the next, ...)."""
    w = _width(road)
    if road.oneway:
        return -sign * lateral / w  # left to right of travel; only differences matter
    right = 1.0 if side == "right" else -1.0
    return -right * sign * lateral / w - 0.5


def _slot_line(road: Road, lateral: float, start_s: float, end_s: float, sign: int) -> np.ndarray | None:
    """The road's line offset by ``lateral`` between arc lengths ``start_s`` and ``end_s``, in the lane's
    direction ``sign``."""
    lo, hi = sorted((start_s, end_s))
    if hi - lo < 1.0:
        return None
    line = offset(road.polyline, lateral)
    s = arc_length(road.polyline)
    ts = np.linspace(lo, hi, max(2, int(math.ceil((hi - lo) / ROAD_STEP_M)) + 1))
    cut = np.stack([np.interp(ts, s, line[:, 0]), np.interp(ts, s, line[:, 1])], axis=1)
    return cut if sign > 0 else cut[::-1]


def _rebuilt(samples: np.ndarray, pieces: list[tuple[_Run, np.ndarray]]) -> tuple[np.ndarray, bool, bool]:
    """A lane's samples with each anchored run replaced by its slot line, the kept pieces around them bent to meet
    them; whether its start and its end were anchored."""
    parts, at, shift = [], 0, None  # shift: how far the run before the kept piece moved its end
    for run, line in pieces:
        parts.append(_bent(samples[at:run.first], shift, line[0] - samples[run.first]))
        parts.append(line)
        at, shift = run.last + 1, line[-1] - samples[run.last]
    parts.append(_bent(samples[at:], shift, None))
    lane = np.concatenate([p for p in parts if len(p)])
    keep = np.r_[True, np.linalg.norm(np.diff(lane, axis=0), axis=1) > 0.2]
    return lane[keep], pieces[0][0].first <= 1, pieces[-1][0].last >= len(samples) - 2


def _bent(kept: np.ndarray, start_shift, end_shift) -> np.ndarray:
    """``kept`` moved by ``start_shift`` at its start and ``end_shift`` at its end: between two runs the move goes
    linearly from one to the other; at a lane's first or last piece it fades out over ``FADE_M``."""
    if not len(kept):
        return kept
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(kept, axis=0), axis=1))]
    if start_shift is not None and end_shift is not None:
        t = (s / max(s[-1], 1e-9))[:, None]
        return kept + (1.0 - t) * start_shift + t * end_shift
    if start_shift is not None:
        return kept + np.clip(1.0 - s / FADE_M, 0.0, 1.0)[:, None] * start_shift
    if end_shift is not None:
        return kept + np.clip(1.0 - (s[-1] - s) / FADE_M, 0.0, 1.0)[:, None] * end_shift
    return kept


def _joined(lanes: list[np.ndarray], successors, fixed: dict[tuple[int, int], bool]) -> list[np.ndarray]:
    """Each successor link whose ends came apart, at most ``JOIN_M``: the end not laid on a road (``fixed``: per
    (lane, 0 start / 1 end)) drawn to the other, bending over ``FADE_M`` (both laid: left apart)."""
    lanes = list(lanes)
    for i, j in successors:
        gap = np.linalg.norm(lanes[i][-1] - lanes[j][0])
        i_fixed, j_fixed = fixed.get((i, 1), False), fixed.get((j, 0), False)
        if i == j or gap < 1e-3 or gap > JOIN_M or (i_fixed and j_fixed):
            continue
        if i_fixed or not j_fixed:
            lanes[j] = moved_start(lanes[j], lanes[i][-1], FADE_M)
        else:
            lanes[i] = moved_start(lanes[i][::-1], lanes[j][0], FADE_M)[::-1]
    return lanes
