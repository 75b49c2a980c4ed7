"""`cmtool export`: GeoJSON features that project back onto the scene; Lanelet2 maps that load back with
our importer and route in the `lanelet2` package (when installed)."""

import json
import math

import numpy as np
import pytest
import shapely
from pathlib import Path

from cmtool.core.geo import LocalProjection
from cmtool.core.geometry import resample
from cmtool.maps.lanegraph import LaneGraph, read_jsonl, write_jsonl
from tests.conftest import SHARED_DATA, in_process


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


def neighbours_scene():
    """Two lanes side by side, each cut into two successive pieces, an oncoming lane and a red light."""
    def line(x0, y0, x1, y1):
        return np.stack([np.linspace(x0, x1, 10), np.linspace(y0, y1, 10)], axis=-1)

    lanes = [line(-30, -1.75, 0, -1.75), line(0, -1.75, 30, -1.75), line(-30, -5.25, 0, -5.25),
             line(0, -5.25, 30, -5.25), line(30, 1.75, -30, 1.75)]
    return LaneGraph(lanes=lanes, successors=[(0, 1), (2, 3)], red_lights=[line(0, -1.75, 10, -1.75)])


def test_lanelet2_export_loads_back_with_our_importer(tmp_path, capsys):
    from cmtool.formats.importers import import_hd_map

    write_jsonl(tmp_path / "s.jsonl", [neighbours_scene()])
    code, out, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "s.jsonl", "--origin", "49.0,8.4",
                                "--out", tmp_path / "s.osm")
    assert code == 0, err
    assert "5 lanes, 2 successor joins, 2 lane-change neighbours, 0 oncoming pairs, 1 light lines" in out
    hd = import_hd_map("lanelet2", tmp_path / "s.osm")
    assert len(hd.lanes) == 5
    # the importer centres its projection on the nodes' mean: compare shapes relative to lane 0's start
    by_index = {i: hd.lanes[str(i + 1)] for i in range(5)}
    ref = neighbours_scene()
    origin_new, origin_old = by_index[0].centerline[0], ref.lanes[0][0]
    for i, lane in by_index.items():
        np.testing.assert_allclose(resample(lane.centerline, 10) - origin_new,
                                   (ref.lanes[i] - origin_old) @ np.array([[0.0, 1.0], [-1.0, 0.0]]), atol=0.05)
    assert by_index[0].successors == ["2"] and by_index[2].successors == ["4"] and not by_index[1].successors
    assert by_index[0].right_neighbor == "3" and by_index[3].left_neighbor == "2"  # shared bounds: lane changes
    assert len(hd.stop_lines) == 1 and hd.stop_lines[0].lane_ids == ["2"]


def test_lanelet2_export_warns_about_lanes_that_fail_validation(tmp_path, capsys):
    hairpin = np.array([[-32.0, 0.0], [0.0, 0.0], [0.5, 1.0], [-32.0, 1.5]])
    write_jsonl(tmp_path / "s.jsonl", [LaneGraph(lanes=[hairpin, np.array([[-32.0, -5.0], [32.0, -5.0]])])])
    code, out, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "s.jsonl", "--origin", "49,8",
                                "--out", tmp_path / "s.osm")
    assert code == 0 and "2 lanes" in out
    assert "warning: 1 of 2 lanes have validity problems (kink 1)" in err


def test_lanelet2_package_routes_the_exported_map(tmp_path):
    from cmtool.formats.lanelet2_export import write_lanelet2

    write_lanelet2(neighbours_scene(), tmp_path / "s.osm", 49.0, 8.4)
    lanelet_map, graph = lanelet2_routing(tmp_path / "s.osm", 49.0, 8.4)
    assert len(lanelet_map.laneletLayer) == 5 and len(lanelet_map.regulatoryElementLayer) == 1
    lane = {int(ll.attributes["cmtool:lane"]): ll for ll in lanelet_map.laneletLayer}
    following = {(i, int(f.attributes["cmtool:lane"])) for i, ll in lane.items() for f in graph.following(ll)}
    assert following == {(0, 1), (2, 3)}  # the lane graph's successor pairs
    assert graph.right(lane[0]) is not None and int(graph.right(lane[0]).attributes["cmtool:lane"]) == 2


