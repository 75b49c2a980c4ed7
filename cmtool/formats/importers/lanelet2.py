"""Lanelet2 maps in OSM XML (lat/lon), e.g. the Karlsruhe ``mapping_example.osm``.

* Lanes: relations with ``type=lanelet`` and a road subtype (``road``, ``highway``, ``play_street``,
  ``emergency_lane``, SinD's ``main_road``, or no subtype as in SinD's connectors -> vehicle; ``bus_lane`` -> bus).
  A lanelet tagged ``one_way=no`` is drivable
  both ways and gives a second lane ``<id>-rev`` with its bounds swapped and reversed.
  ``crosswalk`` lanelets become crosswalk polygons; other subtypes are not lanes.
* Bounds: the ``left``/``right`` member ways may run against the lanelet. The right bound is
  reversed when that pairs the bounds' ends better, then both are reversed if the left bound lies
  on the right of travel, so the lanelet direction follows from the geometry alone.
* Successors: B follows A when A's bounds end on the nodes B's bounds start on (the left and the right
  node shared, as Lanelet2 links lanelets; bounds that merely end at one place are not linked).
  Lanelets with one ``cmtool:lane`` tag are one lane (cmtool's exports write a lane that groups of lanes
  with different successors flow into once per group).
  Neighbours: A's left bound is B's right bound, the same way
  traversed in the same direction.
* Intersections (Lanelet2 has no such flag): a lane is marked ``is_intersection`` when it diverges
  from or merges with a sibling, i.e. another lane starts where it starts but ends elsewhere, or
  ends where it ends but starts elsewhere.
* Traffic lights: each ``regulatory_element`` of subtype ``traffic_light`` with a ``ref_line`` gives
  a stop line (state ``unknown``) controlling the lanes whose lanelet references it.
* Coordinates: transverse Mercator (:class:`~cmtool.core.geo.LocalProjection`) centred on the mean
  latitude/longitude of all nodes in the file, recorded as ``meta.lat0`` / ``meta.lon0``. Maps in local coordinates
  placed near lat/lon 0 (the INTERACTION and SinD maps) project the same way, to metres of their true size.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.geo import LocalProjection, centre_of
from cmtool.core.geometry import resample
from cmtool.formats.importers.common import centerline_and_width, tidy_references
from cmtool.formats.osmxml import OsmData, OsmRelation, read_osm_xml
from cmtool.maps.hdmap import LIGHT_STATES, Crosswalk, HDMap, Lane, StopLine, drives_on

ROAD_SUBTYPES = {
    "road": "vehicle",
    "highway": "vehicle",
    "play_street": "vehicle",
    "emergency_lane": "vehicle",
    "main_road": "vehicle",  # SinD's Changchun map tags its approach and exit lanelets so
    "bus_lane": "bus",
}


@dataclass
class _Bound:
    way: int
    reversed: bool  # traversed against the way's node order
    xy: np.ndarray  # (N, 2) in traversal order
    ends: tuple[int, int]  # its first and last node ids, in traversal order


@dataclass
class _Lanelet:
    id: str
    relation: int
    left: _Bound
    right: _Bound
    lane_type: str
    lane: str = ""  # the id of the lane it is part of: its own, or the first lanelet's with its cmtool:lane tag


def import_lanelet2(path: str | os.PathLike, city: str | None = None) -> HDMap:
    """Read a Lanelet2 OSM map (city code ``KAR``, the Karlsruhe example, unless ``city`` is given or the file is one
    of cmtool's exports, which record it)."""
    path = Path(path)
    osm = read_osm_xml(path)
    lanelets = {rid: rel for rid, rel in osm.relations.items() if rel.tags.get("type") == "lanelet"}
    if not lanelets:
        raise CmtoolError(f"{path}: not a Lanelet2 map (no relations with type=lanelet)")
    if not osm.nodes:
        raise CmtoolError(f"{path}: no nodes")
    xy, (lat0, lon0) = _project(osm)
    recorded = {rel.tags["cmtool:city"] for rel in lanelets.values() if "cmtool:city" in rel.tags}  # cmtool's exports
    if not city:
        tag = recorded.pop() if len(recorded) == 1 else ""
        city = "" if tag == "none" else tag or "KAR"
    hd = HDMap(city=city, drives_on=drives_on(city), source=f"lanelet2:{path.name}",
               meta={"lat0": lat0, "lon0": lon0})

    lanes: list[_Lanelet] = []
    first_of: dict[str, str] = {}  # cmtool:lane tag -> the first lanelet's id
    for rid, rel in sorted(lanelets.items()):
        subtype = rel.tags.get("subtype", "road")
        if subtype not in ROAD_SUBTYPES and subtype != "crosswalk":
            continue
        left, right = _bounds(osm, xy, rid, rel, path)
        if subtype == "crosswalk":
            hd.crosswalks.append(Crosswalk(str(rid), np.concatenate([left.xy, right.xy[::-1]])))
            continue
        lane_type = ROAD_SUBTYPES[subtype]
        tag = rel.tags.get("cmtool:lane")
        lanes.append(_Lanelet(str(rid), rid, left, right, lane_type, first_of.setdefault(tag, str(rid)) if tag else ""))
        if rel.tags.get("one_way", "yes") == "no":
            lanes.append(_Lanelet(f"{rid}-rev", rid, _flip(right), _flip(left), lane_type))

    for ll in lanes:
        ll.lane = ll.lane or ll.id
        if ll.lane == ll.id:
            centerline, width = centerline_and_width(ll.left.xy, ll.right.xy)
            hd.add_lane(Lane(id=ll.id, centerline=centerline, width=width, lane_type=ll.lane_type))
    _link(hd, lanes)
    _neighbours(hd, lanes)
    _traffic_lights(hd, osm, xy, lanes, path)
    return tidy_references(hd)


def _project(osm: OsmData) -> tuple[dict[int, np.ndarray], tuple[float, float]]:
    """Node metres, and the latitude and longitude of the projection's origin."""
    ids = list(osm.nodes)
    lat = np.array([osm.nodes[i].lat for i in ids])
    lon = np.array([osm.nodes[i].lon for i in ids])
    lat0, lon0 = centre_of(np.stack([lat, lon], axis=1))
    return dict(zip(ids, LocalProjection(lat0, lon0).to_metres(lat, lon))), (lat0, lon0)


def _way_xy(osm: OsmData, xy: dict, way_id: int, where: str, path: Path) -> np.ndarray:
    way = osm.ways.get(way_id)
    if way is None:
        raise CmtoolError(f"{path}: {where}: way {way_id} does not exist")
    missing = [n for n in way.nodes if n not in xy]
    if missing or len(way.nodes) < 2:
        raise CmtoolError(f"{path}: {where}: way {way_id} has fewer than 2 nodes or a missing node")
    return np.array([xy[n] for n in way.nodes])


def _bounds(osm: OsmData, xy: dict, rid: int, rel: OsmRelation, path: Path) -> tuple[_Bound, _Bound]:
    """The lanelet's left and right bounds, both oriented in its driving direction."""
    where = f"lanelet {rid}"
    ways = {}
    for kind, ref, role in rel.members:
        if kind == "way" and role in ("left", "right"):
            ways[role] = ref
    if len(ways) != 2:
        raise CmtoolError(f"{path}: {where}: needs one 'left' and one 'right' way member")
    left, right = (_Bound(ways[side], False, _way_xy(osm, xy, ways[side], where, path),
                          (osm.ways[ways[side]].nodes[0], osm.ways[ways[side]].nodes[-1]))
                   for side in ("left", "right"))
    l, r = left.xy, right.xy
    aligned = np.linalg.norm(l[0] - r[0]) + np.linalg.norm(l[-1] - r[-1])
    crossed = np.linalg.norm(l[0] - r[-1]) + np.linalg.norm(l[-1] - r[0])
    if crossed < aligned:
        right = _flip(right)
    n = max(len(left.xy), len(right.xy), 2)
    lr, rr = resample(left.xy, n), resample(right.xy, n)
    direction = np.gradient(0.5 * (lr + rr), axis=0)
    across = lr - rr
    if np.sum(direction[:, 0] * across[:, 1] - direction[:, 1] * across[:, 0]) < 0.0:
        left, right = _flip(left), _flip(right)  # the left way lies on the right: drive the other way
    return left, right


def _flip(b: _Bound) -> _Bound:
    return _Bound(b.way, not b.reversed, b.xy[::-1], b.ends[::-1])


def _ends(lanes: list[_Lanelet], end: int) -> list[tuple[int, int]]:
    """The (left, right) bound node ids at each lane's start (end=0) or end (end=-1)."""
    return [(ll.left.ends[end], ll.right.ends[end]) for ll in lanes]


def _matches(a: list, b: list) -> list[tuple[int, int]]:
    """Index pairs (i, j) with a[i] and b[j] the same left and right nodes: as Lanelet2 itself links lanelets, by
    the nodes they share, not by where nodes lie (two lanes that merely end at one point are not linked)."""
    at = {}
    for j, key in enumerate(b):
        at.setdefault(key, []).append(j)
    return [(i, j) for i, key in enumerate(a) for j in at.get(key, [])]


def _link(hd: HDMap, lanes: list[_Lanelet]) -> None:
    """Successor edges from shared bound end nodes, and the diverge/merge intersection flags."""
    if not lanes:
        return
    starts, ends = _ends(lanes, 0), _ends(lanes, -1)
    for i, j in _matches(ends, starts):
        if lanes[i].lane != lanes[j].lane:
            hd.link(lanes[i].lane, lanes[j].lane)
    same_start, same_end = set(_matches(starts, starts)), set(_matches(ends, ends))
    for i, j in same_start ^ same_end:  # siblings sharing exactly one end (never a lane with itself)
        if lanes[i].lane != lanes[j].lane:
            hd.lanes[lanes[i].lane].is_intersection = True


def _neighbours(hd: HDMap, lanes: list[_Lanelet]) -> None:
    """Same-direction neighbours: A's left bound is B's right bound, traversed the same way."""
    lanes = [ll for ll in lanes if ll.lane == ll.id]
    by_right = {}
    for ll in lanes:
        by_right.setdefault((ll.right.way, ll.right.reversed), ll.id)
    for ll in lanes:
        other = by_right.get((ll.left.way, ll.left.reversed))
        if other is not None and other != ll.id:
            hd.lanes[ll.id].left_neighbor = other
            hd.lanes[other].right_neighbor = ll.id


def _traffic_lights(hd: HDMap, osm: OsmData, xy: dict, lanes: list[_Lanelet], path: Path) -> None:
    controlled: dict[int, list[str]] = {}
    for ll in lanes:
        if ll.id.endswith("-rev"):
            continue  # a lanelet's regulatory elements apply in its own direction
        for kind, ref, role in osm.relations[ll.relation].members:
            if kind == "relation" and role == "regulatory_element" and ll.lane not in controlled.get(ref, []):
                controlled.setdefault(ref, []).append(ll.lane)
    for rid, rel in sorted(osm.relations.items()):
        if rel.tags.get("type") != "regulatory_element" or rel.tags.get("subtype") != "traffic_light":
            continue
        ref_lines = [ref for kind, ref, role in rel.members if kind == "way" and role == "ref_line"]
        if not ref_lines:
            continue
        line = _way_xy(osm, xy, ref_lines[0], f"traffic light {rid}", path)
        state = rel.tags.get("cmtool:state", "unknown")  # cmtool's exports record the light's state
        hd.stop_lines.append(StopLine(str(rid), line, state if state in LIGHT_STATES else "unknown",
                                      controlled.get(rid, [])))
