from pathlib import Path

import numpy as np
import pytest
import shapely
from fixtures.hdmaps import add_road, connect_intersection, crossroads

from cmtool.core.geometry import from_frame
from cmtool.data.frames import hd_poses
from cmtool.data.scene import SceneCropper
from cmtool.data.sd_derive import MAPPED_CLASSES, SDJitter, derive_sd, mapped_classes, road_class, road_network
from cmtool.data.sd_raster import rasterize_sd
from cmtool.maps.hdmap import HDMap, Lane
from cmtool.maps.sdmap import SDMap
from tests.conftest import SHARED_DATA

AV2 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "av2"
BEYOND_M = 4.0  # a lane point is covered when at most this far outside an SD road taken as lanes x 3.5 m wide


def by_lanes(sd):
    return {r.lanes: r for r in sd.roads}


def beyond_roads(sd, points) -> np.ndarray:
    """Per point: its distance from the nearest SD road's edge, taking each road as ``lanes`` x 3.5 m wide."""
    pts = shapely.points(np.asarray(points, dtype=np.float64))
    return np.min([shapely.distance(pts, shapely.LineString(r.polyline)) - 1.75 * r.lanes for r in sd.roads], axis=0)


@pytest.mark.parametrize("kwargs", [
    {},  # procedural style: road_id and intersection_id set
    {"road_id": False, "pieces": 3},  # imported style: short lane pieces, no road ids
    {"road_id": False, "pieces": 3, "with_id": False},  # and connectors without intersection ids
])
def test_crossroads_gives_two_continuous_roads(kwargs):
    sd = derive_sd(crossroads(**kwargs))
    assert len(sd.roads) == 2
    roads = by_lanes(sd)
    assert set(roads) == {2, 4}
    ew, ns = roads[2], roads[4]
    assert ew.oneway == 0 and ns.oneway == 0
    assert (ew.road_class, ns.road_class) == ("residential", "secondary")
    # one polyline each, on the road's midline, running through the intersection
    assert np.abs(ew.polyline[:, 1]).max() < 0.3 and np.abs(ns.polyline[:, 0]).max() < 0.3
    assert np.ptp(ew.polyline[:, 0]) > 195 and np.ptp(ns.polyline[:, 1]) > 195
    for r in (ew, ns):
        assert shapely.LineString(r.polyline).distance(shapely.Point(0, 0)) < 0.3


def test_oneway_street_runs_in_travel_direction():
    hd = HDMap(city="TST")
    add_road(hd, "A", (100, 0), (12, 0), forward=2, backward=0)  # westbound one-way, two lanes
    add_road(hd, "B", (-12, 0), (-100, 0), forward=2, backward=0)
    add_road(hd, "S", (0, -100), (0, -12))
    add_road(hd, "N", (0, 12), (0, 100))
    connect_intersection(hd, "I", (0, 0))
    sd = derive_sd(hd)
    oneway = [r for r in sd.roads if r.oneway]
    assert len(sd.roads) == 2 and len(oneway) == 1
    west = oneway[0]
    assert west.oneway == 1 and west.lanes == 2
    assert west.polyline[0, 0] > 90 and west.polyline[-1, 0] < -90  # along travel (westwards)
    assert np.all(np.diff(west.polyline[:, 0]) < 0)
    assert np.abs(west.polyline[:, 1] - 3.5).max() < 0.3  # middle of its two lanes (right of travel = north)


def test_narrow_median_road_uses_the_midline():
    hd = HDMap(city="SGP")
    add_road(hd, "M", (0, 0), (200, 0), forward=2, backward=2, median=1.0, width=3.2)
    sd = derive_sd(hd)
    assert len(sd.roads) == 1
    r = sd.roads[0]
    assert (r.lanes, r.oneway, r.road_class) == (4, 0, "secondary")
    assert np.abs(r.polyline[:, 1]).max() < 0.3


def test_divided_road_is_two_one_way_ways():
    hd = HDMap(city="SGP")
    add_road(hd, "M", (0, 0), (200, 0), forward=2, backward=2, median=4.0, width=3.2)
    sd = derive_sd(hd, classes="lanes")
    assert len(sd.roads) == 2 and all((r.lanes, r.oneway, r.road_class) == (2, 1, "secondary") for r in sd.roads)
    for seed in range(8):  # classed as mappers tag: both carriageways alike
        assert len({r.road_class for r in derive_sd(hd, seed=seed).roads}) == 1
    east, west = sorted(sd.roads, key=lambda r: r.travel_polyline()[-1, 0], reverse=True)
    assert east.travel_polyline()[0, 0] < 1 and east.travel_polyline()[-1, 0] > 199  # travels east
    # right-hand traffic: the eastbound carriageway lies south, each line in the middle of its two lanes
    assert np.abs(east.polyline[:, 1] + 5.2).max() < 0.3 and np.abs(west.polyline[:, 1] - 5.2).max() < 0.3
    whole = road_network(hd, split_divided=False)
    assert len(whole.pieces) == 1 and (whole.pieces[0].lanes, whole.pieces[0].oneway) == (4, False)