def test_export_takes_the_origin_from_meta_geo_and_refuses_bad_inputs(tmp_path, capsys):
    graph = scene()
    graph.meta["geo"] = {"lat": 60.5, "lon": 26.9, "heading": 90.0}
    write_jsonl(tmp_path / "s.jsonl", [graph, scene(), LaneGraph(lanes=[]),
                                       LaneGraph(lanes=[np.array([[1.0, 1.0], [1.0, 1.0]])])])
    code, out, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "s.jsonl",
                                "--out", tmp_path / "s.geojson")
    assert code == 0, err
    lane = json.loads((tmp_path / "s.geojson").read_text())["features"][0]["geometry"]["coordinates"]
    en = LocalProjection(60.5, 26.9).to_metres(*np.array(lane)[:, ::-1].T)
    np.testing.assert_allclose(en[[0, -1]], [[-30.0, -1.75], [0.0, -1.75]], atol=0.01)  # heading 90: forward is east
    for scene_no, message in ((1, "records no place on the globe (meta.geo); give --origin"),
                              (2, "scene 2 has no lanes to export"), (3, "lane 0 has no length")):
        code, _, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "s.jsonl", "--scene", scene_no,
                                  "--out", tmp_path / "x.osm")
        assert code == 1 and message in err and len(err.strip().splitlines()) == 1, err
    for origin in ("91,8", "49,200"):
        code, _, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "s.jsonl", "--origin", origin,
                                  "--out", tmp_path / "x.osm")
        assert code == 1 and "latitude must be within" in err
    code, _, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "s.jsonl", "--heading", "nan",
                              "--out", tmp_path / "x.osm")
    assert code == 2 and "not a finite number" in err
    (tmp_path / "one.jsonl").write_text('{"version": 1, "lanes": [[[0, 0]]]}\n')
    code, _, err = in_process(capsys, "export", "--format", "opendrive", tmp_path / "one.jsonl", "--origin", "49,8",
                              "--out", tmp_path / "x.osm")
    assert code == 1 and "lanes[0]: expected at least 2 points" in err
    assert not (tmp_path / "x.osm").exists()


def lanelet2_routing(path, lat0, lon0):
    """(map, routing graph) of an exported file as the `lanelet2` package loads it, for a vehicle in Germany."""
    lanelet2 = pytest.importorskip("lanelet2")
    from lanelet2.io import Origin
    from lanelet2.projection import UtmProjector

    lanelet_map, errors = lanelet2.io.loadRobust(str(path), UtmProjector(Origin(lat0, lon0)))
    assert errors == []
    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          lanelet2.traffic_rules.Participants.Vehicle)
    return lanelet_map, lanelet2.routing.RoutingGraph(lanelet_map, rules)


def lanelet2_routes(path, lat0, lon0):
    """Ordered lanelet pairs (by cmtool:lane) joined by a route with lane changes, as the `lanelet2` package's
    routing graph finds them."""
    lanelet_map, graph = lanelet2_routing(path, lat0, lon0)
    lane = {ll.id: int(ll.attributes["cmtool:lane"]) for ll in lanelet_map.laneletLayer}
    return {(lane[ll.id], lane[r.id]) for ll in lanelet_map.laneletLayer
            for r in graph.reachableSet(ll, 1e9, 0, True) if r.id != ll.id}


def source_routes(graph):
    """Ordered lane pairs joined by successor edges and lane changes of the lane graph (a plain search)."""
    from cmtool.metrics.validity import lane_changes

    adj = {i: set() for i in range(len(graph.lanes))}
    for i, j in list(graph.successors) + lane_changes(graph):
        adj[i].add(j)
    routes = set()
    for start in adj:
        seen, stack = {start}, [start]
        while stack:
            for k in adj[stack.pop()] - seen:
                seen.add(k)
                stack.append(k)
        routes |= {(start, k) for k in seen - {start}}
    return routes


def real_and_procedural_maps():
    from cmtool.data.synth import generate_city
    from cmtool.formats.importers import import_hd_map

    for path in sorted((SHARED_DATA / "av2").glob("*.json")):
        yield "av2", import_hd_map("av2", path)
    yield "lanelet2", import_hd_map("lanelet2", SHARED_DATA / "lanelet2" / "mapping_example.osm")
    for city in ("BOS", "SGP"):
        yield city, generate_city(city, seed=3, extent=400.0)


