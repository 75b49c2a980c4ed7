"""What ``cmtool sample`` generates from: SD rasters read from pictures, rasterised from
OpenStreetMap around a point, or derived from an HD map at an ego pose (with its ground truth).

Every input is loaded and checked before anything is generated or written, so a bad input ends
the command with one message and no output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import json_lines
from cmtool.data.sd_raster import FRAME_M, IMAGE_SUFFIXES, SDRasterizer, read_sd_image
from cmtool.data.sd_trace import trace_picture
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import SDMap

MIN_ROAD_M = 1.0  # a frame whose SD roads are shorter in all has nothing to lay lanes on (an OSM way of one spot)


@dataclass
class ControlInput:
    """One SD control (or none, for unconditional maps) and, when known, its ground truth."""

    name: str
    sd: np.ndarray | None  # (128, 128, 3) uint8
    source: str
    truth: LaneGraph | None = None
    city: str | None = None  # the city of the source map, when it has one
    note: str | None = None  # what was converted on reading, for the user
    geo: dict | None = None  # {"lat", "lon", "heading"} of the frame (see cmtool.maps.lanegraph), when known
    sd_map: SDMap | None = None  # the SD map the raster was drawn from, when there is one
    pose: tuple[float, float, float] | None = None  # the frame in ``sd_map``: x, y (m), yaw (radians)


def image_inputs(paths) -> list[ControlInput]:
    """SD inputs from picture files and folders of pictures (sorted by name)."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise CmtoolError(f"{path}: no pictures in the folder ({', '.join(IMAGE_SUFFIXES)})")
            files += found
        else:
            files.append(path)
    inputs = []
    for path in files:
        sd, note = read_sd_image(path)
        if not sd[..., 0].any():
            raise CmtoolError(f"{path}: no roads in the picture (draw roads light on dark or dark on light)")
        inputs.append(ControlInput(path.stem, sd, str(path), note=f"{path.name}: {note}" if note else None,
                                   **_traced(sd)))
    return _unique_names(inputs)


def _traced(sd: np.ndarray) -> dict:
    """The SD map traced from an SD raster's roads (:func:`cmtool.data.sd_trace.trace_picture`) and the frame's pose
    in it (the raster's up is ahead), for what needs the roads' lines: the guarantee's composed map and the rules;
    nothing where no line can be traced."""
    try:
        sd_map = trace_picture(sd, True, FRAME_M / sd.shape[0])
    except CmtoolError:
        return {}
    return {"sd_map": sd_map, "pose": (0.0, 0.0, math.pi / 2)}


def osm_inputs(path, centers: list[tuple[float, float, float]]) -> list[ControlInput]:
    """SD rasters of an OpenStreetMap file around ``(lat, lon, heading)`` points; heading in
    compass degrees (0 = north is up in the raster, 90 = east is up)."""
    from cmtool.core.geo import LocalProjection

    sd_map = osm_sd_map(path)
    proj = LocalProjection(sd_map.meta["lat0"], sd_map.meta["lon0"])
    rasterize = SDRasterizer(sd_map)
    roads = shapely.STRtree([shapely.LineString(r.polyline) for r in sd_map.roads])
    inputs = []
    for k, (lat, lon, heading) in enumerate(centers):
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise CmtoolError(f"--center {lat},{lon}: latitude must be in [-90, 90] and longitude in [-180, 180]"
                              + _swap_hint(sd_map, lat, lon))
        x, y = proj.to_metres(lat, lon)
        sd = rasterize(float(x), float(y), math.radians(90.0 - heading))
        if not sd[..., 0].any():
            raise CmtoolError(f"{path}: no roads within the {FRAME_M:.0f} m frame around {lat:.6f},{lon:.6f} "
                              f"(nearest road {_nearest_road(sd_map, x, y):.0f} m away){_swap_hint(sd_map, lat, lon)}")
        if (length := _length_in_frame(roads, x, y)) < MIN_ROAD_M:
            raise CmtoolError(f"{path}: the roads within the {FRAME_M:.0f} m frame around {lat:.6f},{lon:.6f} are "
                              f"{length:.2f} m long in all: no road to lay lanes on (at least {MIN_ROAD_M:g} m)")
        name = f"{Path(path).name.split('.')[0]}_{k}" if len(centers) > 1 else Path(path).name.split(".")[0]
        inputs.append(ControlInput(name, sd, f"osm:{Path(path).name}@{lat:.6f},{lon:.6f},heading {heading:g}",
                                   geo=_geo(lat, lon, heading), sd_map=sd_map,
                                   pose=(float(x), float(y), math.radians(90.0 - heading))))
    return inputs


def osm_sd_map(path) -> SDMap:
    """The SD map of an OpenStreetMap file, which must hold a drivable road."""
    from cmtool.formats.osm import read_osm

    sd_map = read_osm(path)
    if not sd_map.roads:
        raise CmtoolError(f"{path}: no drivable roads in the OpenStreetMap file")
    return sd_map


def hd_sd_map(path):
    """An HD map JSON, which must hold lanes, and the SD map derived from it."""
    from cmtool.data.sd_derive import derive_sd
    from cmtool.formats.mapfile import read_hd_map

    hd = read_hd_map(path)
    if not hd.lanes:
        raise CmtoolError(f"{path}: the HD map has no lanes")
    return hd, derive_sd(hd)


