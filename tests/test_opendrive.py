"""OpenDRIVE export: maps that the ASAM OpenDRIVE checker passes, and that our own small reader (xml.etree) turns
back into the lane graph's lanes, widths, successor edges and centrelines, in right- and left-hand traffic."""

import functools
import logging
import math
import xml.etree.ElementTree as ET
from collections import Counter

import numpy as np
import pytest
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.data.frames import hd_poses
from cmtool.data.scene import SceneCropper
from cmtool.data.synth import generate_city
from cmtool.formats.importers import import_hd_map
from cmtool.formats.opendrive_export import to_opendrive, write_opendrive
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.neighbours import graph_neighbours, lane_widths
from tests.conftest import SHARED_DATA

ORIGIN = (42.36, -71.06)
HEADING = 30.0
CENTRELINE_MEAN_M = 0.1  # reconstructed lane centres from the lane graph's, mean over a scene: procedural scenes
CENTRELINE_MEAN_ANY_M = 0.5  # the same, any map (lanes of one road start and end up to 5 m apart in imported maps)

AV2 = {f"av2-{p.stem[-5:]}": p for p in sorted((SHARED_DATA / "av2").glob("*.json"))}
OSM = SHARED_DATA / "lanelet2" / "mapping_example.osm"
RULES = {"procedural": "RHT", "procedural-SGP": "LHT", "fork": "RHT", "fork-LHT": "LHT"}  # every road's traffic rule
MAPS = ["procedural", "procedural-SGP", "fork", "fork-LHT", *AV2, *(["lanelet2-example"] if OSM.is_file() else [])]


def line(*points, n: int = 10) -> np.ndarray:
    """A straight line (two points) or a quadratic Bézier curve (three) with ``n`` points."""
    p = np.array(points, np.float64)
    t = np.linspace(0.0, 1.0, n)[:, None]
    if len(p) == 2:
        return p[0] + t * (p[1] - p[0])
    return (1 - t) ** 2 * p[0] + 2 * t * (1 - t) * p[1] + t**2 * p[2]


def fork_scene(mirrored: bool = False) -> LaneGraph:
    """A two-way road forking into a two-way road and a right turn, with a green and a red light; ``mirrored``: its
    mirror image (left-hand traffic, a left turn), still labelled Boston (the geometry, not the city, decides)."""
    lanes = [line((-30, -1.75), (0, -1.75)), line((0, -1.75), (30, -1.75)), line((0, -1.75), (8, -1.75), (8, -12)),
             line((0, 1.75), (-30, 1.75)), line((30, 1.75), (0, 1.75))]
    flip = np.array([1.0, -1.0 if mirrored else 1.0])
    return LaneGraph(lanes=[lane * flip for lane in lanes], successors=[(0, 1), (0, 2), (4, 3)],
                     green_lights=[line((-29, -1.75), (-20, -1.75)) * flip],
                     red_lights=[line((30, 1.75), (20, 1.75)) * flip], city="BOS")


def crops(hd, n: int = 2) -> list[LaneGraph]:
    cropper = SceneCropper(hd)
    return [cropper.extract(pose, num_lines=300, num_lights=50).to_lanegraph()
            for pose in hd_poses(hd, n, np.random.default_rng(1))]


@functools.cache
def lane_graphs(name: str) -> list[LaneGraph]:
    """Ground truth of a procedural city (Boston, right-hand; Singapore, left-hand), the fork scene (or its mirror
    image), or crops of an Argoverse 2 map or the Lanelet2 example."""
    if name.startswith("procedural"):
        return crops(generate_city(name.partition("-")[2] or "BOS", seed=2, extent=300.0))
    if name.startswith("fork"):
        return [fork_scene(mirrored=name == "fork-LHT")]
    return crops(import_hd_map("av2", AV2[name]) if name in AV2 else import_hd_map("lanelet2", OSM))