def test_lanelet2_routes_lane_changes_and_junctions_as_the_source_allows(tmp_path):
    """Ground-truth crops of real Argoverse 2 and Lanelet2 maps and procedural cities, exported: the `lanelet2`
    routing graph routes what the lane graph allows (successors and lane changes between the source's
    neighbours). It never routes more; it may route a little less where a short piece at the frame border does not
    start abreast of its neighbour, or a lane turns tighter than half its width."""
    pytest.importorskip("lanelet2")
    from cmtool.data.frames import hd_poses
    from cmtool.data.scene import SceneCropper
    from cmtool.formats.lanelet2_export import write_lanelet2
    from cmtool.metrics.validity import lane_changes

    totals = {}
    for name, hd in real_and_procedural_maps():
        cropper = SceneCropper(hd)
        for pose in hd_poses(hd, 4, np.random.default_rng(0)):
            graph = cropper.extract(pose, num_lines=300, num_lights=50).to_lanegraph()
            write_lanelet2(graph, tmp_path / "rt.osm", 49.0, 8.4)
            routed, allowed = lanelet2_routes(tmp_path / "rt.osm", 49.0, 8.4), source_routes(graph)
            assert routed <= allowed
            t = totals.setdefault(name, [0, 0, 0])
            t[0], t[1], t[2] = t[0] + len(routed), t[1] + len(allowed), t[2] + len(lane_changes(graph))
    for name, (routed, allowed, changes) in totals.items():
        assert changes > 0, f"{name}: no lane changes in the crops"
        assert routed >= (1.0 if name in ("BOS", "SGP") else 0.97) * allowed, (name, routed, allowed)


def lanelet2_successors(path, lat0, lon0):
    """(lane count, successor pairs by cmtool:lane) as the `lanelet2` package's routing graph sees them (a lane
    exported as several lanelets counts once)."""
    lanelet_map, graph = lanelet2_routing(path, lat0, lon0)
    lane = {ll.id: int(ll.attributes["cmtool:lane"]) for ll in lanelet_map.laneletLayer}
    return len(set(lane.values())), {(lane[ll.id], lane[f.id]) for ll in lanelet_map.laneletLayer
                                     for f in graph.following(ll)}


def test_procedural_scenes_route_the_same_in_the_lanelet2_package(tmp_path):
    pytest.importorskip("lanelet2")
    from cmtool.data.frames import hd_poses
    from cmtool.data.scene import SceneCropper
    from cmtool.data.synth import generate_city
    from cmtool.formats.lanelet2_export import write_lanelet2

    for city in ("LAV", "SGP", "BOS"):
        hd = generate_city(city, seed=2, extent=300.0)
        cropper = SceneCropper(hd)
        for pose in hd_poses(hd, 2, np.random.default_rng(1)):
            graph = cropper.extract(pose, num_lines=300, num_lights=50).to_lanegraph()
            write_lanelet2(graph, tmp_path / "rt.osm", 1.3, 103.8)
            count, following = lanelet2_successors(tmp_path / "rt.osm", 1.3, 103.8)
            assert count == len(graph.lanes)
            assert following == {(int(i), int(j)) for i, j in graph.successors}


def test_procedural_scenes_keep_every_lane_and_successor_through_lanelet2(tmp_path):
    from cmtool.data.frames import hd_poses
    from cmtool.data.scene import SceneCropper
    from cmtool.data.synth import generate_city
    from cmtool.formats.importers import import_hd_map
    from cmtool.formats.lanelet2_export import write_lanelet2

    for city in ("SGP", "BOS"):  # SGP and BOS have forks and merges at their junctions
        hd = generate_city(city, seed=1, extent=300.0)
        cropper = SceneCropper(hd)
        for pose in hd_poses(hd, 2, np.random.default_rng(0)):
            graph = cropper.extract(pose, num_lines=300, num_lights=50).to_lanegraph()
            write_lanelet2(graph, tmp_path / "rt.osm", 1.3, 103.8)
            back = import_hd_map("lanelet2", tmp_path / "rt.osm")
            assert len(back.lanes) == len(graph.lanes)
            got = {(int(a) - 1, int(b) - 1) for a, lane in back.lanes.items() for b in lane.successors}
            assert got == {(int(i), int(j)) for i, j in graph.successors}


