"""Whole areas (issue 46): tiles that cover an SD map's roads, lane graphs of tiles stitched into one, and
`cmtool sample --area` on a small OpenStreetMap file, exported and loaded in CARLA and Lanelet2."""

import json
import math

import numpy as np
import pytest
import shapely
from scipy.spatial import cKDTree

from cmtool.data.scene import Pose
from cmtool.data.tiles import cover
from cmtool.formats.osm import read_osm
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.stitch import JOIN_M, stitch
from tests.conftest import REPO, in_process

TOWN = REPO / "sample_data" / "town_bos.osm"
BOX = "42.3560,-71.0640,42.3575,-71.0620"  # about 165 m x 167 m of the town's middle


def test_tiles_cover_every_road_point_with_a_core_and_stand_on_roads():
    sd = read_osm(TOWN)
    tiles = cover(sd)
    assert 20 < len(tiles) < 200
    roads = shapely.MultiLineString([r.polyline for r in sd.roads])
    assert max(shapely.distance(shapely.Point(t.x, t.y), roads) for t in tiles) < 8.0  # on a road or a junction
    every_metre = [shapely.line_interpolate_point(line, np.arange(0.0, line.length, 1.0)) for line in roads.geoms]
    points = np.concatenate([shapely.get_coordinates(p) for p in every_metre])
    nearest = cKDTree([(t.x, t.y) for t in tiles]).query(points)[1]
    for p, t in zip(points, nearest):  # the nearest tile's frame holds every road point, 9 m inside its edge
        pose = tiles[t]
        c, s = math.cos(pose.yaw), math.sin(pose.yaw)
        d = p - (pose.x, pose.y)
        assert max(abs(c * d[0] + s * d[1]), abs(-s * d[0] + c * d[1])) <= 32.0 - 9.0
    assert len(cover(sd, box=(-50.0, -50.0, 50.0, 50.0))) < len(tiles) / 3


def straight(y0: float, x0: float, x1: float) -> np.ndarray:
    return np.stack([np.linspace(x0, x1, 20), np.full(20, y0)], axis=1)


def test_stitch_joins_a_lane_two_tiles_drew_alike_and_reports_one_they_disagree_on():
    """Two tiles 40 m apart on a road along x: both drew the eastbound lane (1 m apart at their border), only the
    first drew the westbound one. The eastbound lane comes out as one lane through the seam; the westbound one
    ends at the seam, an open seam of the tile that drew it."""
    tiles = [Pose(0.0, 0.0, 0.0), Pose(40.0, 0.0, 0.0)]
    first = LaneGraph(lanes=[straight(-1.75, -30, 30), straight(1.75, 30, -30)], successors=[])
    second = LaneGraph(lanes=[straight(-0.75, -30, 30)], successors=[])
    graph, seams = stitch([first, second], tiles)
    east = [l for l in graph.lanes if l[-1, 0] > l[0, 0]]
    assert len(east) == 1 and east[0][0, 0] == pytest.approx(-30) and east[0][-1, 0] == pytest.approx(70)
    assert np.all(np.abs(np.diff(east[0][:, 1])) < 0.2)  # the 1 m step is faded out, no kink
    west = [l for l in graph.lanes if l[-1, 0] < l[0, 0]]
    assert len(west) == 1 and west[0][0, 0] == pytest.approx(20, abs=0.01)  # cut halfway between the centres
    assert len(seams) == 1 and seams[0].tile == 0 and seams[0].other == 1 and not seams[0].leaving
    far = LaneGraph(lanes=[straight(-1.75 + JOIN_M + 1, -30, 30)], successors=[])
    graph, seams = stitch([first, far], tiles, box=(-25.0, -20.0, 65.0, 20.0))
    assert len(seams) == 3  # too far apart to join: both ends of the eastbound cut stay open
    assert all(np.all(np.abs(l[:, 0] - 20.0) <= 45.0 + 1e-9) for l in graph.lanes)  # cut at the box's edges