@pytest.fixture(scope="module")
def qc_check():
    """The ASAM OpenDRIVE checker bundle (``asam-qc-opendrive``), run in process as its ``qc_opendrive`` application
    runs it: path -> [(level, checker id, description)] of its issues, a checker that crashed at level "CRASH". It
    runs the schema check and the rules defined up to the file's version (1.6); later rules report "skipped"."""
    pytest.importorskip("qc_opendrive")
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    from qc_baselib import Configuration, Result, StatusType
    from qc_opendrive import constants
    from qc_opendrive.main import run_checks

    root.handlers[:] = handlers  # importing qc_opendrive.main configured the root logger
    root.setLevel(level)

    def check(path):
        config = Configuration()
        config.set_config_param("InputFile", str(path))
        result = Result()
        result.register_checker_bundle(name=constants.BUNDLE_NAME, description="OpenDRIVE checker bundle",
                                       version=constants.BUNDLE_VERSION, summary="")
        run_checks(config, result)
        issues = []
        for checker in result.get_checker_results(constants.BUNDLE_NAME):
            if checker.status == StatusType.ERROR:
                issues.append(("CRASH", checker.checker_id, checker.summary))
            for issue in checker.issues:
                where = [loc.description for loc in issue.locations]
                issues.append((issue.level.name, checker.checker_id, f"{issue.description} {where}"))
        return issues

    return check


@pytest.mark.parametrize("name", MAPS)
def test_the_asam_checker_finds_no_errors(name, qc_check, tmp_path):
    for n, graph in enumerate(lane_graphs(name)):
        write_opendrive(graph, tmp_path / "map.xodr", *ORIGIN, HEADING)
        issues = qc_check(tmp_path / "map.xodr")
        errors = [i for i in issues if i[0] in ("ERROR", "CRASH")]
        warnings = [i for i in issues if i[0] == "WARNING"]
        print(f"{name} #{n} ({len(graph.lanes)} lanes): {len(errors)} errors, {len(warnings)} warnings {warnings[:3]}")
        assert not errors, f"{name} #{n}: {errors[:5]} (and {len(warnings)} warnings: {warnings[:5]})"


def carla_missing(xodr: str) -> set[tuple[int, int]]:
    """The driving lanes (road id, lane id) of an OpenDRIVE text that the ``carla`` wheel's offline map (no server)
    leaves out of its topology."""
    carla = pytest.importorskip("carla", reason="the carla wheel (test extra; Linux x86_64, Python 3.10 to 3.12)")
    root = ET.fromstring(xodr.encode())
    lanes = {(int(r.get("id")), int(l.get("id"))) for r in root.iter("road") for l in r.iter("lane")
             if l.get("type") == "driving"}
    seen = {(w.road_id, w.lane_id) for pair in carla.Map("cmtool", xodr).get_topology() for w in pair}
    return lanes - seen


def carla_routes(graph) -> set[tuple[int, int]]:
    """The ordered pairs of lanes (lane graph indices, from each lane's ``cmtool:lane`` user data) that a route
    through the ``carla`` wheel's topology of the OpenDRIVE export joins."""
    carla = pytest.importorskip("carla", reason="the carla wheel (test extra; Linux x86_64, Python 3.10 to 3.12)")
    import networkx as nx

    xodr = to_opendrive(graph, *ORIGIN, HEADING)
    lane_of = {(int(road.get("id")), int(lane.get("id"))): int(data.get("value"))
               for road in ET.fromstring(xodr.encode()).iter("road") for lane in road.iter("lane")
               for data in lane.iter("userData") if data.get("code") == "cmtool:lane"}
    topology = nx.DiGraph()
    for a, b in carla.Map("cmtool", xodr).get_topology():
        if lane_of[(a.road_id, a.lane_id)] != lane_of[(b.road_id, b.lane_id)]:
            topology.add_edge(lane_of[(a.road_id, a.lane_id)], lane_of[(b.road_id, b.lane_id)])
    return {(u, v) for u in topology for v in nx.descendants(topology, u)}


def successor_routes(graph) -> set[tuple[int, int]]:
    """The ordered pairs of lanes that the lane graph's successor edges join (no lane changes, as CARLA's
    topology has none)."""
    import networkx as nx

    joins = nx.DiGraph([(int(i), int(j)) for i, j in graph.successors])
    return {(u, v) for u in joins for v in nx.descendants(joins, u) if u != v}


@pytest.mark.parametrize("name", MAPS)
def test_carla_routes_what_the_lane_graph_allows(name):
    """CARLA routes exactly the pairs the lane graph joins, also through connector lanes that several roads merge
    into (CARLA follows a connecting road's own links, so the export writes one per route through it)."""
    for n, graph in enumerate(lane_graphs(name)):
        assert carla_routes(graph) == successor_routes(graph), f"{name} #{n}"