def test_ground_truth_of_a_lanelet2_map_exports_back_where_it_lies(tmp_path, capsys):
    """`sample --from-hd` of an imported Lanelet2 map knows where its frame lies: exported without --origin,
    the ground truth's lanes land on the source map's own lat/lon."""
    from cmtool.formats.importers import import_hd_map
    from cmtool.sample.inputs import hd_inputs

    hd = import_hd_map("lanelet2", SHARED_DATA / "lanelet2" / "mapping_example.osm")
    hd.save(tmp_path / "kar.json")
    lane = next(iter(hd.lanes.values()))
    x, y = lane.centerline[0]
    truth = hd_inputs(tmp_path / "kar.json", [(x, y, 30.0)])[0].truth
    assert truth.meta["geo"]["heading"] == 60.0
    write_jsonl(tmp_path / "gt.jsonl", [truth])
    code, _, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "gt.jsonl", "--out",
                              tmp_path / "gt.geojson")
    assert code == 0, err
    proj = LocalProjection(hd.meta["lat0"], hd.meta["lon0"])
    source = shapely.MultiLineString([l.centerline for l in hd.lanes.values()])
    lanes = [f for f in json.loads((tmp_path / "gt.geojson").read_text())["features"] if f["properties"]["kind"] == "lane"]
    assert len(lanes) == len(truth.lanes) > 5
    for f in lanes:
        lonlat = np.array(f["geometry"]["coordinates"])
        xy = proj.to_metres(lonlat[:, 1], lonlat[:, 0])
        assert shapely.distance(shapely.points(xy), source).max() < 0.05


