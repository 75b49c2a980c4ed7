"""The command line as a user runs it: outputs, and one-line errors without tracebacks."""

import json

import numpy as np
import pytest
import shapely
from conftest import SHARED_DATA

from cmtool.data.scene import drivable_lanes
from cmtool.data.sd_derive import derive_sd
from cmtool.data.sd_raster import sd_raster_from_image
from cmtool.maps.hdmap import HDMap
from cmtool.maps.roadgraph import road_graph


def assert_one_line_error(result, *fragments):
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    for f in fragments:
        assert f in lines[0]


def test_synth_writes_a_loadable_map(run_cli, tmp_path):
    r = run_cli("data", "synth", "--city", "sgp", "--seed", "3", "--extent", "300", "--out", tmp_path / "c.json")
    assert r.returncode == 0, r.stderr
    hd = HDMap.load(tmp_path / "c.json")
    assert hd.city == "SGP" and hd.drives_on == "left" and len(hd.lanes) > 10
    assert "drives on the left" in r.stdout


def test_sd_derives_from_a_synth_map(run_cli, tmp_path):
    assert run_cli("data", "synth", "--city", "LAV", "--extent", "300", "--out", tmp_path / "c.json").returncode == 0
    r = run_cli("data", "sd", tmp_path / "c.json", "--out", tmp_path / "sd.json")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "sd.json").read_text())["format"] == "cmtool.sdmap"
    r = run_cli("data", "raster", tmp_path / "sd.json", "--png", tmp_path / "sd.png")
    assert r.returncode == 0, r.stderr
    image = sd_raster_from_image(tmp_path / "sd.png")
    assert image.shape == (128, 128, 3) and image[..., 0].any()
    assert set(np.unique(image[..., 0])) == {0, 255} and set(np.unique(image[..., 1])) <= {32 * k for k in range(8)}


def test_poses_lie_on_roads_beside_lanes_of_their_heading_and_near_a_junction(run_cli, tmp_path):
    assert run_cli("data", "synth", "--city", "PIT", "--extent", "300", "--out", tmp_path / "c.json").returncode == 0
    hd = HDMap.load(tmp_path / "c.json")
    lines = [shapely.LineString(l.centerline) for l in drivable_lanes(hd)]
    centres = road_graph(derive_sd(hd)).centres
    for near in (None, 8.0):
        r = run_cli("data", "poses", tmp_path / "c.json", "--n", 5, "--seed", 2,
                    *(() if near is None else ("--near-junction", near)))
        assert r.returncode == 0, r.stderr
        poses = [json.loads(line) for line in r.stdout.splitlines()]
        assert len(poses) == 5
        for p in poses:
            point = shapely.Point(p["x"], p["y"])
            headings = []
            for line in (line for line in lines if line.distance(point) < 4.0):  # the road's lanes
                s = line.project(point)
                a, b = line.interpolate(max(s - 0.5, 0)), line.interpolate(min(s + 0.5, line.length))
                headings.append(np.degrees(np.arctan2(b.y - a.y, b.x - a.x)))
            tol = 30.0 if p["kind"].startswith("junction") else 10.0  # road lines bend into junction nodes
            assert min(abs((h - p["yaw"] + 180) % 360 - 180) for h in headings) < tol, p  # a lane its way
            if near is not None:
                assert np.min(np.linalg.norm(centres - [p["x"], p["y"]], axis=1)) <= near + 0.01
                assert p["kind"].startswith("junction")
    assert_one_line_error(run_cli("data", "poses", tmp_path / "c.json", "--near-junction", 0, "--n", 3),
                          "found 0 of 3 poses within 0 m of a junction")


@pytest.mark.parametrize(
    "args, fragments",
    [
        (["data", "synth", "--city", "NYC", "--out", "x.json"], ["unknown city 'NYC'"]),
        (["data", "import", "--format", "shapefile", "x", "--out", "y.json"], ["--format", "shapefile"]),
        (["data", "import", "--format", "av2", "missing.json", "--out", "y.json"], ["missing.json", "no such file"]),
        (["data", "import", "--format", "lanelet2", "missing.osm", "--out", "y.json"], ["missing.osm"]),
        (["data", "stats", "missing.json"], ["missing.json: no such file"]),
        (["data", "build", "--recipe", "missing.toml", "--out", "d"], ["missing.toml"]),
        (["data", "show", "nodata", "--png", "g.png"], ["nodata"]),
    ],
)
def test_user_errors_are_one_line(run_cli, tmp_path, args, fragments):
    assert_one_line_error(run_cli(*args, cwd=tmp_path), *fragments)


def test_malformed_inputs_are_one_line(run_cli, tmp_path):
    (tmp_path / "bad.json").write_text('{"lane_segments": ')
    assert_one_line_error(run_cli("data", "import", "--format", "av2", "bad.json", "--out", "o.json", cwd=tmp_path),
                          "bad.json")
    assert_one_line_error(run_cli("data", "stats", "bad.json", cwd=tmp_path), "bad.json", "malformed JSON")
    (tmp_path / "bad.osm").write_text("<osm><node id='1' lat='1' lon='2'></osm>")
    assert_one_line_error(run_cli("data", "import", "--format", "lanelet2", "bad.osm", "--out", "o.json", cwd=tmp_path),
                          "bad.osm", "malformed XML")
    assert not (tmp_path / "o.json").exists()


def test_wrong_format_for_file(run_cli, tmp_path):
    lanelet = SHARED_DATA / "lanelet2" / "mapping_example.osm"
    if not lanelet.exists():
        pytest.skip("shared sample data not present")
    assert_one_line_error(run_cli("data", "import", "--format", "av2", lanelet, "--out", tmp_path / "o.json"),
                          "mapping_example.osm")
