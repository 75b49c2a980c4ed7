"""The command line as a user runs it: outputs, and one-line errors without tracebacks."""

import json
from pathlib import Path

import numpy as np
import pytest
import shapely
from conftest import SHARED_DATA

from cmtool.data.scene import drivable_lanes
from cmtool.data.sd_derive import derive_sd
from cmtool.data.sd_raster import CLASS_VALUES, sd_raster_from_image
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
    assert set(np.unique(image[..., 0])) <= {0, *CLASS_VALUES}
    assert set(np.unique(image[..., 1])) <= {32 * k for k in range(8)}
    assert "SD raster of encoding 2 (R road class" in r.stdout


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


def test_input_of_the_wrong_kind_says_what_was_given_and_what_is_expected(run_cli, tmp_path):
    """Issue 58: a map where a picture is expected, a picture where a map is, and a point given as LON,LAT each end
    in one line that says what was given and what is expected."""
    import cv2

    from cmtool.data.synth import generate_city
    from cmtool.maps.lanegraph import LaneGraph

    generate_city("LAV", seed=0, extent=200.0).save(tmp_path / "city.json")
    (tmp_path / "map.json").write_text(json.dumps(LaneGraph(lanes=[np.array([[0.0, 0.0], [9.0, 0.0]])]).to_json()))
    cv2.imwrite(str(tmp_path / "roads.png"), np.full((64, 64), 255, np.uint8))
    assert_one_line_error(run_cli("sample", "--sd", "map.json", "--out", "o", cwd=tmp_path),
                          "map.json is a lane graph (JSON); --sd takes a picture (a PNG/JPG SD raster or road "
                          "drawing); for a map use --from-hd")
    assert_one_line_error(run_cli("sample", "--sd", "city.json", "--area", "all", "--out", "o", cwd=tmp_path),
                          "city.json is an HD map (JSON); --sd takes a picture")
    assert_one_line_error(run_cli("export", "--format", "opendrive", "roads.png", "--origin", "49,8", "--out", "a.xodr",
                                  cwd=tmp_path), "roads.png is a picture (PNG); this command takes a map file",
                          "for a map of a picture use `cmtool sample --sd`")
    osm = Path(__file__).resolve().parent / "fixtures" / "small.osm"  # roads at 40.44 N 79.99 W
    assert_one_line_error(run_cli("sample", "--osm", osm, "--center", "-79.9895,40.441", "--out", tmp_path / "o"),
                          "nearest road", "m away); did you swap latitude and longitude? (LAT,LON: 40.441,-79.9895)")
    assert not (tmp_path / "o").exists() and not (tmp_path / "a.xodr").exists()


def test_a_picture_that_is_not_square_is_padded_not_stretched(tmp_path):
    """Issue 58: a road drawing or SD raster that is not square is padded to a square, centred on the raster's
    background, so that its roads keep their shape; one note says how many pixels were added."""
    import cv2

    from cmtool.data.sd_raster import rasterize_sd
    from cmtool.maps.sdmap import Road, SDMap
    from cmtool.sample.inputs import image_inputs

    drawing = np.full((200, 400), 255, np.uint8)
    cv2.rectangle(drawing, (150, 50), (250, 150), 0, 8)  # a square block of dark roads on white paper, centred
    cv2.imwrite(str(tmp_path / "wide.png"), drawing)
    raster = rasterize_sd(SDMap(roads=[Road(id="r", polyline=np.array([[-40.0, 3.0], [40.0, -5.0]]), lanes=2)]),
                          0.0, 0.0, 0.0)
    cv2.imwrite(str(tmp_path / "tall.png"), cv2.cvtColor(np.ascontiguousarray(raster[:, 32:96]), cv2.COLOR_RGB2BGR))
    wide, tall = image_inputs([tmp_path / "wide.png", tmp_path / "tall.png"])
    rows, cols = np.nonzero(wide.sd[..., 0])
    assert abs((rows.max() - rows.min()) - (cols.max() - cols.min())) <= 1  # still a square
    assert abs((rows.max() + rows.min()) / 2 - 63.5) <= 1 and abs((cols.max() + cols.min()) / 2 - 63.5) <= 1
    assert wide.note.endswith("padded to 400 x 400 to keep the roads' shape (100 px of background above and below)")
    assert np.array_equal(tall.sd[:, 32:96], raster[:, 32:96]) and not tall.sd[:, :32].any()
    assert not tall.sd[:, 96:].any()
    assert "resampled the 64 x 128 SD raster" in tall.note and "(32 px of background left and right)" in tall.note
