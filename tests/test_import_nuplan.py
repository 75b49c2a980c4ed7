"""nuPlan importer on a small GeoPackage built here in the nuPlan map schema (tests/nuplan_fixture.py)."""

import sqlite3

import numpy as np
import pytest
from nuplan_fixture import CONNECTORS, LANES, build_gpkg, connector_line, lane_line

from cmtool.core.errors import CmtoolError
from cmtool.formats.importers import import_hd_map
from cmtool.maps.hdmap import HDMap


@pytest.fixture
def gpkg(tmp_path):
    path = tmp_path / "us-ma-boston" / "9.12.1817" / "map.gpkg"
    path.parent.mkdir(parents=True)
    build_gpkg(path)
    return path


def test_lanes_connectors_and_edges(gpkg):
    hd = import_hd_map("nuplan", gpkg)
    assert set(hd.lanes) == {f"l{f}" for f in LANES} | {f"c{f}" for f in CONNECTORS}
    edges = {(a, b) for a, lane in hd.lanes.items() for b in lane.successors}
    expected = set()
    for f, (exit_lane, entry_lane, _) in CONNECTORS.items():
        expected |= {(f"l{exit_lane}", f"c{f}"), (f"c{f}", f"l{entry_lane}")}
    assert edges == expected
    for a, b in edges:  # the edges join up geometrically
        assert np.linalg.norm(hd.lanes[a].centerline[-1] - hd.lanes[b].centerline[0]) < 1e-6
    assert hd.reference_errors() == []
    assert set(HDMap.from_json(hd.to_json()).lanes) == set(hd.lanes)


def test_intersection_flags_widths_and_neighbours(gpkg):
    hd = import_hd_map("nuplan", gpkg)
    for f in CONNECTORS:
        lane = hd.lanes[f"c{f}"]
        assert lane.is_intersection and lane.intersection_id == "7"
        np.testing.assert_allclose(lane.centerline, connector_line(f))
    for f in LANES:
        lane = hd.lanes[f"l{f}"]
        assert not lane.is_intersection and lane.intersection_id is None
        np.testing.assert_allclose(lane.centerline, lane_line(f))
        assert lane.width == pytest.approx(3.5)
    assert hd.lanes["c1"].width == pytest.approx(3.0)  # from its scaled-width polygon
    assert hd.lanes["c2"].width == pytest.approx(3.5)  # mean of the lanes it joins
    assert (hd.lanes["l1"].right_neighbor, hd.lanes["l2"].left_neighbor) == ("l2", "l1")
    assert (hd.lanes["l1"].left_neighbor, hd.lanes["l2"].right_neighbor) == (None, None)
    assert hd.lanes["l3"].right_neighbor == "l4" and hd.lanes["c1"].right_neighbor is None


def test_crosswalks_stop_lines_city(gpkg):
    hd = import_hd_map("nuplan", gpkg)
    assert len(hd.crosswalks) == 1
    assert sorted(map(tuple, hd.crosswalks[0].polygon)) == [(0, -6), (0, 6), (4, -6), (4, 6)]
    assert len(hd.stop_lines) == 1  # the stop-sign polygon is not a traffic light
    sl = hd.stop_lines[0]
    assert sorted(sl.lane_ids) == ["c1", "c2"] and sl.state == "unknown"
    np.testing.assert_allclose(sorted(map(tuple, sl.line)), [(-10, -3.5), (-10, 3.5)])
    assert hd.city == "BOS" and hd.drives_on == "right" and hd.source == "nuplan:map.gpkg"
    assert import_hd_map("nuplan", gpkg, city="LAV").city == "LAV"


def test_city_codes(tmp_path):
    for location, code in [("sg-one-north", "SGP"), ("us-pa-pittsburgh-hazelwood", "PIT"), ("elsewhere", "UNK")]:
        path = tmp_path / location / "map.gpkg"
        path.parent.mkdir()
        build_gpkg(path)
        hd = import_hd_map("nuplan", path)
        assert hd.city == code
        assert hd.drives_on == ("left" if code == "SGP" else "right")


def test_geographic_layers_are_projected(tmp_path):
    path = tmp_path / "map.gpkg"
    build_gpkg(path, geographic=True)
    hd = import_hd_map("nuplan", path)
    for f in LANES:
        c = hd.lanes[f"l{f}"].centerline
        assert np.linalg.norm(c[-1] - c[0]) == pytest.approx(40.0, rel=0.01)
        assert hd.lanes[f"l{f}"].width == pytest.approx(3.5, rel=0.01)
    a, b = hd.lanes["l1"].centerline[0], hd.lanes["l2"].centerline[0]
    assert np.linalg.norm(a - b) == pytest.approx(3.5, rel=0.01)


def test_errors(tmp_path, gpkg):
    with pytest.raises(CmtoolError, match="no such file"):
        import_hd_map("nuplan", tmp_path / "missing.gpkg")
    assert not (tmp_path / "missing.gpkg").exists()
    text = tmp_path / "log_map.json"
    text.write_text('{"lane_segments": {}}')
    with pytest.raises(CmtoolError, match=r"log_map\.json: not a readable GeoPackage"):
        import_hd_map("nuplan", text)
    plain = tmp_path / "plain.sqlite"
    sqlite3.connect(plain).execute("CREATE TABLE t (x)").connection.close()
    with pytest.raises(CmtoolError, match=r"plain\.sqlite: not a GeoPackage"):
        import_hd_map("nuplan", plain)
    con = sqlite3.connect(gpkg)
    con.execute("DELETE FROM gpkg_geometry_columns WHERE table_name = 'lane_connectors'")
    con.commit()
    con.close()
    with pytest.raises(CmtoolError, match=r"map\.gpkg: not a nuPlan map \(no 'lane_connectors' layer\)"):
        import_hd_map("nuplan", gpkg)
    with pytest.raises(CmtoolError, match=r"^unknown format 'gpkg' \(choose from av2, lanelet2, nuplan, apollo\)$"):
        import_hd_map("gpkg", gpkg)