def hd_inputs(path, poses: list[tuple[float, float, float]] | None, seed: int = 0) -> list[ControlInput]:
    """SD rasters derived from an HD map JSON at ego poses ``(x, y, yaw degrees)``, each with the
    ground-truth lane graph of the same frame; ``poses`` None picks one drivable pose at random."""
    from cmtool.core.geo import LocalProjection
    from cmtool.data.frames import FrameSampler
    from cmtool.data.scene import Pose, SceneCropper

    hd, sd_map = hd_sd_map(path)
    if poses is None:
        picked = FrameSampler(sd_map).sample(1, np.random.default_rng(seed))
        poses = [(f.pose.x, f.pose.y, math.degrees(f.pose.yaw)) for f in picked]
    cropper, rasterize = SceneCropper(hd), SDRasterizer(sd_map)
    stem = Path(path).name.split(".")[0]
    inputs = []
    for k, (x, y, yaw) in enumerate(poses):
        pose = Pose(x, y, math.radians(yaw))
        sd = rasterize(pose.x, pose.y, pose.yaw)
        truth = cropper.extract(pose).to_lanegraph()
        if not sd[..., 0].any() and not truth.lanes:
            raise CmtoolError(f"{path}: no roads within the {FRAME_M:.0f} m frame at pose {x:g},{y:g},{yaw:g}; "
                              f"pick a pose on a road (the map spans {_bounds(hd)})")
        name = f"{stem}_{k}" if len(poses) > 1 else stem
        geo = None
        if "lat0" in hd.meta and "lon0" in hd.meta:  # a map imported from lat/lon (Lanelet2)
            lat, lon = LocalProjection(hd.meta["lat0"], hd.meta["lon0"]).to_latlon([x, y])
            geo = truth.meta["geo"] = _geo(lat, lon, 90.0 - yaw)
        inputs.append(ControlInput(name, sd, f"hd:{Path(path).name}@{x:.2f},{y:.2f},{yaw:.1f}deg",
                                   truth=truth, city=hd.city, geo=geo, sd_map=sd_map, pose=(pose.x, pose.y, pose.yaw)))
    return inputs


def _geo(lat: float, lon: float, heading: float) -> dict:
    return {"lat": round(float(lat), 8), "lon": round(float(lon), 8), "heading": round(float(heading) % 360.0, 4)}


def parse_points(value: str, keys: tuple[str, ...], defaults: dict, option: str) -> list[tuple[float, ...]]:
    """``"a,b[,c]"`` or a JSON Lines file of objects with ``keys`` -> a list of float tuples."""
    path = Path(value)
    if path.suffix == ".jsonl" or path.is_file():
        if not path.is_file():
            raise CmtoolError(f"{option} {value}: no such file")
        rows = []
        for lineno, obj in json_lines(path):
            if not isinstance(obj, dict):
                raise CmtoolError(f"{path}: line {lineno}: expected an object with {', '.join(keys)}")
            rows.append(tuple(_number(obj.get(k, defaults.get(k)), f"{path}: line {lineno}: {k}") for k in keys))
        if not rows:
            raise CmtoolError(f"{path}: no points in the file")
        return rows
    parts = value.split(",")
    need = [k for k in keys if k not in defaults]
    if not len(need) <= len(parts) <= len(keys):
        raise CmtoolError(f"{option} {value!r}: expected {','.join(k.upper() for k in keys[:len(need)])} "
                          f"(or a .jsonl file of them)")
    values = [_number(p.strip(), f"{option} {value!r}") for p in parts]
    return [tuple(values + [defaults[k] for k in keys[len(values):]])]


def _number(value, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise CmtoolError(f"{where}: expected a number, got {value!r}") from None
    if not math.isfinite(number):
        raise CmtoolError(f"{where}: expected a finite number, got {value!r}")
    return number


def _length_in_frame(roads: shapely.STRtree, x: float, y: float) -> float:
    """The length of the SD ``roads`` inside the frame's circle around ``(x, y)`` (metres)."""
    circle = shapely.Point(x, y).buffer(FRAME_M / math.sqrt(2.0))
    near = roads.geometries[roads.query(circle)]
    return float(shapely.length(shapely.intersection(near, circle)).sum())


def _nearest_road(sd_map, x: float, y: float) -> float:
    from cmtool.metrics.lanes import distance_to_polylines

    return float(distance_to_polylines(np.array([[x, y]]), [r.polyline for r in sd_map.roads])[0])


def _swap_hint(sd_map, lat: float, lon: float) -> str:
    """A hint when ``(lon, lat)`` lies within the extent of an OpenStreetMap SD map's roads (and a frame around
    them) and ``(lat, lon)`` does not (:func:`cmtool.core.geo.swap_hint`)."""
    from cmtool.core.geo import swap_hint

    reach = float(np.linalg.norm(np.concatenate([r.polyline for r in sd_map.roads]), axis=1).max()) + FRAME_M
    return swap_hint(lat, lon, sd_map.meta["lat0"], sd_map.meta["lon0"], reach)


def _bounds(hd) -> str:
    x0, y0, x1, y1 = hd.bounds()
    return f"x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f} m"


def _unique_names(inputs: list[ControlInput]) -> list[ControlInput]:
    seen: dict[str, int] = {}
    for item in inputs:
        n = seen.get(item.name, 0)
        seen[item.name] = n + 1
        if n:
            item.name = f"{item.name}_{n}"
    return inputs

