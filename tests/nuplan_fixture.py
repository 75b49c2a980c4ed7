"""Builds a tiny nuPlan-schema GeoPackage for the importer tests.

Scene (metres, x east): lane group 10 west of an intersection (lanes 1 and 2, x -50..-10), lane group
20 east of it (lanes 3 and 4, x 10..50), all driving east; lane_index 0 is the left (north) lane.
Intersection 7 holds connectors 1 (lane 1 -> 3), 2 (lane 2 -> 4) and 3 (lane 2 -> 3). A traffic-light
stop polygon (fid 1, listed by connectors 1 and 2) and a stop-sign polygon (fid 2) lie at x = -10;
one crosswalk at x 0..4. Lane and connector fids overlap on purpose (1..3).
"""

from __future__ import annotations

import sqlite3
import struct

import numpy as np
import shapely
import shapely.wkb
from shapely.geometry import LineString, box

LANE_W = 3.5
UTM = 32619  # WGS 84 / UTM zone 19N (Boston)
WGS84 = 4326
LAT0, LON0 = 42.336, -71.058  # origin of the geographic variant
LANES = {  # fid: (lane_group_fid, lane_index, y)
    1: (10, 0, 1.75),
    2: (10, 1, -1.75),
    3: (20, 0, 1.75),
    4: (20, 1, -1.75),
}
CONNECTORS = {  # fid: (exit_lane_fid, entry_lane_fid, traffic_light_stop_line_fids)
    1: (1, 3, "1"),
    2: (2, 4, "1"),
    3: (2, 3, ""),
}


def lane_line(fid: int) -> np.ndarray:
    _, _, y = LANES[fid]
    x0, x1 = (-50.0, -10.0) if fid in (1, 2) else (10.0, 50.0)
    return np.array([[x0, y], [0.5 * (x0 + x1), y], [x1, y]])


def connector_line(fid: int) -> np.ndarray:
    a, b, _ = CONNECTORS[fid]
    start, end = lane_line(a)[-1], lane_line(b)[0]
    t = np.linspace(0.0, 1.0, 5)[:, None]
    return start + t * (end - start)


def _blob(geom, srs_id: int, envelope: bool) -> bytes:
    """GeoPackage binary: 'GP', version 0, flags (little endian, envelope code 1 or 0), srs id, envelope, WKB."""
    flags = 0b01 | (0b10 if envelope else 0)
    head = b"GP" + bytes([0, flags]) + struct.pack("<i", srs_id)
    if envelope:
        minx, miny, maxx, maxy = geom.bounds
        head += struct.pack("<4d", minx, maxx, miny, maxy)
    return head + shapely.wkb.dumps(geom)


def build_gpkg(path, geographic: bool = False) -> None:
    """Write the fixture map to ``path``; ``geographic`` stores lon/lat (EPSG:4326) instead of UTM metres."""
    srs = WGS84 if geographic else UTM

    def geo(g):
        if not geographic:
            return g
        return shapely.transform(g, lambda c: np.stack([LON0 + c[:, 0] / (111320.0 * np.cos(np.radians(LAT0))),
                                                         LAT0 + c[:, 1] / 111132.0], axis=1))

    layers = {
        "lanes_polygons": ("fid INTEGER PRIMARY KEY, lane_fid INTEGER, lane_group_fid INTEGER, lane_index INTEGER",
                           [(f, f, g, i, LineString(lane_line(f)).buffer(LANE_W / 2, cap_style="flat"))
                            for f, (g, i, _) in LANES.items()]),
        "lane_connectors": ("fid INTEGER PRIMARY KEY, exit_lane_fid INTEGER, entry_lane_fid INTEGER, "
                            "intersection_fid INTEGER, traffic_light_stop_line_fids TEXT",
                            [(f, a, b, 7, tl, LineString(connector_line(f))) for f, (a, b, tl) in CONNECTORS.items()]),
        "gen_lane_connectors_scaled_width_polygons": (
            "fid INTEGER PRIMARY KEY, lane_connector_fid INTEGER",
            [(1, 1, LineString(connector_line(1)).buffer(1.5, cap_style="flat"))],
        ),
        "baseline_paths": ("fid INTEGER PRIMARY KEY, lane_fid INTEGER, lane_connector_fid INTEGER",
                           [(f, f, None, LineString(lane_line(f))) for f in LANES]
                           + [(10 + f, None, f, LineString(connector_line(f))) for f in CONNECTORS]),
        "crosswalks": ("fid INTEGER PRIMARY KEY", [(1, box(0.0, -6.0, 4.0, 6.0))]),
        "stop_polygons": ("fid INTEGER PRIMARY KEY, stop_polygon_type_fid INTEGER",
                          [(1, 2, box(-10.5, -3.5, -9.5, 3.5)), (2, 1, box(-10.5, 4.0, -9.5, 6.0))]),
        "intersections": ("fid INTEGER PRIMARY KEY", [(7, box(-10.0, -8.0, 10.0, 8.0))]),
    }
    con = sqlite3.connect(path)
    con.executescript("""
        CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT, srs_id INTEGER PRIMARY KEY, organization TEXT,
            organization_coordsys_id INTEGER, definition TEXT, description TEXT);
        CREATE TABLE gpkg_contents (table_name TEXT PRIMARY KEY, data_type TEXT, identifier TEXT, srs_id INTEGER);
        CREATE TABLE gpkg_geometry_columns (table_name TEXT, column_name TEXT, geometry_type_name TEXT,
            srs_id INTEGER, z TINYINT, m TINYINT);
    """)
    con.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, '')",
                ("WGS 84 / UTM zone 19N", UTM, UTM, 'PROJCS["WGS 84 / UTM zone 19N",GEOGCS["WGS 84"]]'))
    con.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, '')",
                ("WGS 84", WGS84, WGS84, 'GEOGCS["WGS 84",DATUM["WGS_1984"]]'))
    for k, (name, (columns, rows)) in enumerate(layers.items()):
        con.execute(f"CREATE TABLE {name} ({columns}, geom BLOB)")
        con.execute("INSERT INTO gpkg_contents VALUES (?, 'features', ?, ?)", (name, name, srs))
        con.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', 'GEOMETRY', ?, 0, 0)", (name, srs))
        marks = ", ".join("?" * (len(rows[0])))
        con.executemany(f"INSERT INTO {name} VALUES ({marks})",
                        [(*r[:-1], _blob(geo(r[-1]), srs, envelope=k % 2 == 0)) for r in rows])
    con.commit()
    con.close()
