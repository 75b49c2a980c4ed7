"""Maps composed from their SD map (cmtool.sample.compose): every SD road carries its lanes, whole, and nothing else
does; junctions joined from the laid lanes; the model's decisions; validity the same before and after writing."""

import json

import numpy as np
import pytest
import shapely

from cmtool.core.geometry import rounded_corners, unit
from cmtool.core.radius import min_radii
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.validity import check
from cmtool.sample.compose import compose
from cmtool.sample.guarantee import guarantee
from cmtool.sample.roads import drawn_lane_counts, frame_roads

W = 3.1  # a residential lane


def line(*points, n=20):
    """A lane through ``points``, ``n`` points along each leg."""
    pts = [np.asarray(p, np.float64) for p in points]
    return np.concatenate([np.linspace(a, b, n, endpoint=k == len(pts) - 2) for k, (a, b) in
                           enumerate(zip(pts, pts[1:]))])


def t_junction():
    """An east-west through road and a stem to the south, meeting at the origin (two-way, untagged)."""
    return [Road("ew", np.array([[-60.0, 0.0], [0.0, 0.0], [60.0, 0.0]])),
            Road("s", np.array([[0.0, 0.0], [0.0, -60.0]]))]


def lanes_near(graph, a, b, tol=1.0):
    """The lanes whose every point lies within ``tol`` of the segment a-b (a lane of that road stretch)."""
    seg = shapely.LineString([a, b])
    return [k for k, l in enumerate(graph.lanes) if shapely.distance(shapely.MultiPoint(np.asarray(l)), seg) >= 0
            and max(shapely.distance(shapely.Point(p), seg) for p in np.asarray(l)) <= tol]


def covered(graph, a, b, offset, tol=0.3):
    """The share of the stretch a-b, offset ``offset`` to its left, within ``tol`` of a lane of ``graph``."""
    d = unit(np.asarray(b, float) - np.asarray(a, float))
    left = np.array([-d[1], d[0]])
    points = np.linspace(np.asarray(a, float) + offset * left, np.asarray(b, float) + offset * left, 200)
    lanes = shapely.MultiLineString([np.asarray(l) for l in graph.lanes])
    return float(np.mean([shapely.distance(shapely.Point(p), lanes) <= tol for p in points]))


def test_a_lane_no_sd_road_explains_is_not_written_and_the_map_keeps_the_roads_lanes():
    stray = line([-30.0, 20.0], [30.0, 20.0])  # 20 m from the only road
    along = line([-30.0, -1.5], [30.0, -1.5])
    out = compose(LaneGraph([along, stray]), [Road("r", np.array([[-60.0, 0.0], [60.0, 0.0]]))], "right")
    assert out.meta["composed"]["dropped"] == 1
    assert all(np.abs(np.asarray(l)[:, 1]).max() < W for l in out.lanes)  # nothing near y = 20
    assert covered(out, (-32, 0), (32, 0), -W / 2) == 1.0 and covered(out, (-32, 0), (32, 0), W / 2) == 1.0


def test_an_sd_road_the_model_left_empty_is_filled_and_joined_at_its_junction():
    through = [line([-32.0, -1.55], [32.0, -1.55]), line([32.0, 1.55], [-32.0, 1.55])]  # no lane on the stem
    out = compose(LaneGraph(through), t_junction(), "right")
    for offset in (-W / 2, W / 2):
        assert covered(out, (0, -12), (0, -32), offset) == 1.0
    stem = [k for k, l in enumerate(out.lanes) if np.asarray(l)[:, 1].max() < -5.0]  # wholly on the stem
    assert len(stem) == 2
    linked = {k for edge in out.successors for k in edge}
    assert all(k in linked for k in stem)  # joined at the junction
    assert check(out).score == 1.0


def test_a_road_broken_into_pieces_by_the_model_carries_its_lanes_whole():
    pieces = [line([-32.0, -1.4], [-12.0, -1.7]), line([-2.0, -1.5], [8.0, -1.6]), line([20.0, -1.5], [32.0, -1.5])]
    out = compose(LaneGraph(pieces), [Road("r", np.array([[-60.0, 0.0], [60.0, 0.0]]), oneway=1, lanes=1)], "right")
    assert len(out.lanes) == 1 and covered(out, (-32, 0), (32, 0), 0.0, tol=0.01) == 1.0
    assert np.asarray(out.lanes[0])[-1, 0] > np.asarray(out.lanes[0])[0, 0]  # the one-way road's way


