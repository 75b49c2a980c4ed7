"""nuPlan maps: the per-city SQLite GeoPackage ``map.gpkg`` of the nuPlan map release.

Read with ``sqlite3`` and shapely only. Layers used (column names as in nuplan-devkit's map API):

* ``lanes_polygons`` (``fid``, ``lane_group_fid``, ``lane_index``, polygon): lanes; ``lane_index``
  counts from the left within a lane group, giving the left/right neighbours; width = area / length
  of the baseline.
* ``lane_connectors`` (``fid``, ``exit_lane_fid``, ``entry_lane_fid``, ``intersection_fid``,
  ``traffic_light_stop_line_fids``): connector lanes inside intersections. As in the devkit a
  connector's incoming lane is ``exit_lane_fid`` and its outgoing lane ``entry_lane_fid``, so the
  edges are exit lane -> connector -> entry lane. Width from
  ``gen_lane_connectors_scaled_width_polygons`` when present, else the mean of the joined lanes.
* ``baseline_paths`` (``lane_fid`` or ``lane_connector_fid``, linestring): the centerlines.
* ``crosswalks`` (polygons) and ``stop_polygons`` (``stop_polygon_type_fid`` 2 = traffic light): a
  traffic-light stop polygon becomes a stop line along its long axis, controlling the connectors
  that list it in ``traffic_light_stop_line_fids``.

Lane ids are ``l<fid>`` and connector ids ``c<fid>`` (the two tables number independently).
Coordinates are metres when the layer's spatial reference system is projected (UTM); a geographic
(lon/lat) layer is projected with :class:`~cmtool.core.geo.LocalProjection` centred on the mean
baseline position. The city comes from the map location in the path (``us-nv-las-vegas-strip`` ->
LAV, ``us-pa-pittsburgh-hazelwood`` -> PIT, ``sg-one-north`` -> SGP, ``us-ma-boston`` -> BOS).
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np
import shapely
import shapely.wkb

from cmtool.core.errors import CmtoolError
from cmtool.core.geo import LocalProjection, centre_of
from cmtool.formats.importers.common import MAX_WIDTH, MIN_WIDTH, tidy_references
from cmtool.maps.hdmap import Crosswalk, HDMap, Lane, StopLine, drives_on

CITIES = {
    "us-nv-las-vegas-strip": "LAV",
    "us-pa-pittsburgh-hazelwood": "PIT",
    "sg-one-north": "SGP",
    "us-ma-boston": "BOS",
}
TRAFFIC_LIGHT_STOP = 2  # nuPlan StopLineType.TRAFFIC_LIGHT
_ENVELOPE_BYTES = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}


def import_nuplan(path: str | os.PathLike, city: str | None = None) -> HDMap:
    """Read a nuPlan GeoPackage map; ``city`` overrides the code derived from the path."""
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such file")
    code = next((c for name, c in CITIES.items() if name in str(path)), "UNK")
    hd = HDMap(city=city or code, drives_on=drives_on(code), source=f"nuplan:{path.name}")
    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
        try:
            _read(_GeoPackage(con, path), hd)
        finally:
            con.close()
    except sqlite3.DatabaseError as e:
        raise CmtoolError(f"{path}: not a readable GeoPackage ({e})") from None
    except (TypeError, ValueError) as e:
        raise CmtoolError(f"{path}: malformed nuPlan map ({type(e).__name__}: {e})") from None
    return tidy_references(hd)


class _GeoPackage:
    """Rows of GeoPackage feature tables, with geometries decoded to shapely."""

    def __init__(self, con: sqlite3.Connection, path: Path):
        self.con, self.path = con, path
        con.row_factory = sqlite3.Row
        try:
            rows = con.execute("SELECT table_name, column_name, srs_id FROM gpkg_geometry_columns").fetchall()
        except sqlite3.OperationalError:
            raise CmtoolError(f"{path}: not a GeoPackage (no gpkg_geometry_columns table)") from None
        self.columns = {r["table_name"]: (r["column_name"], r["srs_id"]) for r in rows}
        self.project = None  # lon/lat -> metres, set for geographic maps

    def has(self, layer: str) -> bool:
        return layer in self.columns

    def geographic(self, layer: str) -> bool:
        query = "SELECT definition FROM gpkg_spatial_ref_sys WHERE srs_id = ?"
        row = self.con.execute(query, (self.columns[layer][1],)).fetchone()
        return row is not None and str(row["definition"]).lstrip().upper().startswith(("GEOGCS", "GEOGCRS"))

    def rows(self, layer: str, required: tuple[str, ...]) -> list[dict]:
        """All features of ``layer`` as dicts with a decoded ``geometry`` (None when empty)."""
        if layer not in self.columns:
            raise CmtoolError(f"{self.path}: not a nuPlan map (no '{layer}' layer)")
        geom_col = self.columns[layer][0]
        out = []
        for r in self.con.execute(f'SELECT * FROM "{layer}"'):
            row = dict(r)
            missing = [c for c in required if c not in row]
            if missing:
                raise CmtoolError(f"{self.path}: layer '{layer}' lacks column(s) {', '.join(missing)}")
            row["geometry"] = self._geometry(row.pop(geom_col), layer, row.get("fid"))
            out.append(row)
        return out

    def _geometry(self, blob, layer: str, fid):
        """Decode a GeoPackage binary geometry: 'GP', version, flags, srs id, envelope, then WKB."""
        if blob is None:
            return None
        blob = bytes(blob)
        if len(blob) < 8 or blob[:2] != b"GP":
            raise CmtoolError(f"{self.path}: layer '{layer}' fid {fid}: not a GeoPackage geometry")
        flags = blob[3]
        envelope = _ENVELOPE_BYTES.get((flags >> 1) & 0b111)
        if envelope is None or flags & 0b10000:  # invalid envelope code, or the empty-geometry flag
            return None
        try:
            geom = shapely.wkb.loads(blob[8 + envelope :])
        except shapely.errors.ShapelyError as e:
            raise CmtoolError(f"{self.path}: layer '{layer}' fid {fid}: bad WKB ({e})") from None
        if self.project is not None:
            geom = shapely.transform(geom, lambda c: self.project.to_metres(c[:, 1], c[:, 0]))
        return geom


def _read(gp: _GeoPackage, hd: HDMap) -> None:
    if gp.geographic("baseline_paths"):
        rows = gp.rows("baseline_paths", ())
        lonlat = np.concatenate([shapely.get_coordinates(r["geometry"]) for r in rows if r["geometry"] is not None])
        gp.project = LocalProjection(*centre_of(lonlat[:, ::-1]))
    centerlines = {}
    for row in gp.rows("baseline_paths", ("lane_fid", "lane_connector_fid")):
        geom = row["geometry"]
        if geom is None or geom.length <= 0.0:
            continue
        if row["lane_fid"] is not None:
            centerlines[f"l{int(row['lane_fid'])}"] = shapely.get_coordinates(geom)
        elif row["lane_connector_fid"] is not None:
            centerlines[f"c{int(row['lane_connector_fid'])}"] = shapely.get_coordinates(geom)
    _lanes(gp, hd, centerlines)
    light_lanes = _connectors(gp, hd, centerlines)
    if gp.has("crosswalks"):
        for row in gp.rows("crosswalks", ("fid",)):
            parts = [] if row["geometry"] is None else list(getattr(row["geometry"], "geoms", [row["geometry"]]))
            for k, poly in enumerate(p for p in parts if isinstance(p, shapely.Polygon) and not p.is_empty):
                cid = str(int(row["fid"])) if len(parts) == 1 else f"{int(row['fid'])}.{k}"
                hd.crosswalks.append(Crosswalk(cid, shapely.get_coordinates(poly.exterior)[:-1]))
    if gp.has("stop_polygons"):
        for row in gp.rows("stop_polygons", ("fid", "stop_polygon_type_fid")):
            line = _long_axis(row["geometry"]) if row["stop_polygon_type_fid"] == TRAFFIC_LIGHT_STOP else None
            if line is not None:
                lane_ids = light_lanes.get(int(row["fid"]), [])
                hd.stop_lines.append(StopLine(str(int(row["fid"])), line, "unknown", lane_ids))


def _lanes(gp: _GeoPackage, hd: HDMap, centerlines: dict) -> None:
    """Lanes with a baseline path; neighbours by ``lane_index`` (0 = leftmost) within a lane group."""
    groups: dict[int, dict[int, str]] = {}
    for row in gp.rows("lanes_polygons", ("fid", "lane_group_fid", "lane_index")):
        lid = f"l{int(row['fid'])}"
        if lid in centerlines:
            hd.add_lane(Lane(id=lid, centerline=centerlines[lid], width=_width(row["geometry"], centerlines[lid])))
            if row["lane_group_fid"] is not None and row["lane_index"] is not None:
                groups.setdefault(int(row["lane_group_fid"]), {})[int(row["lane_index"])] = lid
    for members in groups.values():
        for index, lid in members.items():
            hd.lanes[lid].left_neighbor = members.get(index - 1)
            hd.lanes[lid].right_neighbor = members.get(index + 1)


def _connectors(gp: _GeoPackage, hd: HDMap, centerlines: dict) -> dict[int, list[str]]:
    """Connector lanes (exit lane -> connector -> entry lane); returns the connectors of each stop polygon."""
    polygons = {}
    if gp.has("gen_lane_connectors_scaled_width_polygons"):
        for row in gp.rows("gen_lane_connectors_scaled_width_polygons", ("lane_connector_fid",)):
            polygons[f"c{int(row['lane_connector_fid'])}"] = row["geometry"]
    light_lanes: dict[int, list[str]] = {}
    for row in gp.rows("lane_connectors", ("fid", "exit_lane_fid", "entry_lane_fid")):
        cid = f"c{int(row['fid'])}"
        if cid not in centerlines:
            continue
        src, dst = f"l{int(row['exit_lane_fid'])}", f"l{int(row['entry_lane_fid'])}"
        if cid in polygons:
            width = _width(polygons[cid], centerlines[cid])
        else:
            joined = [hd.lanes[i].width for i in (src, dst) if i in hd.lanes]
            width = float(np.mean(joined)) if joined else 3.5
        inter = row.get("intersection_fid")
        hd.add_lane(Lane(id=cid, centerline=centerlines[cid], width=width, predecessors=[src], successors=[dst],
                         is_intersection=True, intersection_id=None if inter is None else str(int(inter))))
        for fid in str(row.get("traffic_light_stop_line_fids") or "").split(","):
            if fid.strip():
                light_lanes.setdefault(int(fid), []).append(cid)
    return light_lanes


def _width(polygon, centerline: np.ndarray) -> float:
    """Mean lane width: polygon area over centerline length (3.5 m when there is no polygon)."""
    length = float(np.linalg.norm(np.diff(centerline, axis=0), axis=1).sum())
    if polygon is None or polygon.is_empty or length <= 0.0:
        return 3.5
    return float(np.clip(polygon.area / length, MIN_WIDTH, MAX_WIDTH))


def _long_axis(polygon) -> np.ndarray | None:
    """The midline along the long side of a (thin) polygon's minimum rotated rectangle (None when the
    polygon is empty or degenerate)."""
    if polygon is None or not isinstance(polygon.minimum_rotated_rectangle, shapely.Polygon):
        return None
    box = shapely.get_coordinates(polygon.minimum_rotated_rectangle)[:4]
    sides = np.linalg.norm(box - np.roll(box, -1, axis=0), axis=1)
    k = 0 if sides[0] >= sides[1] else 1  # side k (box[k] -> box[k+1]) is a long side
    return 0.5 * (box[[k, k + 1]] + box[[(k + 3) % 4, (k + 2) % 4]])
