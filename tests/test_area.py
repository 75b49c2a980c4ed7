"""Whole areas (issue 46): tiles that cover an SD map's roads, lane graphs of tiles stitched into one, and
`cmtool sample --area` on a small OpenStreetMap file, exported and loaded in CARLA and Lanelet2."""

import json
import math
from collections import defaultdict

import cv2
import numpy as np
import pytest
import shapely
from rerun.chunk import RrdReader
from scipy.spatial import cKDTree

from cmtool.data.rules import rule_layout
from cmtool.data.scene import Pose
from cmtool.data.sd_raster import rasterize_sd
from cmtool.data.sd_trace import trace_sd
from cmtool.data.tiles import Tile, cover
from cmtool.formats.osm import read_osm
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.patch import complete, open_ends, prune, stranded, trim
from cmtool.maps.roadgraph import road_graph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.maps.stitch import JOIN_M, stitch
from cmtool.metrics.connectivity import routed_share, sd_end_pairs, unrouted
from cmtool.metrics.validity import check
from tests.conftest import REPO, in_process, interrupted_at

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
    centres = np.array([(t.x, t.y) for t in tiles])
    owner = cKDTree(centres).query(points)[1]
    hubs = np.array([k for k, t in enumerate(tiles) if t.reach > 0])
    assert len(hubs) and {tiles[k].reach for k in hubs} == {20.0}  # a tile on each junction, owning 20 m around it
    d, k = cKDTree(centres[hubs]).query(points)
    owner = np.where(d <= 20.0, hubs[k], owner)
    for p, t in zip(points, owner):  # the owning tile's frame holds every road point, 9 m inside its edge
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


def test_a_junction_tile_draws_its_junction_whole():
    """A tile on a junction owns every point within its reach (20 m), even where a road tile stands nearer: a lane
    through both is cut on that circle, not halfway between the centres (4 m from the junction)."""
    lane = straight(-1.75, -30, 30)
    tiles = [Tile(0.0, 0.0, 0.0, 20.0), Tile(8.0, 0.0, 0.0)]
    graph, seams = stitch([LaneGraph(lanes=[lane]), LaneGraph(lanes=[lane - (8.0, 0.0)])], tiles)
    assert not seams and len(graph.lanes) == 1  # the two pieces joined into one lane
    assert tiles[1].reach == 0.0
    graph, seams = stitch([LaneGraph(lanes=[lane]), LaneGraph(lanes=[])], tiles)
    assert len(seams) == 1 and seams[0].point[0] == pytest.approx(math.sqrt(20.0 ** 2 - 1.75 ** 2), abs=1e-3)


def test_sample_area_makes_one_map_that_exports_and_routes(tmp_path, capsys):
    code, out, err = in_process(capsys, "sample", "--osm", TOWN, "--area", BOX, "--steps", 8, "--sampler",
                                "dpm++2m-sde", "--quiet", "--out", tmp_path)
    assert code == 0, err
    assert "successor joins from" in out and "left open 0" in out
    doc = json.loads((tmp_path / "town_bos_area.json").read_text())
    area = doc["meta"]["area"]
    assert area["tiles"] >= 4 and area["lanes"] == len(doc["lanes"]) > 10
    assert area["open_seams"] == len(area["seams"]) == 0
    assert area["seams_disagreed"] == len(area["seams_disagreed_at"])
    assert area["sd_end_pairs_routed"] >= 0.9 and area["validity"] > 0.8 and area["sd_coverage"] > 0.9
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
    steps = defaultdict(set)  # entity -> the diffusion steps recorded: every tile denoises in its place
    for chunk in RrdReader(tmp_path / "area.rrd").stream():
        names = chunk.to_record_batch().schema.names
        if "diffusion_step" in names:
            steps[str(chunk.entity_path)] |= set(chunk.to_record_batch().column("diffusion_step").to_pylist())
    lanes = {p for p in steps if p.endswith("/diffusion/x0/lanes")}
    assert lanes == {f"/area/denoising/{k}/diffusion/x0/lanes" for k in range(area["tiles"])}
    assert all(len(steps[p]) >= 2 for p in lanes)
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


def test_the_rule_layout_completes_a_junction_the_tiles_left_unconnected():
    """The area's guarantee: a T junction whose road lanes the map has but whose turns it lacks gets the rule
    layout's connectors, joined to the road lanes, and then routes every pair of the SD road ends."""
    sd, box = t_junction()
    rules = rule_layout(sd, "right")
    roads = LaneGraph.from_hd(rules)
    roads = LaneGraph([l for l, n in zip(roads.lanes, rules.lanes.values()) if not n.in_intersection])  # no turns
    ends, pairs = sd_end_pairs(sd, box)
    assert len(ends) == 3 and len(pairs) == 6  # every end to both others
    assert routed_share(roads, ends, pairs) == 0.0
    graph, lent = complete(roads, rules, box)
    assert lent == 6 and len(graph.lanes) == len(roads.lanes) + 6
    assert routed_share(graph, ends, pairs) == 1.0 and check(graph).score == 1.0
    assert complete(graph, rules, box)[1] == 0  # nothing left to lend