def test_every_command_takes_every_map_that_holds_lanes(tmp_path, capsys):
    """Issue 43: HD maps of any source, and lane graphs, go into validate, export, metrics, data sd/raster/poses and
    sample --from-hd; files without lanes get one line saying what they are, and so do maps given to commands that
    read datasets (eval, ablate, train)."""
    from cmtool.data.synth import generate_city
    from cmtool.formats.mapfile import map_kind, read_hd_map, read_lane_graphs
    from cmtool.maps.hdmap import HDMap

    city = tmp_path / "city.json"
    hd = generate_city("LAV", seed=3, extent=300.0)
    hd.save(city)
    (graph,) = read_lane_graphs(city)
    assert len(graph.lanes) == len(hd.lanes) and graph.city == "LAV"
    assert len(graph.successors) == sum(len(lane.successors) for lane in hd.lanes.values())
    assert all(np.abs(lane).max() < graph.frame_m / 2 - 1.0 for lane in graph.lanes)  # the whole map inside its frame
    back = graph.to_hd()  # and back: the same lanes, links and lights
    assert back.reference_errors() == [] and len(back.lanes) == len(hd.lanes)
    assert sorted(len(lane.successors) for lane in back.lanes.values()) == \
        sorted(len(lane.successors) for lane in hd.lanes.values())
    renamed = {lane: f"l{k}" for k, lane in enumerate(hd.lanes)}  # each light controls the same lanes
    assert {(s.state, lane) for s in back.stop_lines for lane in s.lane_ids} == \
        {(s.state, renamed[lane]) for s in hd.stop_lines if s.state in ("green", "red") for lane in s.lane_ids}

    assert in_process(capsys, "validate", city)[0] == 0
    for fmt, suffix in (("lanelet2", "osm"), ("opendrive", "xodr"), ("geojson", "geojson")):
        code, out, err = in_process(capsys, "export", "--format", fmt, city, "--origin", "36.1,-115.2", "--out",
                                    tmp_path / f"city.{suffix}")
        assert code == 0, err
    code, _, err = in_process(capsys, "metrics", "--generated", city, "--reference", city, "--no-features", "--json",
                              tmp_path / "m.json")
    assert code == 0, err
    text = (tmp_path / "m.json").read_text()
    assert "NaN" not in text and "Infinity" not in text  # strict JSON: what no score exists for is null
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    for command in (("data", "sd", city, "--out", tmp_path / "sd.json"),
                    ("data", "raster", city, "--png", tmp_path / "sd.png"),
                    ("data", "poses", city, "--n", 2, "--out", tmp_path / "poses.jsonl"),
                    ("sample", "--from-hd", city, "--steps", 3, "--no-log", "--quiet", "--out", tmp_path / "s")):
        code, _, err = in_process(capsys, *command)
        assert code == 0, (command, err)
    generated = tmp_path / "s" / "city.json"  # a lane graph of one frame goes wherever an HD map goes
    assert map_kind(generated)[0] == "lanegraph" and map_kind(city)[0] == "hdmap"
    assert len(read_hd_map(generated).lanes) == len(read_lane_graphs(generated)[0].lanes)
    for command in (("data", "sd", generated, "--out", tmp_path / "sd2.json"),
                    ("sample", "--from-hd", generated, "--steps", 3, "--no-log", "--quiet", "--out", tmp_path / "s2")):
        code, _, err = in_process(capsys, *command)
        assert code == 0, (command, err)

    # imported formats, read by content: an Argoverse 2 map and a Lanelet2 map, placed where they lie
    av2 = sorted((SHARED_DATA / "av2").glob("*.json"))[0]
    lanelet2 = sorted((SHARED_DATA / "lanelet2").glob("*.osm"))[0]
    assert map_kind(av2)[0] == "av2" and map_kind(lanelet2)[0] == "lanelet2"
    assert in_process(capsys, "validate", av2)[0] == 0
    code, out, err = in_process(capsys, "export", "--format", "opendrive", lanelet2, "--out", tmp_path / "l2.xodr")
    assert code == 0 and "heading 90" in out, err  # the import's projection origin, x east

    # files without lanes, and files of no map kind: one line each
    code, _, err = in_process(capsys, "validate", tmp_path / "sd.json")
    assert code == 1 and "an SD map (roads, no lanes)" in err and len(err.strip().splitlines()) == 1
    code, _, err = in_process(capsys, "export", "--format", "lanelet2", SHARED_DATA / "osm" / "finland_test.osm.pbf",
                              "--origin", "60,25", "--out", tmp_path / "x.osm")
    assert code == 1 and "an OpenStreetMap file (roads, no lanes)" in err
    two = tmp_path / "two.jsonl"
    write_jsonl(two, [graph, graph])
    code, _, err = in_process(capsys, "data", "sd", two, "--out", tmp_path / "x.json")
    assert code == 1 and "2 lane graphs; this command takes one map" in err
    (tmp_path / "list.json").write_text("[1, 2]")
    code, _, err = in_process(capsys, "validate", tmp_path / "list.json")
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert isinstance(HDMap.load(city), HDMap)
    for command in (("eval", "--data", city), ("ablate", "cfg", "--data", lanelet2), ("train", "dit", "--data", two)):
        code, _, err = in_process(capsys, *command, "--out", tmp_path / "x")  # they read datasets: say how to make one
        assert code == 2 and "is a map file" in err and "[[data.real_maps]]" in err, (command, err)

    # cmtool convert: between cmtool's own formats
    assert in_process(capsys, "convert", city, "--to", "lanegraph", "--out", tmp_path / "lg.json")[0] == 0
    assert read_jsonl(tmp_path / "lg.json")[0].to_json() == graph.to_json()
    assert in_process(capsys, "convert", tmp_path / "lg.json", "--to", "hdmap", "--out", tmp_path / "hd.json")[0] == 0
    assert len(HDMap.load(tmp_path / "hd.json").lanes) == len(hd.lanes)
    code, _, err = in_process(capsys, "convert", lanelet2, "--to", "hdmap", "--out", tmp_path / "kar.json")
    assert code == 0 and HDMap.load(tmp_path / "kar.json").city == "KAR", err
    code, _, err = in_process(capsys, "convert", city, "--to", "hdmap", "--out", city)
    assert code == 2 and "input is also its output" in err