def test_turns_do_not_continue_a_road():
    hd = HDMap(city="TST")
    add_road(hd, "W", (-100, 0), (-12, 0))
    add_road(hd, "N", (0, 12), (0, 100))
    add_road(hd, "E", (12, 0), (100, 0), forward=2, backward=2)  # different lane count
    connect_intersection(hd, "I", (0, 0))
    sd = derive_sd(hd)
    assert len(sd.roads) == 3
    net = road_network(hd)
    assert [p.ends for p in net.pieces] == [[None, "I"], ["I", None], ["I", None]]
    centre = net.intersections["I"]
    assert np.linalg.norm(centre) < 4.0  # centroid of the connector lanes
    for r in sd.roads:  # each way ends at the junction node, like OSM ways at a T-junction
        assert min(np.linalg.norm(r.polyline[[0, -1]] - centre, axis=1)) < 1e-9


def test_jitter():
    hd = crossroads()
    base = derive_sd(hd, classes="lanes")
    for other in (derive_sd(hd, classes="lanes"), derive_sd(hd, SDJitter(), classes="lanes"),
                  derive_sd(hd, None, seed=5, classes="lanes")):
        assert other.to_json() == base.to_json()
    moved = derive_sd(hd, SDJitter(offset_m=5.0), seed=3)
    assert moved.to_json() == derive_sd(hd, SDJitter(offset_m=5.0), seed=3).to_json()
    shifts = np.concatenate([m.polyline - b.polyline for m, b in zip(moved.roads, base.roads)])
    assert np.allclose(shifts, shifts[0]) and 0.0 < np.linalg.norm(shifts[0]) <= 5.0
    other = derive_sd(hd, SDJitter(offset_m=5.0), seed=4)
    assert not np.allclose(other.roads[0].polyline, moved.roads[0].polyline)
    turned = derive_sd(hd, SDJitter(rotation_deg=10.0), seed=1)
    for t, b in zip(turned.roads, base.roads):
        np.testing.assert_allclose(np.linalg.norm(np.diff(t.polyline, axis=0), axis=1),
                                   np.linalg.norm(np.diff(b.polyline, axis=0), axis=1))
        h_t = np.arctan2(*(t.polyline[-1] - t.polyline[0])[::-1])
        h_b = np.arctan2(*(b.polyline[-1] - b.polyline[0])[::-1])
        assert 0.0 < abs(np.degrees(h_t - h_b)) <= 10.0
    dropped = derive_sd(hd, SDJitter(drop_minor=1.0), classes="lanes")
    assert [r.road_class for r in dropped.roads] == ["secondary"]  # the residential road is gone


def test_derived_classes_follow_the_measured_distribution_of_real_osm():
    """Roads of two lanes both ways take their class from MAPPED_CLASSES, seeded: over 400 draws each class's share
    lies within 4 standard errors of the table's; the same seed gives the same classes, another seed others."""
    hd = HDMap(city="TST")
    for k in range(20):
        add_road(hd, f"R{k}", (0, 40 * k), (300, 40 * k), width=3.4)
    drawn = [r.road_class for seed in range(20) for r in derive_sd(hd, seed=seed).roads]
    assert len(drawn) == 400
    for name, share in MAPPED_CLASSES[2, False].items():
        assert abs(drawn.count(name) / 400 - share) <= 4 * np.sqrt(share * (1 - share) / 400) + 1e-9, name
    assert set(drawn) <= set(MAPPED_CLASSES[2, False])
    assert derive_sd(hd, seed=3).to_json() == derive_sd(hd, seed=3).to_json()
    assert [r.road_class for r in derive_sd(hd, seed=3).roads] != [r.road_class for r in derive_sd(hd, seed=4).roads]
    assert {r.road_class for r in derive_sd(hd, classes="lanes").roads} == {"residential"}


@pytest.mark.skipif(not (SHARED_DATA / "osm" / "finland_test.osm.pbf").is_file(), reason="no shared OSM extract here")
def test_the_class_table_is_the_one_measured_on_real_osm():
    from cmtool.formats.osm import read_osm

    assert mapped_classes(read_osm(SHARED_DATA / "osm" / "finland_test.osm.pbf")) == MAPPED_CLASSES


def test_road_class_rule():
    assert [road_class(n, 3.5) for n in (8, 6, 5, 4, 3, 2, 1)] == [
        "primary", "primary", "secondary", "secondary", "tertiary", "residential", "residential"]
    assert road_class(2, 2.5) == "service"


def test_derived_map_is_valid_json():
    sd = derive_sd(crossroads(road_id=False, pieces=2))
    back = SDMap.from_json(sd.to_json())
    assert [r.lanes for r in back.roads] == [r.lanes for r in sd.roads]


def test_empty_map():
    assert derive_sd(HDMap(city="X")).roads == []


def av2_maps() -> list:
    """The shared Argoverse 2 sample maps, imported, with their paths (the test is skipped without them)."""
    files = sorted(AV2.glob("*.json"))
    if not files:
        pytest.skip("shared Argoverse 2 sample data not available")
    importers = pytest.importorskip("cmtool.formats.importers")
    return [(path, importers.import_hd_map("av2", path)) for path in files]


