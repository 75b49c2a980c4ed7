"""The SD roads of a frame, and what a lane graph draws along them.

Lanes are matched to the roads as :mod:`cmtool.metrics.decisions` matches them (:func:`lane_runs`: stretches of at
least ``MIN_RUN_M`` along one road, one way). How many lanes a direction of a road has as drawn: on one-way roads the
distinct runs (lateral positions more than ``SAME_LANE`` lane widths apart), on two-way roads as many as the farthest
run from the centreline, at most ``MAX_LANES``. :mod:`cmtool.sample.compose` takes the model's lane counts from it,
``cmtool eval`` the truth's and the model's.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

import numpy as np
import shapely

from cmtool.core.geometry import to_frame
from cmtool.data.rules import lane_width
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.decisions import MAX_LANES, STEP_M, lane_runs
from cmtool.metrics.lanes import resampled

SAME_LANE = 0.6  # runs of one road and direction closer than this many lane widths are one lane
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


def drawn_lane_counts(graph: LaneGraph, roads: list[Road], side: str) -> dict[tuple[int, int], int]:
    """The lanes a lane graph draws along each of the frame's ``roads`` (:func:`frame_roads`), per (road index, +1
    along its polyline / -1 against it) (module doc); lanes up to ``MAX_LANES`` a direction out are matched."""
    wide = [replace(r, lanes=None) for r in roads]
    runs = lane_runs(resampled([np.asarray(l, np.float64) for l in graph.lanes], STEP_M), wide) \
        if graph.lanes and roads else []
    groups: dict[tuple[int, int], list[float]] = defaultdict(list)
    for p, sign, _, _, lateral in (run for lane in runs for run in lane):
        groups[(p, sign)].append(_outward(wide[p], sign, lateral, side))
    out = {}
    for (p, sign), places in groups.items():
        places = sorted(places)
        if wide[p].oneway:
            out[(p, sign)] = 1 + int(np.sum(np.diff(places) > SAME_LANE))
        else:
            out[(p, sign)] = int(np.clip(np.round(places[-1]), 0, MAX_LANES - 1)) + 1
    return out


def _outward(road: Road, sign: int, lateral: float, side: str) -> float:
    """A lateral position in lane widths, counted as lanes are laid (0 for the lane nearest the centreline of a two-way
    road, 1 for the next, ...; left to right of travel on a one-way road, where only differences matter)."""
    w = lane_width(road)
    if road.oneway:
        return -sign * lateral / w
    right = 1.0 if side == "right" else -1.0
    return -right * sign * lateral / w - 0.5