@pytest.mark.parametrize("name", MAPS)
def test_carla_keeps_every_exported_lane_in_its_topology(name):
    for n, graph in enumerate(lane_graphs(name)):
        assert carla_missing(to_opendrive(graph, *ORIGIN, HEADING)) == set(), f"{name} #{n}"


@pytest.mark.parametrize("half", [32.0, 30.0, 20.0, 31.9])
def test_carla_keeps_the_lanes_of_a_straight_road_that_leads_nowhere(half):
    """A road of one straight geometry whose length a 32-bit float holds exactly (64 m: a composed map's road across
    the frame) or rounds up: its lanes, joined to nothing, stay in CARLA's topology."""
    x = np.linspace(-half, half, 20)
    graph = LaneGraph([np.stack([x[::-1], np.full(20, 1.65)], axis=1), np.stack([x, np.full(20, -1.65)], axis=1)],
                      widths=[3.3, 3.3], left_neighbors=[], oncoming=[(0, 1)])
    assert carla_missing(to_opendrive(graph, *ORIGIN, HEADING)) == set()


def test_carla_keeps_every_lane_and_route_of_whole_maps_and_of_generated_ones(tmp_path, capsys):
    from cmtool.formats.mapfile import read_lane_graphs
    from tests.conftest import in_process

    city = tmp_path / "city.json"
    generate_city("LAV", seed=3, extent=300.0).save(city)
    for path in (city, *AV2.values(), *([OSM] if OSM.is_file() else [])):
        (graph,) = read_lane_graphs(path)
        assert carla_missing(to_opendrive(graph, *ORIGIN, HEADING)) == set(), path
        assert carla_routes(graph) == successor_routes(graph), path
    code, _, err = in_process(capsys, "sample", "--from-hd", city, "--num", 6, "--steps", 10, "--no-log", "--quiet",
                              "--out", tmp_path / "maps")  # the shipped weights
    assert code == 0, err
    for path in sorted((tmp_path / "maps").glob("city_s*.json")):
        if not path.name.endswith(".gt.json"):
            (graph,) = read_lane_graphs(path)
            assert carla_missing(to_opendrive(graph, *ORIGIN, HEADING)) == set(), path
            assert carla_routes(graph) == successor_routes(graph), path


@pytest.mark.parametrize("name", MAPS)
def test_sumo_reads_every_export_without_errors(name, tmp_path):
    import subprocess

    from cmtool.formats.sumo import netconvert_path

    if netconvert_path() is None:
        pytest.skip("SUMO's netconvert is not installed (pip install eclipse-sumo)")
    for n, graph in enumerate(lane_graphs(name)):
        write_opendrive(graph, tmp_path / "map.xodr", *ORIGIN, HEADING)
        done = subprocess.run([netconvert_path(), "--opendrive-files", str(tmp_path / "map.xodr"), "-o",
                               str(tmp_path / "map.net.xml")], capture_output=True, text=True, timeout=120)
        errors = [line for line in (done.stdout + done.stderr).splitlines() if line.startswith("Error")]
        assert done.returncode == 0 and not errors, f"{name} #{n}: {errors[:3]}"


def read_xodr(path) -> dict:
    """Our own reader: {"geoReference": text, "roads": {id: road}, "connections": [(incoming road, connecting
    road, contact point, [(from, to)])]}; a road is {"junction", "length", "links" {tag: (elementType, elementId,
    contactPoint)}, "rule", "geometry" [(s, x, y, hdg, length)], "lanes" {lane id: lane}, "signals" [attributes]} and a
    lane {"lane" (its lane graph index), "width", "predecessor" [lane ids], "successor" [lane ids]}."""
    root = ET.parse(path).getroot()
    roads = {road.get("id"): {
        "junction": road.get("junction"),
        "length": float(road.get("length")),
        "rule": road.get("rule", "RHT"),
        "links": {e.tag: tuple(e.get(k) for k in ("elementType", "elementId", "contactPoint"))
                  for e in road.findall("link/*")},
        "geometry": [tuple(float(g.get(k)) for k in ("s", "x", "y", "hdg", "length")) for g in road.iter("geometry")],
        "lanes": {int(lane.get("id")): read_lane(lane) for lane in road.iter("lane") if lane.get("type") == "driving"},
        "signals": [dict(s.attrib) for s in road.iter("signal")],
    } for road in root.iter("road")}
    connections = [(c.get("incomingRoad"), c.get("connectingRoad"), c.get("contactPoint"),
                    [(int(link.get("from")), int(link.get("to"))) for link in c.iter("laneLink")])
                   for c in root.iter("connection")]
    return {"geoReference": root.find("header/geoReference").text, "roads": roads, "connections": connections}