def test_argoverse2_maps():
    for _, hd in av2_maps():
        sd = derive_sd(hd)
        SDMap.from_json(sd.to_json())  # valid: lane counts 1..16, classes known, finite points
        net = road_network(hd)
        assert len(net.intersections) >= 5
        road_lanes = sum(1 for l in hd.lanes.values() if not l.is_intersection)
        assert 5 <= len(sd.roads) < road_lanes / 3  # far fewer roads than lane pieces
        two_way = [r for r in sd.roads if r.oneway == 0]
        assert two_way and all(r.lanes >= 2 for r in two_way)
        pts = np.concatenate([r.polyline for r in sd.roads])
        lo, hi = np.array(hd.bounds()[:2]), np.array(hd.bounds()[2:])
        assert np.all(pts >= lo - 20.0) and np.all(pts <= hi + 20.0)


@pytest.mark.parametrize("pieces", [1, 3])
def test_spur_of_intersection_lanes_is_a_road(pieces):
    """A dead-end road whose lanes are all flagged as intersection lanes (as Argoverse 2 maps have them) is kept."""
    hd = HDMap(city="TST")
    add_road(hd, "W", (-100, 0), (-12, 0), road_id=False, pieces=pieces)
    add_road(hd, "E", (12, 0), (100, 0), road_id=False, pieces=pieces)
    add_road(hd, "N", (0, 12), (0, 96), road_id=False, pieces=pieces)  # the spur, 84 m
    connect_intersection(hd, "I", (0, 0), with_id=False)
    for lane in hd.lanes.values():
        lane.is_intersection |= lane.id.startswith("N")
    sd = derive_sd(hd)
    assert len(sd.roads) == 2
    main, spur = sorted(sd.roads, key=lambda r: np.ptp(r.polyline[:, 1]))
    assert np.ptp(main.polyline[:, 0]) > 195 and np.abs(main.polyline[:, 1]).max() < 0.3
    assert (spur.lanes, spur.oneway) == (2, 0)
    assert np.abs(spur.polyline[:, 0]).max() < 0.3 and spur.polyline[:, 1].max() > 95
    assert spur.polyline[:, 1].min() < 4.0  # it meets the main road at the junction node
    assert beyond_roads(sd, np.concatenate([l.centerline for l in hd.lanes.values()])).max() <= BEYOND_M


def test_a_branching_lane_is_its_own_road():
    """A lane forking off a road without an intersection gets its own road rather than vanishing in the road."""
    hd = HDMap(city="TST")
    hd.add_lane(Lane("a", np.linspace([-100.0, 0.0], [0.0, 0.0], 11)))
    hd.add_lane(Lane("b", np.linspace([0.0, 0.0], [100.0, 0.0], 11)))
    hd.add_lane(Lane("c", np.linspace([0.0, 0.0], [60.0, 45.0], 11)))
    hd.link("a", "b")
    hd.link("a", "c")
    sd = derive_sd(hd)
    assert len(sd.roads) == 2
    assert beyond_roads(sd, np.concatenate([l.centerline for l in hd.lanes.values()])).max() <= BEYOND_M


def test_argoverse2_crops_lie_on_the_sd_map():
    """Every drivable lane piece of a crop lies near a road of the derived SD map, so no SD raster is empty."""
    for path, hd in av2_maps():
        sd = derive_sd(hd)
        cropper = SceneCropper(hd)
        for pose in hd_poses(hd, 16, np.random.default_rng(0)):
            scene = cropper.extract(pose, num_lines=1000, num_points=40)
            lines = scene.lines[scene.line_mask].astype(np.float64)
            assert len(lines) and rasterize_sd(sd, pose.x, pose.y, pose.yaw)[..., 0].any(), (path.name, pose)
            beyond = beyond_roads(sd, from_frame(lines.reshape(-1, 2), pose.x, pose.y, pose.yaw))
            assert beyond.max() <= BEYOND_M, (path.name, pose, float(beyond.max()))


@pytest.mark.parametrize("city", ["PIT", "SGP", "BOS"])
def test_roads_meet_at_shared_nodes(city):
    from cmtool.data.synth import generate_city

    sd = derive_sd(generate_city(city, seed=0, extent=400.0))
    lines = [shapely.LineString(r.polyline) for r in sd.roads]
    vertices = [{tuple(p) for p in r.polyline} for r in sd.roads]
    touching = 0
    for i, road in enumerate(sd.roads):
        for end in (road.polyline[0], road.polyline[-1]):
            for j, other in enumerate(lines):
                if j != i and shapely.distance(shapely.Point(end), other) < 5.0:
                    assert tuple(end) in vertices[j]  # ends on a node of the road it meets
                    touching += 1
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            for p in shapely.get_coordinates(shapely.intersection(lines[i], lines[j])):
                assert tuple(p) in vertices[i] and tuple(p) in vertices[j]  # crossings are shared nodes
    assert touching > 0