def test_lanelet2_and_carla_route_exactly_what_the_lane_graph_allows(tmp_path, capsys):
    """Lanelet2 reads a lane as flowing into every lane whose start nodes its end nodes are, so a lane that ends
    where a fork starts would take every branch of it: the export gives such a branch a lanelet of its own for each
    group of lanes that may enter it (issue 43). On maps of the shipped weights, whose successors seldom form clean
    forks, the lane graph, Lanelet2's routing graph and CARLA's topology route the same pairs, and our importer
    reads the lane graph's successors back."""
    pytest.importorskip("lanelet2")
    from cmtool.formats.importers import import_hd_map
    from cmtool.formats.lanelet2_export import to_lanelet2, write_lanelet2
    from tests.test_opendrive import carla_routes, successor_routes

    def line(a, b):
        return np.linspace(a, b, 10)

    lanes = [line((0, 0), (10, 0)), line((10, -10), (10, 0)), line((10, 0), (20, 0)), line((10, 0), (10, 10))]
    graph = LaneGraph(lanes=lanes, successors=[(0, 2), (0, 3), (1, 2)])  # lane 1 may go on to 2, not to 3
    write_lanelet2(graph, tmp_path / "fork.osm", 49.0, 8.4)
    count, following = lanelet2_successors(tmp_path / "fork.osm", 49.0, 8.4)
    assert count == 4 and following == set(graph.successors)
    assert to_lanelet2(graph, 49.0, 8.4).count('k="type" v="lanelet"') == 5  # lane 2 once for lane 0, once for 1

    city = tmp_path / "city.json"
    from cmtool.data.synth import generate_city

    generate_city("PIT", seed=2, extent=300.0).save(city)
    code, _, err = in_process(capsys, "sample", "--from-hd", city, "--num", 6, "--steps", 10, "--no-log", "--quiet",
                              "--out", tmp_path / "maps")
    assert code == 0, err
    paths = [p for p in sorted((tmp_path / "maps").glob("city_s*.json")) if not p.name.endswith(".gt.json")]
    assert len(paths) == 6
    for path in paths:
        (generated,) = read_jsonl(path)
        write_lanelet2(generated, tmp_path / "g.osm", 49.0, 8.4)
        count, following = lanelet2_successors(tmp_path / "g.osm", 49.0, 8.4)
        allowed = {(int(i), int(j)) for i, j in generated.successors}
        assert count == len(generated.lanes) and following == allowed, path
        assert carla_routes(generated) == successor_routes(generated), path
        assert lanelet2_routes(tmp_path / "g.osm", 49.0, 8.4) <= source_routes(generated), path
        back = import_hd_map("lanelet2", tmp_path / "g.osm")
        assert len(back.lanes) == len(generated.lanes), path
        assert {(int(a) - 1, int(b) - 1) for a, lane in back.lanes.items() for b in lane.successors} == allowed, path


def test_a_lanelet2_round_trip_keeps_the_city_and_every_light(tmp_path, capsys):
    from cmtool.formats.importers import import_hd_map

    lanes = [np.linspace((0, 0), (30, 0), 10), np.linspace((30, 0), (60, 0), 10), np.linspace((30, 0), (30, 30), 10)]
    lights = {"green_lights": [lanes[1][:4], np.linspace((50, 20), (55, 20), 3)],  # the second controls no lane
              "red_lights": [lanes[2][:4]]}
    for city in ("SGP", None):
        graph = LaneGraph(lanes=lanes, successors=[(0, 1), (0, 2)], city=city, **lights)
        write_jsonl(tmp_path / "g.jsonl", [graph])
        assert in_process(capsys, "export", "--format", "lanelet2", tmp_path / "g.jsonl", "--origin", "1.3,103.8",
                          "--out", tmp_path / "g.osm")[0] == 0
        hd = import_hd_map("lanelet2", tmp_path / "g.osm")
        assert hd.city == (city or "") and hd.drives_on == ("left" if city == "SGP" else "right")
        assert sorted((s.state, len(s.lane_ids)) for s in hd.stop_lines) == [("green", 0), ("green", 1), ("red", 1)]
        back = LaneGraph.from_hd(hd)
        assert (len(back.green_lights), len(back.red_lights), back.city) == (2, 1, city)
    assert import_hd_map("lanelet2", SHARED_DATA / "lanelet2" / "mapping_example.osm").city == "KAR"


