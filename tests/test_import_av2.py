"""Argoverse 2 importer against the raw log-map JSON (parsed here independently with json/shapely)."""

import json
from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString, Polygon

from cmtool.core.errors import CmtoolError
from cmtool.formats.importers import import_hd_map
from cmtool.maps.hdmap import HDMap

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "av2"
FILES = sorted(DATA.glob("*.json")) if DATA.is_dir() else []
DRIVABLE = ("VEHICLE", "BUS")


def _xy(points):
    return [(p["x"], p["y"]) for p in points]


@pytest.fixture(scope="module", params=FILES, ids=lambda p: p.name[16:24])
def case(request):
    raw = json.loads(request.param.read_text())
    return request.param, raw, import_hd_map("av2", request.param)


def test_files_present():
    if not FILES:
        pytest.skip("shared AV2 data not available")
    assert len(FILES) == 3


def test_lanes_and_crosswalks_match_raw(case):
    path, raw, hd = case
    segs = raw["lane_segments"]
    drivable = {k for k, s in segs.items() if s["lane_type"] in DRIVABLE}
    assert set(hd.lanes) == drivable
    assert len(hd.lanes) == sum(s["lane_type"] in DRIVABLE for s in segs.values())
    assert len(hd.crosswalks) == len(raw["pedestrian_crossings"])
    for k in drivable:
        assert hd.lanes[k].is_intersection == segs[k]["is_intersection"]
        assert hd.lanes[k].lane_type == segs[k]["lane_type"].lower()
    assert hd.city == "PIT" and hd.drives_on == "right" and hd.source == f"av2:{path.name}"


def test_successors_match_raw(case):
    _, raw, hd = case
    segs = raw["lane_segments"]
    ok = {k for k, s in segs.items() if s["lane_type"] in DRIVABLE}
    pairs = {(k, str(j)) for k in ok for j in segs[k]["successors"] if str(j) in ok}
    pairs |= {(str(j), k) for k in ok for j in segs[k]["predecessors"] if str(j) in ok}
    edges = {(a, b) for a, lane in hd.lanes.items() for b in lane.successors}
    assert edges == pairs and len(edges) > 100
    assert {(a, b) for b, lane in hd.lanes.items() for a in lane.predecessors} == edges
    assert hd.reference_errors() == []


def test_neighbours_are_raw_neighbours_of_same_direction(case):
    _, raw, hd = case
    segs = raw["lane_segments"]
    count = 0
    for k, lane in hd.lanes.items():
        for side in ("left", "right"):
            n = getattr(lane, f"{side}_neighbor")
            if n is not None:
                count += 1
                assert n == str(segs[k][f"{side}_neighbor_id"])
                a, b = hd.lanes[k].centerline, hd.lanes[n].centerline
                assert np.dot(a[-1] - a[0], b[-1] - b[0]) > 0
    assert count > 10


def test_centerline_between_boundaries(case):
    _, raw, hd = case
    segs = raw["lane_segments"]
    off, inside = [], []
    for k, lane in hd.lanes.items():
        left, right = _xy(segs[k]["left_lane_boundary"]), _xy(segs[k]["right_lane_boundary"])
        pts = shapely.points(lane.centerline)
        dl, dr = shapely.distance(pts, LineString(left)), shapely.distance(pts, LineString(right))
        off.append(max(np.abs(dl - lane.width / 2).mean(), np.abs(dr - lane.width / 2).mean()))
        inside.append(shapely.covers(Polygon(left + right[::-1]).buffer(0.05), pts).mean())
    assert np.median(off) < 0.3 and np.percentile(off, 90) < 1.0
    assert np.mean(inside) > 0.98
    widths = np.array([lane.width for lane in hd.lanes.values()])
    assert 2.5 < np.median(widths) < 5.0


def test_crosswalk_polygon_from_edges(case):
    _, raw, hd = case
    first = next(iter(raw["pedestrian_crossings"].values()))
    cw = next(c for c in hd.crosswalks if c.id == str(first["id"]))
    expected = _xy(first["edge1"]) + _xy(first["edge2"])[::-1]
    np.testing.assert_allclose(cw.polygon, expected)
    assert Polygon(cw.polygon).is_valid


def test_round_trip_and_city_override(case):
    path, _, hd = case
    back = HDMap.from_json(hd.to_json())
    assert set(back.lanes) == set(hd.lanes)
    assert import_hd_map("av2", path, city="XYZ").city == "XYZ"


def test_errors(tmp_path):
    with pytest.raises(CmtoolError, match="no such file"):
        import_hd_map("av2", tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"lane_segments": {')
    with pytest.raises(CmtoolError, match=r"bad\.json: malformed JSON"):
        import_hd_map("av2", bad)
    other = tmp_path / "other.json"
    other.write_text('{"lanes": []}')
    with pytest.raises(CmtoolError, match=r"other\.json: not an Argoverse 2 map"):
        import_hd_map("av2", other)
    broken = tmp_path / "broken.json"
    broken.write_text('{"lane_segments": {"5": {"id": 5, "lane_type": "VEHICLE", "left_lane_boundary": []}}}')
    with pytest.raises(CmtoolError, match=r"broken\.json: lane segment 5: malformed"):
        import_hd_map("av2", broken)
    osm = tmp_path / "map.osm"
    osm.write_text("<osm version='0.6'></osm>")
    with pytest.raises(CmtoolError, match=r"map\.osm: malformed JSON"):
        import_hd_map("av2", osm)
    with pytest.raises(CmtoolError, match=r"^unknown format 'x' \(choose from av2, lanelet2, nuplan, apollo\)$"):
        import_hd_map("x", osm)
