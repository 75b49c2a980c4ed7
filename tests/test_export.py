"""`cmtool export --format geojson`: WGS84 features that project back onto the scene."""

import json
import math

import numpy as np
import pytest

from cmtool.data.geo import LocalProjection
from cmtool.data.lanegraph import LaneGraph, write_jsonl
from tests.conftest import in_process


def scene():
    lanes = [np.array([[-30.0, -1.75], [0.0, -1.75]]), np.array([[0.0, -1.75], [30.0, -1.75]]),
             np.array([[30.0, 1.75], [-30.0, 1.75]])]
    return LaneGraph(lanes=lanes, successors=[(0, 1)], green_lights=[np.array([[-2.0, -1.75], [5.0, -1.75]])],
                     city="LAV")


@pytest.mark.parametrize("heading", [0.0, 90.0])
def test_geojson_round_trips_to_the_scene(tmp_path, capsys, heading):
    write_jsonl(tmp_path / "s.jsonl", [scene()])
    code, out, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "s.jsonl", "--origin",
                                "49.0,8.4", "--heading", heading, "--out", tmp_path / "s.geojson")
    assert code == 0, err
    assert "3 lanes, 6 boundaries, 1 lights" in out
    fc = json.loads((tmp_path / "s.geojson").read_text())
    lanes = [f for f in fc["features"] if f["properties"]["kind"] == "lane"]
    assert lanes[0]["properties"]["successors"] == [1] and lanes[1]["properties"]["predecessors"] == [0]
    proj = LocalProjection(49.0, 8.4)
    yaw = math.radians(90.0 - heading)
    for f, lane in zip(lanes, scene().lanes):
        lonlat = np.array(f["geometry"]["coordinates"])
        en = proj.to_metres(lonlat[:, 1], lonlat[:, 0])
        rot = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])  # east/north -> scene
        np.testing.assert_allclose(en @ rot.T, lane, atol=0.01)
    left = next(f for f in fc["features"] if f["properties"] == {"kind": "boundary", "lane": 0, "side": "left"})
    en = proj.to_metres(*np.array(left["geometry"]["coordinates"])[:, ::-1].T)
    assert np.linalg.norm(en[0]) == pytest.approx(math.hypot(30.0, 0.0), abs=0.01)  # y = -1.75 + 1.75 = 0


def test_export_errors(tmp_path, capsys):
    write_jsonl(tmp_path / "s.jsonl", [scene()])
    code, _, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "s.jsonl", "--origin", "49.0",
                              "--out", tmp_path / "x.geojson")
    assert code == 1 and "expected LAT,LON" in err
    code, _, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "s.jsonl", "--origin", "49,8",
                              "--scene", 3, "--out", tmp_path / "x.geojson")
    assert code == 1 and "no scene 3 (1 scene)" in err and not (tmp_path / "x.geojson").exists()