def read_lane(lane: ET.Element) -> dict:
    return {"lane": int(lane.find("userData[@code='cmtool:lane']").get("value")),
            "width": float(lane.find("width").get("a")),
            **{tag: [int(e.get("id")) for e in lane.findall(f"link/{tag}")] for tag in ("predecessor", "successor")}}


def runs_along(road: dict, lane_id: int) -> bool:
    """Whether traffic on a lane runs along its road's reference line: right lanes in RHT, left lanes in LHT."""
    return (lane_id < 0) == (road["rule"] == "RHT")


def leaves_at(road: dict, lane_id: int, end: str) -> bool:
    """Whether traffic on a lane leaves its road at ``end``."""
    return runs_along(road, lane_id) == (end == "end")


def successor_edges(xodr: dict) -> set[tuple[int, int]]:
    """Lane graph successor edges from the road links with their lane links, and from the junctions' lane links."""
    roads, edges = xodr["roads"], set()
    for road in roads.values():
        for tag, end in (("predecessor", "start"), ("successor", "end")):
            kind, other, _ = road["links"].get(tag, (None, None, None))
            for lane_id, lane in road["lanes"].items() if kind == "road" else ():
                for k in lane[tag]:
                    a, b = lane["lane"], roads[other]["lanes"][k]["lane"]
                    edges.add((a, b) if leaves_at(road, lane_id, end) else (b, a))
    for incoming, connecting, contact, lane_links in xodr["connections"]:
        for a, b in lane_links:
            outer, inner = roads[incoming]["lanes"][a]["lane"], roads[connecting]["lanes"][b]["lane"]
            edges.add((inner, outer) if leaves_at(roads[connecting], b, contact) else (outer, inner))
    return edges


def centrelines(xodr: dict, heading: float, samples: int = 40) -> dict[int, np.ndarray]:
    """Lane graph index -> the lane's centre (reference line plus lane offsets) in the scene frame, in its direction."""
    yaw = math.radians(90.0 - heading)
    to_scene = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])  # rows: east, north
    out = {}
    for road in xodr["roads"].values():
        geometry = np.array(road["geometry"])
        s = np.linspace(0.0, road["length"], samples)
        g = geometry[np.clip(np.searchsorted(geometry[:, 0], s, side="right") - 1, 0, len(geometry) - 1)]
        hdg = g[:, 3]
        along = g[:, 1:3] + (s - g[:, 0])[:, None] * np.stack([np.cos(hdg), np.sin(hdg)], 1)
        normal = np.stack([-np.sin(hdg), np.cos(hdg)], 1)
        for lane_id, lane in road["lanes"].items():
            inner = sum(road["lanes"][k]["width"] for k in road["lanes"] if 0 < k / lane_id < 1)
            points = (along + math.copysign(inner + 0.5 * lane["width"], lane_id) * normal) @ to_scene
            out[lane["lane"]] = points if runs_along(road, lane_id) else points[::-1]
    return out


def mean_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean distance between two polylines (from the points of each to the other line)."""
    la, lb = shapely.LineString(a), shapely.LineString(b)
    return 0.5 * (shapely.distance(shapely.points(a), lb).mean() + shapely.distance(shapely.points(b), la).mean())


def runs_backwards(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether polyline a runs against b: its ends lie nearer b's opposite ends than b's own."""
    return np.linalg.norm(a[[0, -1]] - b[[-1, 0]]) < np.linalg.norm(a[[0, -1]] - b[[0, -1]])