def test_the_rule_layout_bridges_a_gap_between_lanes_that_do_not_meet():
    """A one-way road whose lanes two tiles drew 2.5 m apart and 4 m short of each other: the rule lane is lent
    between them, from the end of the first to the start of the second, and the road routes; where the second lane
    begins alongside the first, the lent piece merges into it, split there."""
    sd = SDMap(roads=[Road("a", np.array([[-60.0, 0.0], [60.0, 0.0]]), oneway=1)])
    box = (-50.0, -20.0, 50.0, 20.0)
    first, second = straight(0.0, -50.0, 2.0), straight(2.5, 6.0, 50.0)
    graph = LaneGraph(lanes=[first, second], successors=[])
    ends, pairs = sd_end_pairs(sd, box)
    assert pairs == [(0, 1)] and routed_share(graph, ends, pairs) == 0.0
    done, lent = complete(graph, rule_layout(sd, "right"), box)
    assert lent == 1 and len(done.lanes) == 3 and done.successors == [(0, 2), (2, 1)]
    assert np.allclose(done.lanes[2][[0, -1]], [first[-1], second[0]])
    assert routed_share(done, ends, pairs) == 1.0 and check(done).score == 1.0
    beside = straight(2.5, -20.0, 50.0)  # from x = -20: 22 m alongside the first lane, 4.5 m from it at most
    done, lent = complete(LaneGraph(lanes=[straight(-2.0, -50.0, 2.0), beside], successors=[]),
                          rule_layout(sd, "right"), box)
    assert lent == 1 and len(done.lanes) == 4 and done.successors == [(0, 3), (1, 2), (3, 2)]
    assert done.lanes[2][0, 0] == pytest.approx(8.0) and done.lanes[1][-1, 0] == pytest.approx(8.0)
    assert routed_share(done, ends, pairs) == 1.0 and check(done).score == 1.0


def test_traffic_stuck_on_the_way_between_two_road_ends_gets_the_rule_lane_there():
    """A one-way road whose two halves two tiles drew 5 m apart, unjoined: the pair of its ends is not routed;
    followed from its first end along the rule layout, the traffic is on the first half up to 2 m past its end and
    cannot reach the rule lane's end; the rule lane lent from there (leaving the first half's end) routes the
    pair."""
    sd = SDMap(roads=[Road("a", np.array([[-60.0, 0.0], [60.0, 0.0]]), oneway=1)])
    box, rules = (-50.0, -20.0, 50.0, 20.0), rule_layout(sd, "right")
    graph = LaneGraph(lanes=[straight(0.0, -50.0, 0.0), straight(5.0, 5.0, 50.0)], successors=[])
    ends, pairs = sd_end_pairs(sd, box)
    assert unrouted(graph, ends, pairs) == [(0, 1)]
    stuck = stranded(graph, rules, ends[[0]], 15.0, box)
    assert stuck == {0: (26, {0})}  # rule lane 0 (the road's only one) at x = 2 m (sample 26), on graph lane 0
    done, lent = complete(graph, rules, box, entries=(ends[[0]], 15.0))
    assert lent == 1 and not unrouted(done, ends, pairs) and (0, 2) in done.successors
    assert stranded(done, rules, ends[[0]], 15.0, box) == {}


def test_lanes_stop_at_the_sd_maps_dead_ends_and_branches_into_open_seams_go():
    """trim: a lane drawn 20 m past the end of a dead-end road is cut 2 m past it, a lane of the road beyond it is
    left alone; prune: a branch that leads only into an open seam is dropped, the lane it left is
    kept."""
    sd = SDMap(roads=[Road("stub", np.array([[0.0, 0.0], [40.0, 0.0]])),
                      Road("far", np.array([[70.0, -30.0], [70.0, 30.0]]))])
    over, far = straight(-1.5, 0.0, 60.0), np.array([[68.0, -30.0], [68.0, 30.0]])
    graph, cut = trim(LaneGraph(lanes=[over, far], successors=[]), sd)
    assert cut == 1 and graph.lanes[0][-1, 0] == pytest.approx(42.0, abs=0.01)
    assert np.array_equal(graph.lanes[1], far) and graph.lanes[0][0, 0] == 0.0
    road, branch, on = straight(0.0, 0.0, 30.0), straight(0.0, 30.0, 40.0), straight(0.0, 30.0, 60.0)
    seam = branch[-1]
    pruned, gone = prune(LaneGraph(lanes=[road, branch, on], successors=[(0, 1), (0, 2)]), seam[None])
    assert gone == 1 and len(pruned.lanes) == 2 and pruned.successors == [(0, 1)]
    assert len(open_ends(pruned, seam[None])) == 0
    alone, gone = prune(LaneGraph(lanes=[road, branch], successors=[(0, 1)]), seam[None])
    assert gone == 2 and not alone.lanes  # every way on ends at the seam: the whole chain goes