@pytest.mark.parametrize("side", ["right", "left"])
def test_connectors_are_smooth_and_join_both_their_lanes_ends(side):
    cross = [Road("ew", np.array([[-60.0, 0.0], [0.0, 0.0], [60.0, 0.0]]), "primary"),
             Road("ns", np.array([[0.0, -60.0], [0.0, 0.0], [0.0, 60.0]]))]
    out = compose(LaneGraph([]), cross, side)
    lanes = [np.asarray(l) for l in out.lanes]
    before = {j: i for i, j in out.successors}
    after = {i: j for i, j in out.successors}
    connectors = [k for k in range(len(lanes)) if k in before and k in after]
    assert len(connectors) >= 8
    for k in connectors:
        into, out_ = lanes[before[k]], lanes[after[k]]
        assert np.allclose(into[-1], lanes[k][0], atol=2e-3) and np.allclose(lanes[k][-1], out_[0], atol=2e-3)
        joins = ((into[-1] - into[-2], lanes[k][1] - lanes[k][0]), (lanes[k][-1] - lanes[k][-2], out_[1] - out_[0]))
        for a, b in joins:
            assert float(unit(a) @ unit(b)) > np.cos(np.radians(12.0))  # tangent to both, at 20 points a lane
    assert min_radii([lanes[k] for k in connectors])[0].min() >= 4.0
    assert check(out).score == 1.0
    near = -1.0 if side == "right" else 1.0  # lanes of the travel direction lie on this side (as left offsets)
    eastbound = [l for l in lanes if l[-1, 0] - l[0, 0] > 10 and abs(l[:, 1]).max() < 10]
    assert eastbound and all(np.sign(np.median(l[:, 1])) == near for l in eastbound)


def test_the_lanes_of_one_movement_do_not_cross():
    wide = [Road("ew", np.array([[-60.0, 0.0], [0.0, 0.0], [60.0, 0.0]]), "primary", lanes=6),
            Road("ns", np.array([[0.0, -60.0], [0.0, 0.0], [0.0, 60.0]]), "primary", lanes=6)]
    out = compose(LaneGraph([]), wide, "right")
    lanes = [np.asarray(l) for l in out.lanes]
    before = {j: i for i, j in out.successors}
    after = {i: j for i, j in out.successors}
    movement = {}  # (arriving road direction, leaving road direction) -> its connectors
    for k in (k for k in range(len(lanes)) if k in before and k in after):
        key = tuple((np.round(unit(lanes[m][-1] - lanes[m][0]), 1) + 0.0).tolist() for m in (before[k], after[k]))
        movement.setdefault(str(key), []).append(shapely.LineString(lanes[k]))
    assert len(movement) == 12 and max(len(v) for v in movement.values()) == 3  # 4 arms x 3 ways on; 3 lanes straight
    for group in movement.values():
        assert not any(a.crosses(b) for i, a in enumerate(group) for b in group[i + 1:])


def test_a_divided_road_stays_two_carriageways():
    divided = [Road("n", np.array([[-60.0, 4.0], [0.0, 4.0], [60.0, 4.0]]), "primary", oneway=-1, lanes=2),
               Road("s", np.array([[-60.0, -4.0], [0.0, -4.0], [60.0, -4.0]]), "primary", oneway=1, lanes=2),
               Road("x", np.array([[0.0, -60.0], [0.0, -4.0], [0.0, 4.0], [0.0, 60.0]]))]
    out = compose(LaneGraph([]), divided, "right")
    along = [np.asarray(l) for l in out.lanes if abs(np.asarray(l)[-1, 0] - np.asarray(l)[0, 0]) > 15
             and np.ptp(np.asarray(l)[:, 1]) < 0.5]
    west, east = [l for l in along if l[-1, 0] < l[0, 0]], [l for l in along if l[-1, 0] > l[0, 0]]
    assert all(l[:, 1].min() > 1.0 for l in west) and all(l[:, 1].max() < -1.0 for l in east)  # each on its own
    lanes = [np.asarray(l) for l in out.lanes]
    for i, j in out.successors:  # no U-turn from one carriageway into the other
        assert float(unit(lanes[i][-1] - lanes[i][-2]) @ unit(lanes[j][1] - lanes[j][0])) > -0.5
    assert check(out).score == 1.0


def test_the_model_decides_the_movements_and_every_lane_keeps_a_way_on():
    right = 1.55
    drawn = [line([-32.0, -right], [32.0, -right]), line([32.0, right], [-32.0, right]),  # straight both ways
             line([right, -32.0], [right, -8.0], [8.0, -right], [32.0, -right]),  # stem: right turn (east)
             line([32.0, right], [8.0, right], [-right, -8.0], [-right, -32.0])]  # east to the stem: left turn
    out = compose(LaneGraph(drawn), t_junction(), "right")
    assert out.meta["composed"]["movements"] == {"model": 4}

    def moves(graph):
        lanes = [np.asarray(l) for l in graph.lanes]
        before = {j: i for i, j in graph.successors}
        after = {i: j for i, j in graph.successors}
        return {(tuple(np.round(unit(lanes[before[k]][-1] - lanes[before[k]][-2])) + 0.0),
                 tuple(np.round(unit(lanes[after[k]][1] - lanes[after[k]][0])) + 0.0))
                for k in range(len(lanes)) if k in before and k in after}

    assert ((0.0, 1.0), (-1.0, 0.0)) not in moves(out)  # no left turn out of the stem: the model drew none
    everything = compose(LaneGraph([]), t_junction(), "right")  # no lane drawn: every legal movement
    assert len(moves(everything)) == 6 and everything.meta["composed"]["movements"] == {"rules": 6}


