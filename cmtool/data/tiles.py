"""Tiles that cover an area's roads: scene frames (the model's 64 m squares) standing on roads and facing along them,
as training frames do, placed so that every road point of the area lies in the middle ``core_m`` square of one.

Each point of the area belongs to the tile whose centre is nearest (:mod:`cmtool.maps.stitch`), except that a tile
standing on a junction owns every point within its ``reach`` (``HUB_M``): the junction is drawn by one tile, and
no seam between two tiles runs through it. A road point lies in some tile's core, so its nearest centre is at most
``core_m / sqrt(2)`` away and the point lies inside that tile's frame with a margin of ``frame_m / 2 - core_m /
sqrt(2)`` (9 m for the defaults), room for the lanes beside it; a point a junction tile owns lies ``frame_m / 2 -
HUB_M`` (12 m) inside its frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.data.scene import Pose
from cmtool.data.sd_raster import FRAME_M
from cmtool.maps.roadgraph import road_graph
from cmtool.maps.sdmap import SDMap

CORE_M = 32.0  # every road point lies in the middle square of this side of some tile
STEP_M = 2.0  # road points are tried this far apart
HUB_M = 20.0  # a tile on a junction owns every point this near its centre (for the model's 64 m frames)
MAX_ROAD_KM = 1_000.0  # of road in one area (about 38,000 tiles, a city of 100 km2); a larger area is refused


@dataclass
class Tile(Pose):
    reach: float = 0.0  # the tile owns every point this near its centre (a junction's tile), else only the nearest


def cover(sd: SDMap, box: tuple[float, float, float, float] | None = None, core_m: float = CORE_M,
          step_m: float = STEP_M, frame_m: float = FRAME_M) -> list[Tile]:
    """Tiles covering the roads of ``sd`` (their parts inside ``box``, (x0, y0, x1, y1) metres, when given): first
    one centred on each junction (owning the points within ``HUB_M`` of it, so that no tile border cuts through it),
    then, walking each road (longest first) in steps of ``step_m``, a point outside the core of every tile so far
    gets a tile half a core further on, its core starting about where the last one's ends. Tiles face the road's
    travel direction (along the polyline on two-way roads)."""
    if not 0 < core_m <= frame_m:
        raise CmtoolError(f"tile core {core_m} m: must be in (0, {frame_m:g}] m")
    area = shapely.box(*box) if box is not None else None
    pieces = []
    for road in sd.roads:
        line = shapely.LineString(road.travel_polyline())
        clipped = line if area is None else shapely.intersection(line, area)
        pieces += [p for p in getattr(clipped, "geoms", [clipped]) if isinstance(p, shapely.LineString)
                   and not p.is_empty and p.length > 0]
    pieces.sort(key=lambda p: -p.length)
    tiles = _Tiles(core_m)
    if pieces:
        for centre in road_graph(sd).centres:
            if area is None or area.contains(shapely.Point(centre)):
                nearest = pieces[int(np.argmin(shapely.distance(shapely.Point(centre), pieces)))]
                tiles.add(centre, _heading(nearest, nearest.project(shapely.Point(centre))), HUB_M * frame_m / FRAME_M)
    for line in pieces:
        for at in np.linspace(0.0, line.length, max(2, int(math.ceil(line.length / step_m)) + 1)):
            p = _point(line, at)
            if tiles.covers(p):
                continue
            ahead = min(at + core_m / 2.0, line.length)
            tiles.add(_point(line, ahead), _heading(line, ahead))
            if not tiles.covers(p):  # the road turns: stand one on the point itself
                tiles.add(p, _heading(line, at))
    return tiles.poses


def check_extent(sd: SDMap, box: tuple[float, float, float, float], option: str) -> None:
    """Refuse, naming ``option`` (what set the area), an area whose roads run over ``MAX_ROAD_KM``, before any tile
    is laid."""
    roads = shapely.intersection([shapely.LineString(r.polyline) for r in sd.roads], shapely.box(*box))
    km = float(shapely.length(roads).sum()) / 1000.0
    if not km <= MAX_ROAD_KM:
        raise CmtoolError(f"{option}: the area's roads run {km:,.0f} km; one area holds up to {MAX_ROAD_KM:,.0f} km "
                          f"of road (about {MAX_ROAD_KM * 38:,.0f} tiles)")


class _Tiles:
    """Tiles placed so far, found by a grid of ``core_m`` cells."""

    def __init__(self, core_m: float):
        self.core, self.poses, self.grid = core_m, [], {}

    def add(self, p: np.ndarray, yaw: float, reach: float = 0.0) -> None:
        self.grid.setdefault(self._cell(p), []).append(len(self.poses))
        self.poses.append(Tile(float(p[0]), float(p[1]), float(yaw), reach))

    def covers(self, p: np.ndarray) -> bool:
        """Whether ``p`` lies in the core square of a tile."""
        cx, cy = self._cell(p)
        half = self.core / 2.0
        for t in (t for dx in (-1, 0, 1) for dy in (-1, 0, 1) for t in self.grid.get((cx + dx, cy + dy), ())):
            pose = self.poses[t]
            dx, dy = p[0] - pose.x, p[1] - pose.y
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            if abs(c * dx + s * dy) <= half and abs(-s * dx + c * dy) <= half:
                return True
        return False

    def _cell(self, p) -> tuple[int, int]:
        return int(p[0] // self.core), int(p[1] // self.core)


def _point(line, at: float) -> np.ndarray:
    return shapely.get_coordinates(shapely.line_interpolate_point(line, at))[0]


def _heading(line, at: float) -> float:
    """The heading of ``line`` at ``at`` metres along it (over the 2 m around it)."""
    a, b = _point(line, max(at - 1.0, 0.0)), _point(line, min(at + 1.0, line.length))
    return float(math.atan2(b[1] - a[1], b[0] - a[0]))
