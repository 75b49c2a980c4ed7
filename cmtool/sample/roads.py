"""The SD roads of a frame, and what a lane graph draws along them.

A lane, sampled every ``STEP_M``, is matched point by point to the nearest SD road segment that runs along it
(within ``ALIGN_DEG`` and within reach of the road's line); a stretch of at least ``MIN_RUN_M`` on one road, one way,
is a run. How many lanes a direction of a road has as drawn: on one-way roads the distinct runs (lateral positions
more than ``SAME_LANE`` lane widths apart), on two-way roads as many as the farthest run from the centreline, at most
``MAX_LANES``. :mod:`cmtool.sample.compose` takes the model's lane counts from it, ``cmtool eval`` the truth's and
the model's.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import replace

import numpy as np
import shapely

from cmtool.core.geometry import to_frame, unit
from cmtool.data.rules import lane_counts, lane_width
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.lanes import resampled

STEP_M = 1.0  # lanes are matched to roads at points this far apart
ALIGN_DEG = 25.0  # a lane point follows a road whose direction is within this of the lane's
MIN_RUN_M = 6.0  # shorter stretches along a road are not counted
SAME_LANE = 0.6  # runs of one road and direction closer than this many lane widths are one lane
MAX_LANES = 4  # lanes per direction at most
GAP_POINTS = 3  # a lane's points matched elsewhere (or nowhere) between two stretches on one road join them
MARGIN_M = 24.0  # roads this far beyond the frame are the frame's too (junctions just outside it shape its lanes)


def frame_roads(sd_map: SDMap, pose, frame_m: float = 64.0) -> list[Road]:
    """The roads of ``sd_map`` within ``MARGIN_M`` of the frame at ``pose`` (x, y, yaw), in the frame's metres: one
    :class:`Road` per piece of a road inside that square, its vertices (shared points where roads meet) kept and its
    travel direction too."""
    half = frame_m / 2.0 + MARGIN_M
    out = []
    for road in sd_map.roads:
        line = to_frame(np.asarray(road.polyline, np.float64), *pose)
        if len(line) < 2 or (line.min(axis=0) > half).any() or (line.max(axis=0) < -half).any():
            continue
        whole = shapely.LineString(line)
        for part in shapely.get_parts(shapely.clip_by_rect(whole, -half, -half, half, half)):
            if shapely.get_type_id(part) != 1 or part.length < 0.5:
                continue
            piece = shapely.get_coordinates(part)
            if whole.project(shapely.Point(piece[0])) > whole.project(shapely.Point(piece[-1])):
                piece = piece[::-1]
            out.append(Road(road.id, piece, road.road_class, road.lanes, road.oneway, road.link, road.layer))
    return out


def road_reach(road: Road) -> float:
    """How far from a road's line a lane of it may lie: one lane beyond its count per direction."""
    return (max(lane_counts(road)) + 1) * lane_width(road)


def drawn_lane_counts(graph: LaneGraph, roads: list[Road], side: str) -> dict[tuple[int, int], int]:
    """The lanes a lane graph draws along each of the frame's ``roads`` (:func:`frame_roads`), per (road index, +1
    along its polyline / -1 against it) (module doc); lanes up to ``MAX_LANES`` a direction out are matched."""
    wide = [replace(r, lanes=None) for r in roads]
    runs = _runs(resampled([np.asarray(l, np.float64) for l in graph.lanes], STEP_M), wide) \
        if graph.lanes and roads else []
    groups: dict[tuple[int, int], list[float]] = defaultdict(list)
    for p, sign, lateral in runs:
        groups[(p, sign)].append(_outward(wide[p], sign, lateral, side))
    out = {}
    for (p, sign), places in groups.items():
        places = sorted(places)
        if wide[p].oneway:
            out[(p, sign)] = 1 + int(np.sum(np.diff(places) > SAME_LANE))
        else:
            out[(p, sign)] = int(np.clip(np.round(places[-1]), 0, MAX_LANES - 1)) + 1
    return out


def _runs(samples: list[np.ndarray], roads: list[Road]) -> list[tuple[int, int, float]]:
    """Every lane's stretches along one road (module doc) as (road index, +1 along its polyline / -1 against it,
    median lateral position left of the road's line); stretches against a one-way road are left out."""
    a = np.concatenate([r.polyline[:-1] for r in roads])
    b = np.concatenate([r.polyline[1:] for r in roads])
    piece = np.repeat(np.arange(len(roads)), [len(r.polyline) - 1 for r in roads])
    seg = b - a
    seg_len = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    seg_dir = seg / seg_len[:, None]
    reach = np.array([(MAX_LANES + 1) * lane_width(r) for r in roads])[piece]
    cos = math.cos(math.radians(ALIGN_DEG))
    runs = []
    for pts in samples:
        if len(pts) < 2:
            continue
        tangent = unit(np.gradient(pts, axis=0))
        rel = pts[:, None, :] - a[None]  # (P, S, 2)
        t = np.clip(np.einsum("psk,sk->ps", rel, seg_dir), 0.0, seg_len[None])
        dist = np.linalg.norm(rel - t[..., None] * seg_dir[None], axis=2)
        along = tangent @ seg_dir.T  # (P, S) cosine of the angle between the lane and the segment
        dist = np.where((np.abs(along) >= cos) & (dist <= reach[None]), dist, np.inf)
        best = np.argmin(dist, axis=1)
        rows = np.arange(len(pts))
        key = _filled(np.where(np.isfinite(dist[rows, best]), piece[best] * 2 + (along[rows, best] < 0), -1))
        d, r = seg_dir[best], rel[rows, best]
        lateral = d[:, 0] * r[:, 1] - d[:, 1] * r[:, 0]  # left of the road
        for first, last in _stretches(key):
            if key[first] < 0 or (last - first) * STEP_M < MIN_RUN_M:
                continue
            p, sign = int(key[first] // 2), -1 if key[first] % 2 else 1
            if roads[p].oneway and sign != (1 if roads[p].oneway == 1 else -1):
                continue
            runs.append((p, sign, float(np.median(lateral[first:last + 1]))))
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


def _outward(road: Road, sign: int, lateral: float, side: str) -> float:
    """A lateral position in lane widths, counted as lanes are laid (0 for the lane nearest the centreline of a two-way
    road, 1 for the next, ...; left to right of travel on a one-way road, where only differences matter)."""
    w = lane_width(road)
    if road.oneway:
        return -sign * lateral / w
    right = 1.0 if side == "right" else -1.0
    return -right * sign * lateral / w - 0.5