@pytest.mark.parametrize("name", MAPS)
def test_round_trip_keeps_lanes_widths_successors_and_centrelines(name, tmp_path):
    for n, graph in enumerate(lane_graphs(name)):
        write_opendrive(graph, tmp_path / "map.xodr", *ORIGIN, HEADING)
        xodr = read_xodr(tmp_path / "map.xodr")
        assert xodr["geoReference"].startswith(f"+proj=tmerc +lat_0={ORIGIN[0]:.9f} +lon_0={ORIGIN[1]:.9f} ")
        lanes = [lane for road in xodr["roads"].values() for lane in road["lanes"].values()]
        assert sorted({lane["lane"] for lane in lanes}) == list(range(len(graph.lanes))), f"#{n}"
        written = Counter(tuple((k, lane["lane"]) for k, lane in road["lanes"].items()) for road in xodr["roads"].values())
        assert all(road["junction"] != "-1" for road in xodr["roads"].values()
                   if written[tuple((k, lane["lane"]) for k, lane in road["lanes"].items())] > 1), \
            f"#{n}: only connecting roads are written more than once"
        widths = lane_widths(graph.lanes, graph_neighbours(graph)[0], graph.widths)
        assert [lane["width"] for lane in lanes] == pytest.approx([widths[lane["lane"]] for lane in lanes], abs=1e-3)
        assert successor_edges(xodr) == {(int(i), int(j)) for i, j in graph.successors}, f"#{n}"
        roads = xodr["roads"]
        if name in RULES:
            assert {road["rule"] for road in roads.values()} == {RULES[name]}, f"#{n}"
        for rid, road in roads.items():  # no road link between connecting roads; the other road links back
            for kind, other, contact in road["links"].values():
                if kind == "road":
                    assert roads[other]["junction"] == "-1" or road["junction"] == "-1", f"#{n}: road {rid}"
                    back = roads[other]["links"]["predecessor" if contact == "start" else "successor"]
                    assert back[0] == "junction" or back[1] == rid, f"#{n}: road {rid}"
        centres = centrelines(xodr, HEADING)
        assert not [k for k, lane in enumerate(graph.lanes) if runs_backwards(centres[k], np.asarray(lane))], f"#{n}"
        mean = np.mean([mean_distance(centres[k], lane) for k, lane in enumerate(graph.lanes)])
        print(f"{name} #{n}: lane centres {mean:.3f} m from the lane graph's (mean)")
        assert mean < (CENTRELINE_MEAN_M if name in RULES else CENTRELINE_MEAN_ANY_M), f"#{n}"


@pytest.mark.parametrize("rule", ["RHT", "LHT"])
def test_a_fork_goes_through_a_junction_and_lights_become_signals(rule, tmp_path):
    write_opendrive(fork_scene(mirrored=rule == "LHT"), tmp_path / "fork.xodr", *ORIGIN)
    xodr = read_xodr(tmp_path / "fork.xodr")
    roads = xodr["roads"]
    lane_ids = {lane["lane"]: lane_id for road in roads.values() for lane_id, lane in road["lanes"].items()}
    road_of = {lane["lane"]: rid for rid, road in roads.items() for lane in road["lanes"].values()}
    assert road_of[0] == road_of[3] and road_of[1] == road_of[4]  # two-way roads
    along = 1 if rule == "LHT" else -1  # the sign of the ids of lanes driving along the reference line
    assert {road["rule"] for road in roads.values()} == {rule} and lane_ids == {0: along, 1: along, 2: along,
                                                                               3: -along, 4: -along}
    incoming = road_of[0]
    assert roads[incoming]["junction"] == "-1" and roads[incoming]["links"]["successor"][0] == "junction"
    assert sorted(c[1] for c in xodr["connections"]) == sorted([road_of[1], road_of[2]])  # the roads leaving it
    assert all(roads[c[1]]["junction"] != "-1" and c[0] == incoming and c[2] == "start" for c in xodr["connections"])
    signals = {s["name"]: (rid, s) for rid, road in roads.items() for s in road["signals"]}
    assert set(signals) == {"traffic light green", "traffic light red"}
    rid, green = signals["traffic light green"]
    assert rid == road_of[0] and float(green["s"]) == 0.0 and float(green["t"]) == pytest.approx(along * 1.75)
    assert green["orientation"] == "+" and green["dynamic"] == "yes" and green["type"] == "1000001"
    rid, red = signals["traffic light red"]
    assert rid == road_of[4] and red["orientation"] == "-" and float(red["t"]) == pytest.approx(-along * 1.75)
    assert float(red["s"]) == pytest.approx(roads[rid]["length"])


@pytest.mark.parametrize("lanes, message", [
    ([], "no lanes to export"),
    ([line((0, 0), (10, 0)), np.array([[5.0, 5.0], [5.0, 5.0]])], "lane 1 has zero length"),
])
def test_bad_inputs_are_one_line_errors(lanes, message):
    with pytest.raises(CmtoolError) as error:
        to_opendrive(LaneGraph(lanes=lanes), *ORIGIN)
    assert str(error.value) == message
