"""Argoverse 2 log-map archives (``log_map_archive_<log id>____<CITY>_city_<n>.json``).

The JSON holds ``lane_segments``, ``pedestrian_crossings`` and ``drivable_areas``, keyed by id, in
city-frame metres. Vehicle and bus lane segments become lanes (bike lanes are skipped); pedestrian
crossings become crosswalks. AV2 maps have no traffic-light stop lines.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import as_polyline
from cmtool.core.jsonio import read_json
from cmtool.formats.importers.common import centerline_and_width, same_direction, tidy_references
from cmtool.maps.hdmap import Crosswalk, HDMap, Lane

LANE_TYPES = {"VEHICLE": "vehicle", "BUS": "bus"}
_CITY = re.compile(r"____([A-Za-z]+)_city_")


def import_av2(path: str | os.PathLike, city: str | None = None) -> HDMap:
    """Read one AV2 log map. The city code comes from the file name (``...____PIT_city_71109.json``
    gives ``PIT``, ``UNK`` when absent) unless ``city`` is given."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or "lane_segments" not in data:
        raise CmtoolError(f"{path}: not an Argoverse 2 map (no 'lane_segments')")
    match = _CITY.search(path.name)
    code = match.group(1).upper() if match else "UNK"
    hd = HDMap(city=city or code, drives_on="right", source=f"av2:{path.name}")

    segments = _records(data["lane_segments"], path, "lane_segments")
    seen: set[str] = set()
    for seg in segments:
        try:
            if str(seg["id"]) in seen:
                raise ValueError("its id is the id of an earlier lane segment")
            seen.add(str(seg["id"]))
            lane_type = LANE_TYPES.get(seg["lane_type"])
            if lane_type is None:
                continue
            left, right = _points(seg["left_lane_boundary"]), _points(seg["right_lane_boundary"])
            centerline, width = centerline_and_width(left, right)
            if seg.get("centerline"):
                centerline = _points(seg["centerline"])
            hd.add_lane(
                Lane(
                    id=str(seg["id"]),
                    centerline=centerline,
                    width=width,
                    successors=_ids(seg, "successors"),
                    predecessors=_ids(seg, "predecessors"),
                    left_neighbor=_id(seg.get("left_neighbor_id")),
                    right_neighbor=_id(seg.get("right_neighbor_id")),
                    is_intersection=bool(seg.get("is_intersection", False)),
                    lane_type=lane_type,
                )
            )
        except (KeyError, TypeError, ValueError) as e:
            raise CmtoolError(f"{path}: lane segment {_name(seg)}: malformed ({type(e).__name__}: {e})") from None

    if not hd.lanes:
        raise CmtoolError(f"{path}: no lane segments of the kinds cmtool reads ({', '.join(LANE_TYPES)})")
    # AV2 neighbours may run in the opposite direction; HDMap neighbours are same-direction lanes.
    for lane in hd.lanes.values():
        for side in ("left_neighbor", "right_neighbor"):
            other = hd.lanes.get(getattr(lane, side))
            if other is None or not same_direction(lane.centerline, other.centerline):
                setattr(lane, side, None)

    for crossing in _records(data.get("pedestrian_crossings", {}), path, "pedestrian_crossings"):
        try:
            polygon = np.concatenate([_points(crossing["edge1"]), _points(crossing["edge2"])[::-1]])
            hd.crosswalks.append(Crosswalk(str(crossing["id"]), polygon))
        except (KeyError, TypeError, ValueError) as e:
            msg = f"pedestrian crossing {_name(crossing)}: malformed ({type(e).__name__}: {e})"
            raise CmtoolError(f"{path}: {msg}") from None
    return tidy_references(hd)


def _records(items, path: Path, key: str) -> list[dict]:
    """The records of a top-level collection, stored as an id-keyed object or a list."""
    values = list(items.values()) if isinstance(items, dict) else items
    if not isinstance(values, list) or not all(isinstance(v, dict) for v in values):
        raise CmtoolError(f"{path}: '{key}' must hold JSON objects")
    return values


def _points(items) -> np.ndarray:
    """AV2 points ``[{"x":, "y":, "z":}, ...]`` as an (N, 2) array."""
    return as_polyline([[p["x"], p["y"]] for p in items])


def _ids(seg: dict, key: str) -> list[str]:
    """A list of lane ids (``key`` absent or null: none)."""
    ids = seg.get(key) or []
    if not isinstance(ids, list) or not all(isinstance(i, (int, str)) and not isinstance(i, bool) for i in ids):
        raise ValueError(f"{key}: expected a list of lane ids, got {json.dumps(ids)[:40]}")
    return [str(i) for i in ids]


def _id(value) -> str | None:
    return None if value is None else str(value)


def _name(record: dict) -> str:
    return repr(record.get("id", "?"))