def test_lane_counts_from_the_tag_the_class_or_the_model():
    two = [line([-32.0, -1.5], [32.0, -1.5]), line([-32.0, -4.7], [32.0, -4.7])]  # two lanes eastbound
    untagged = [Road("r", np.array([[-60.0, 0.0], [60.0, 0.0]]))]
    assert drawn_lane_counts(LaneGraph(two), untagged, "right") == {(0, 1): 2}
    by_class = compose(LaneGraph(two), untagged, "right", counts="class")
    by_model = compose(LaneGraph(two), untagged, "right")  # the default: the model's counts
    tagged = compose(LaneGraph(two), [Road("r", untagged[0].polyline, lanes=4)], "right")
    east = lambda g: sum(np.asarray(l)[-1, 0] > np.asarray(l)[0, 0] for l in g.lanes)  # noqa: E731
    west = lambda g: len(g.lanes) - east(g)  # noqa: E731
    assert (east(by_class), west(by_class)) == (1, 1) and by_class.meta["composed"]["lanes_from"] == {"class": 2}
    assert (east(by_model), west(by_model)) == (2, 1)  # the model drew none westbound: the class's one
    assert by_model.meta["composed"]["lanes_from"] == {"model": 1, "class": 1}
    assert (east(tagged), west(tagged)) == (2, 2) and tagged.meta["composed"]["lanes_from"] == {"tag": 2}
    with pytest.raises(ValueError, match="lane-counts"):
        compose(LaneGraph(two), untagged, "right", counts="guess")


def test_lights_stay_where_a_lane_runs_under_them():
    green = [line([10.0, -1.5], [14.0, -1.5], n=5), line([10.0, 25.0], [14.0, 25.0], n=5)]
    out = compose(LaneGraph([line([-32.0, -1.5], [32.0, -1.5])], green_lights=green),
                  [Road("r", np.array([[-60.0, 0.0], [60.0, 0.0]]))], "right")
    assert len(out.green_lights) == 1 and np.allclose(out.green_lights[0], green[0])


def test_a_sharp_bend_is_rounded_and_a_sharp_join_is_a_junction_of_two_arms():
    bent = [Road("l", np.array([[-60.0, -10.0], [10.0, -10.0], [10.0, 60.0]]))]  # a right angle inside one road
    joined = [Road("a", np.array([[-60.0, -10.0], [10.0, -10.0]])), Road("b", np.array([[10.0, -10.0], [10.0, 60.0]]))]
    for roads in (bent, joined):
        out = compose(LaneGraph([]), roads, "right")
        assert check(out).score == 1.0 and min_radii([np.asarray(l) for l in out.lanes])[0].min() >= 4.0
        assert covered(out, (-32, -10), (-5, -10), -W / 2) == 1.0 and covered(out, (10, 25), (10, 32), W / 2) == 1.0
    arc = rounded_corners(np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0]]), 6.0)
    assert abs(min_radii([arc])[0][0] - 6.0) < 0.1 and np.allclose(arc[[0, -1]], [[0, 0], [20, 20]])


def test_validity_is_the_same_in_memory_and_read_back_from_the_file():
    rng = np.random.default_rng(0)
    for _ in range(50):
        lanes = [np.cumsum(rng.normal(0.0, 1.0, (12, 2)) + [2.0, 0.0], axis=0) - [12.0, 0.0] for _ in range(6)]
        graph = LaneGraph(lanes, [(0, 1), (2, 3)]).as_written()
        back = LaneGraph.from_json(json.loads(json.dumps(graph.to_json())))
        assert all(np.array_equal(a, b) for a, b in zip(graph.lanes, back.lanes))
        assert check(graph).to_json() == check(back).to_json()


def test_without_roads_the_guarantee_turns_lanes_that_run_against_one_way_roads():
    from cmtool.data.sd_raster import rasterize_sd

    sd = rasterize_sd(SDMap(roads=[Road("one", np.array([[-40.0, 0.0], [40.0, 0.0]]), oneway=1, lanes=1)]), 0, 0, 0)
    wrong = line([30.0, 0.0], [-30.0, 0.0])
    out = guarantee(LaneGraph([wrong], meta={"source": "test"}), sd)
    assert out.meta["guarantee"] == {"turned": 1} and np.array_equal(out.lanes[0], wrong[::-1])
    assert out.meta["source"] == "test" and guarantee(out, sd).meta["guarantee"] == {"turned": 0}


def test_frame_roads_are_in_the_frame_and_keep_their_vertices_and_travel_direction():
    sd = SDMap(roads=[Road("a", np.array([[100.0, 50.0], [150.0, 50.0], [300.0, 50.0]]), oneway=-1),
                      Road("far", np.array([[1000.0, 0.0], [1100.0, 0.0]]))])
    roads = frame_roads(sd, (150.0, 50.0, np.pi / 2))  # facing north: the road runs to the frame's right
    assert [r.id for r in roads] == ["a"] and roads[0].oneway == -1
    points = roads[0].polyline
    assert np.allclose(points[:, 0], 0.0) and points[0, 1] > points[-1, 1]  # polyline order kept: east is -y
    assert np.allclose(points[:, 1], [50.0, 0.0, -56.0])  # the vertex at (150, 50) kept, cut at the margin