def test_sample_area_makes_one_map_that_exports_and_routes(tmp_path, capsys):
    code, out, err = in_process(capsys, "sample", "--osm", TOWN, "--area", BOX, "--steps", 8, "--sampler",
                                "dpm++2m-sde", "--quiet", "--out", tmp_path)
    assert code == 0, err
    assert "successor joins from" in out and "open seams" in out
    doc = json.loads((tmp_path / "town_bos_area.json").read_text())
    area = doc["meta"]["area"]
    assert area["tiles"] >= 4 and area["lanes"] == len(doc["lanes"]) > 10
    assert area["open_seams"] == len(area["seams"]) and area["validity"] > 0.5 and area["sd_coverage"] > 0.8
    assert doc["meta"]["geo"]["heading"] == 90.0 and doc["meta"]["init"] == "rules"
    x0, y0, x1, y1 = area["box_m"]
    for lane in doc["lanes"]:
        p = np.array(lane)
        assert np.all((p[:, 0] >= x0 - 0.01) & (p[:, 0] <= x1 + 0.01) & (p[:, 1] >= y0 - 0.01) & (p[:, 1] <= y1 + 0.01))
    ends = np.array([p for lane in doc["lanes"] for p in (lane[0], lane[-1])])
    for seam in area["seams"]:  # every open seam is a lane end of the map, not at the box's edge
        assert np.min(np.linalg.norm(ends - seam["point"], axis=1)) < 0.01, seam
        assert min(seam["point"][0] - x0, x1 - seam["point"][0], seam["point"][1] - y0, y1 - seam["point"][1]) > 0.01
    assert (tmp_path / "town_bos_area.png").stat().st_size > 10_000
    verified = []
    for fmt, suffix in (("opendrive", "xodr"), ("lanelet2", "osm")):
        wheel = "carla" if fmt == "opendrive" else "lanelet2"
        try:
            __import__(wheel)
        except ImportError:
            continue
        code, out, err = in_process(capsys, "export", "--format", fmt, tmp_path / "town_bos_area.json", "--out",
                                    tmp_path / f"area.{suffix}", "--verify")
        assert code == 0 and "and nothing else" in out, err
        verified.append(fmt)
    if not verified:
        pytest.skip("neither the carla nor the lanelet2 wheel is installed (test extra)")
    code, _, err = in_process(capsys, "sample", "--osm", TOWN, "--area", BOX, "--center", "42.357,-71.063", "--out",
                              tmp_path / "x")
    assert code == 1 and "leave out --center" in err
    code, _, err = in_process(capsys, "sample", "--osm", TOWN, "--area", "1,2,3", "--out", tmp_path / "x")
    assert code == 1 and "LAT0,LON0,LAT1,LON1" in err


def test_lent_connectors_route_a_junction_the_tiles_left_unconnected():
    """The area's guarantee at junctions: a T junction whose road lanes the map has but whose turns it lacks gets
    the rule layout's connectors, joined to the road lanes, and then routes every pair of the SD road ends."""
    from cmtool.data.layouts import without_connectors
    from cmtool.data.rules import rule_layout
    from cmtool.maps.sdmap import Road, SDMap
    from cmtool.metrics.connectivity import routed_share, sd_end_pairs
    from cmtool.sample.area import lend_connectors

    sd = SDMap(roads=[Road("a", np.array([[-60.0, 0.0], [0.0, 0.0], [60.0, 0.0]])),
                      Road("b", np.array([[0.0, 0.0], [0.0, -60.0]]))])
    box, centre = (-50.0, -50.0, 50.0, 50.0), np.zeros(2)
    roads = LaneGraph.from_hd(without_connectors(rule_layout(sd, "right")))
    ends, pairs = sd_end_pairs(sd, box)
    assert len(ends) == 3 and len(pairs) == 6  # every end to both others
    assert routed_share(roads, ends, pairs) == 0.0
    graph, lent = lend_connectors(roads, sd, box, centre)
    assert lent == 6 and len(graph.lanes) == len(roads.lanes) + 6
    assert routed_share(graph, ends, pairs) == 1.0
    assert lend_connectors(graph, sd, box, centre)[1] == 0  # nothing left to lend


def test_an_area_of_an_hd_map_routes_in_carla(tmp_path, capsys):
    """`--from-hd MAP --area all`: the area of a procedural city, whose stitched lanes split into two abreast
    (OpenDRIVE then needs a junction there: CARLA keeps one successor per lane of a direct road link)."""
    pytest.importorskip("carla", reason="the carla wheel (test extra; Linux x86_64, Python 3.10 to 3.12)")
    from cmtool.data.synth import generate_city

    generate_city("LAV", seed=3, extent=300.0).save(tmp_path / "city.json")
    code, out, err = in_process(capsys, "sample", "--from-hd", tmp_path / "city.json", "--area", "all", "--steps", 8,
                                "--sampler", "dpm++2m-sde", "--quiet", "--out", tmp_path)
    assert code == 0, err
    code, out, err = in_process(capsys, "export", "--format", "opendrive", tmp_path / "city_area.json", "--origin",
                                "36.1,-115.2", "--out", tmp_path / "city.xodr", "--verify")
    assert code == 0 and "and nothing else" in out, err


def test_a_killed_area_run_goes_on_where_it_stopped(tmp_path, capsys, monkeypatch):
    """Finished batches of tiles wait in OUT/.NAME_area.tiles: the same command after a kill makes only the rest,
    and the map is the one an unbroken run makes; the folder is gone once the map is written."""
    import cmtool.sample.area as area_module

    args = ("sample", "--osm", TOWN, "--area", BOX, "--steps", 4, "--sampler", "dpm++2m-sde", "--batch", 4, "--raw")
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "whole")
    assert code == 0, err
    real, calls = area_module.batch_maps, []

    def dies_on_the_third_batch(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(area_module, "batch_maps", dies_on_the_third_batch)
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "broken")  # Ctrl-C, as the CLI reports it
    assert code == 130, err
    cache = tmp_path / "broken" / ".town_bos_area.tiles"
    assert len(list(cache.glob("b*.jsonl"))) == 2 and not (tmp_path / "broken" / "town_bos_area.json").exists()
    monkeypatch.setattr(area_module, "batch_maps", real)
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "broken")
    assert code == 0 and "resuming: 8 of" in err, err
    assert not cache.exists()
    whole = json.loads((tmp_path / "whole" / "town_bos_area.json").read_text())
    resumed = json.loads((tmp_path / "broken" / "town_bos_area.json").read_text())
    assert resumed["lanes"] == whole["lanes"] and resumed["successors"] == whole["successors"]