def t_junction():
    sd = SDMap(roads=[Road("a", np.array([[-60.0, 0.0], [0.0, 0.0], [60.0, 0.0]])),
                      Road("b", np.array([[0.0, 0.0], [0.0, -60.0]]))])
    return sd, (-50.0, -50.0, 50.0, 50.0)


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
    real = interrupted_at(monkeypatch, area_module, "write_jsonl", 3)  # as the third batch is kept
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "broken")  # Ctrl-C, as the CLI reports it
    assert code == 130, err
    cache = tmp_path / "broken" / ".town_bos_area.tiles"
    assert len(list(cache.glob("b*.jsonl"))) == 2 and not (tmp_path / "broken" / "town_bos_area.json").exists()
    monkeypatch.setattr(area_module, "write_jsonl", real)
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "broken")
    assert code == 0 and "resuming: 8 of" in err, err
    assert not cache.exists()
    whole = json.loads((tmp_path / "whole" / "town_bos_area.json").read_text())
    resumed = json.loads((tmp_path / "broken" / "town_bos_area.json").read_text())
    assert resumed["lanes"] == whole["lanes"] and resumed["successors"] == whole["successors"]


def test_a_road_drawing_is_traced_into_an_sd_map(tmp_path):
    """Roads drawn as strokes: a crossing, a T and a ring alone. The strokes' lines come out as roads in metres
    (0.5 m a pixel, north up, about the picture's centre), meeting at an X and a T junction; the ring is one road."""
    img = np.zeros((400, 600), np.uint8)
    cv2.line(img, (20, 200), (580, 200), 255, 8)  # west - east, through the middle
    cv2.line(img, (300, 20), (300, 380), 255, 8)  # north - south: the X at the centre
    cv2.line(img, (450, 200), (450, 380), 255, 8)  # south from 75 m east: the T
    cv2.circle(img, (120, 90), 50, 255, 7)
    path = tmp_path / "drawing.png"
    cv2.imwrite(str(path), img)
    sd = trace_sd(path, 0.5, "SGP")
    graph = road_graph(sd)
    assert sd.city == "SGP" and len(sd.roads) == 7
    assert sorted((j.kind, *np.round(j.centre).tolist()) for j in graph.junctions) == [("T", 75.0, -0.0),
                                                                                       ("X", 0.0, -0.0)]
    ring = [r for r in sd.roads if np.allclose(r.polyline[0], r.polyline[-1])]
    assert len(ring) == 1 and shapely.LineString(ring[0].polyline).length == pytest.approx(2 * math.pi * 25, rel=0.05)
    assert len(graph.dead_ends) == 5


def test_an_sd_picture_larger_than_a_frame_keeps_directions_and_makes_an_area(tmp_path, capsys):
    """A 200 m picture of the town in the SD raster's colours (north up): traced, its one-way roads run the way the
    town's do and its lane counts are kept; `sample --sd PICTURE --area all` makes one map of it."""
    town = read_osm(TOWN)
    every = np.concatenate([r.polyline for r in town.roads])
    centre = 0.5 * (every.min(axis=0) + every.max(axis=0))
    picture = rasterize_sd(town, float(centre[0]), float(centre[1]), math.pi / 2, frame_m=200.0, size=400)
    cv2.imwrite(str(tmp_path / "town.png"), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    sd = trace_sd(tmp_path / "town.png")
    originals = [(shapely.LineString(r.travel_polyline() - centre), r) for r in town.roads]
    long = [r for r in sd.roads if shapely.LineString(r.polyline).length > 20]
    assert len(long) >= 10
    for road in long:
        line = road.travel_polyline()
        middle = shapely.Point(line[len(line) // 2])
        near, original = min(originals, key=lambda o: o[0].distance(middle))
        assert bool(road.oneway) == bool(original.oneway) and road.lanes == original.lanes
        at = near.project(middle)
        along = np.diff(shapely.get_coordinates(near.interpolate([max(at - 2, 0), min(at + 2, near.length)])), axis=0)
        assert not road.oneway or float(along[0] @ (line[-1] - line[0])) > 0
    code, out, err = in_process(capsys, "sample", "--sd", tmp_path / "town.png", "--area", "all", "--steps", 4,
                                "--sampler", "dpm++2m-sde", "--no-log", "--quiet", "--out", tmp_path / "out")
    assert code == 0 and "left open 0" in out, err
    area = json.loads((tmp_path / "out" / "town_area.json").read_text())["meta"]["area"]
    assert area["tiles"] > 10 and area["sd_end_pairs_routed"] >= 0.8
    code, _, err = in_process(capsys, "sample", "--sd", tmp_path, "--area", "all", "--out", tmp_path / "x")
    assert code == 1 and "one --sd file" in err