def sumo_traffic(net, tmp_path, seconds: int = 60) -> dict[str, int]:
    """SUMO's statistics after ``seconds`` of random trips on the network ``net`` (randomTrips.py, then sumo)."""
    import subprocess
    import sys
    import xml.etree.ElementTree as ET

    sumo = pytest.importorskip("sumo", reason="SUMO (the eclipse-sumo wheel, in the test extra)")
    tools = Path(sumo.SUMO_HOME) / "tools"
    trips, stats = tmp_path / "trips.xml", tmp_path / "stats.xml"
    subprocess.run([sys.executable, str(tools / "randomTrips.py"), "-n", str(net), "-o", str(trips), "-r",
                    str(tmp_path / "routes.rou.xml"), "-e", str(seconds // 2), "--validate", "--seed", "1"],
                   check=True, capture_output=True, timeout=120, cwd=tmp_path)
    done = subprocess.run([str(Path(sumo.SUMO_HOME) / "bin" / "sumo"), "-n", str(net), "-r", str(trips), "--end",
                           str(seconds), "--no-step-log", "--statistic-output", str(stats)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    root = ET.parse(stats).getroot()
    vehicles, safety, teleports = (root.find(tag).attrib for tag in ("vehicles", "safety", "teleports"))
    return {"inserted": int(vehicles["inserted"]), "arrived": int(vehicles["inserted"]) - int(vehicles["running"])
            - int(vehicles["waiting"]), "collisions": int(safety["collisions"]), "teleports": int(teleports["total"])}


def test_sumo_carries_traffic_on_an_exported_city_and_a_generated_map(tmp_path, capsys):
    from cmtool.data.synth import generate_city
    from cmtool.formats.sumo import netconvert_path

    if netconvert_path() is None:
        pytest.skip("SUMO's netconvert is not installed (pip install eclipse-sumo)")
    city = tmp_path / "city.json"
    generate_city("LAV", seed=3, extent=300.0).save(city)
    code, out, err = in_process(capsys, "export", "--format", "sumo", city, "--origin", "36.1,-115.2", "--out",
                                tmp_path / "city.net.xml")
    assert code == 0 and "SUMO network of 32 lanes" in out, err
    traffic = sumo_traffic(tmp_path / "city.net.xml", tmp_path)
    assert traffic["inserted"] > 0 and traffic["arrived"] > 0 and traffic["collisions"] == traffic["teleports"] == 0
    assert in_process(capsys, "data", "poses", city, "--n", 1, "--kind", "junction", "--out", tmp_path / "p.jsonl")[0] == 0
    code, _, err = in_process(capsys, "sample", "--from-hd", city, "--pose", tmp_path / "p.jsonl", "--steps", 10,
                              "--no-log", "--quiet", "--out", tmp_path / "maps")  # the shipped weights, at a junction
    assert code == 0, err
    (generated,) = [p for p in (tmp_path / "maps").glob("*.json") if not p.name.endswith(".gt.json")]
    code, _, err = in_process(capsys, "export", "--format", "sumo", generated, "--origin", "36.1,-115.2", "--out",
                              tmp_path / "gen.net.xml")
    assert code == 0, err
    traffic = sumo_traffic(tmp_path / "gen.net.xml", tmp_path, seconds=30)
    assert traffic["inserted"] > 0 and traffic["collisions"] == 0


def test_export_verify_holds_each_export_against_its_reader(tmp_path, capsys, monkeypatch):
    """`export --verify` loads the export in CARLA or Lanelet2 and says whether it routes as the lane graph does;
    an exporter that lets a lane graph's fork down (one lanelet per lane) is caught, with exit code 1."""
    pytest.importorskip("carla", reason="the carla wheel (test extra; Linux x86_64, Python 3.10 to 3.12)")
    pytest.importorskip("lanelet2")
    import cmtool.formats.lanelet2_export as lanelet2_export
    from cmtool.data.synth import generate_city

    generate_city("LAV", seed=3, extent=300.0).save(tmp_path / "city.json")
    for fmt, suffix, reader in (("opendrive", "xodr", "CARLA 0.9.16"), ("lanelet2", "osm", "Lanelet2 ")):
        code, out, err = in_process(capsys, "export", "--format", fmt, tmp_path / "city.json", "--origin",
                                    "36.1,-115.2", "--out", tmp_path / f"city.{suffix}", "--verify")
        assert code == 0, err
        assert f"{reader}" in out and "routes the lane graph's 32 successor joins and nothing else" in out

    lanes = [np.linspace((0, 0), (10, 0), 10), np.linspace((10, -10), (10, 0), 10), np.linspace((10, 0), (20, 0), 10),
             np.linspace((10, 0), (10, 10), 10)]
    write_jsonl(tmp_path / "fork.jsonl", [LaneGraph(lanes=lanes, successors=[(0, 2), (0, 3), (1, 2)])])
    args = ("export", "--format", "lanelet2", tmp_path / "fork.jsonl", "--origin", "49,8.4", "--out",
            tmp_path / "fork.osm", "--verify")
    assert in_process(capsys, *args)[0] == 0
    monkeypatch.setattr(lanelet2_export, "_lanelets", lambda n, successors: (
        list(range(n)), [((i, lanelet2_export.END), (j, lanelet2_export.START)) for i, j in sorted(successors)],
        successors))
    code, _, err = in_process(capsys, *args)
    assert code == 1 and "routes otherwise than the lane graph: 1 of its 3 successor joins not routed" in err
    code, _, err = in_process(capsys, "export", "--format", "geojson", tmp_path / "fork.jsonl", "--origin", "49,8.4",
                              "--out", tmp_path / "fork.geojson", "--verify")
    assert code == 1 and "--verify checks opendrive and lanelet2 exports, not geojson" in err


@pytest.mark.parametrize("fmt, suffix, wheel", [("opendrive", "xodr", "carla"), ("lanelet2", "osm", "lanelet2")])
def test_failed_export_verify_leaves_an_earlier_file(tmp_path, capsys, monkeypatch, fmt, suffix, wheel):
    """Issue 58: `export --verify` without the reader's wheel stops before any work with one line naming what to
    install, and a reader that routes otherwise fails the export: either way an earlier file stays byte for byte and
    no temporary is left beside it."""
    import sys
    import types

    import cmtool.formats.consumers as consumers

    write_jsonl(tmp_path / "s.jsonl", [neighbours_scene()])
    out = tmp_path / f"area.{suffix}"
    out.write_bytes(b"an earlier export\n")
    args = ("export", "--format", fmt, tmp_path / "s.jsonl", "--origin", "49,8.4", "--out", out, "--verify")
    monkeypatch.setitem(sys.modules, wheel, None)  # `import carla` fails as without the wheel
    code, _, err = in_process(capsys, *args)
    assert code == 1 and err.count("\n") == 1 and err.startswith("Error: --verify ") and "Traceback" not in err
    assert f"needs the {wheel} wheel: pip install -e '.[verify]' in a source checkout" in err
    assert out.read_bytes() == b"an earlier export\n"
    monkeypatch.setitem(sys.modules, wheel, types.ModuleType(wheel))  # a package of that name without the reader
    if fmt == "lanelet2":
        monkeypatch.setitem(sys.modules, "lanelet2.io", None)  # `from lanelet2.io import ...` fails
    code, _, err = in_process(capsys, *args)
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"the installed {wheel} is not" in err and "reinstall it" in err
    assert out.read_bytes() == b"an earlier export\n"
    # a reader that routes otherwise
    monkeypatch.setattr(consumers, "verify", lambda *a: consumers.Verdict("Reader 1", 4, [(0, 1)], [], []))
    code, _, err = in_process(capsys, *args)
    assert code == 1 and err.count("\n") == 1 and "routes otherwise than the lane graph" in err, err
    assert "(not written)" in err and out.read_bytes() == b"an earlier export\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name, "s.jsonl"]


def test_lanelet2_routes_two_lanes_that_meet_into_a_short_one(tmp_path, capsys):
    """Found on a stitched area map: two lane-change neighbours end at one point and go on into a 4 m lane, beside two
    lanes that start at one point. Sharing the neighbours' bound made the short lanelet's start corner its end corner,
    and Lanelet2 routed none of its joins; such a join of corners is refused."""
    pytest.importorskip("lanelet2")
    lanes = [[[-11.89, 5.73], [-7.04, 2.68], [-2.13, -0.29], [2.89, -3.07], [7.92, -5.83], [12.97, -8.56]],
             [[-11.89, 5.73], [-7.07, 2.81], [-2.18, -0.03], [2.81, -2.67], [7.9, -5.1], [13.04, -7.44]],
             [[-8.97, 8.85], [-4.9, 6.29], [-0.76, 3.86], [3.42, 1.49], [7.4, -1.2], [11.42, -3.83]],
             [[-9.74, 8.03], [-5.57, 5.54], [-1.37, 3.11], [2.86, 0.74], [7.13, -1.57], [11.42, -3.83]],
             [[11.42, -3.83], [11.75, -4.55], [12.07, -5.27], [12.39, -6.0], [12.72, -6.72], [13.04, -7.44]],
             [[13.04, -7.44], [32.89, -18.09], [52.19, -29.75], [71.73, -40.99], [91.25, -52.28], [110.51, -63.96]]]
    graph = LaneGraph(lanes=[np.array(l) for l in lanes], successors=[(0, 5), (1, 5), (2, 4), (3, 4), (4, 5)])
    (tmp_path / "meet.json").write_text(json.dumps(graph.to_json()))
    code, out, err = in_process(capsys, "export", "--format", "lanelet2", tmp_path / "meet.json", "--origin",
                                "60.53,26.95", "--out", tmp_path / "meet.osm", "--verify")
    assert code == 0 and "routes the lane graph's 5 successor joins and nothing else" in out, err
