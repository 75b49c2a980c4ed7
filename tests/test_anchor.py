"""Lane geometry from the SD map (cmtool.sample.anchor) and the joined lending of the guarantee."""

import numpy as np

from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.validity import check
from cmtool.sample.anchor import anchor, frame_roads
from cmtool.sample.guarantee import guarantee

W = 3.1  # a residential lane


def wobbly(x0, x1, y, seed=0):
    """A decoded-looking lane from x0 to x1 at about y: off by up to 0.3 m."""
    x = np.linspace(x0, x1, 20)
    return np.stack([x, y + 0.3 * np.sin(x / 5.0 + seed)], axis=1)


def road(lanes=None, oneway=0, cls="residential"):
    return Road("r", np.array([[-60.0, 0.0], [60.0, 0.0]]), cls, lanes, oneway)


def test_lanes_along_a_road_are_laid_on_it_a_lane_width_apart():
    graph = LaneGraph([wobbly(-30, 20, -1.0), wobbly(25, -28, 2.3, 1)])
    out = anchor(graph, [road()], "right")
    a, b = (np.asarray(l) for l in out.lanes)
    assert np.allclose(a[:, 1], -W / 2, atol=1e-6) and np.allclose(b[:, 1], W / 2, atol=1e-6)
    assert abs(a[0, 0] + 30) < 1.0 and abs(a[-1, 0] - 20) < 1.0  # where the model's lane starts and ends
    assert a[-1, 0] > a[0, 0] and b[-1, 0] < b[0, 0]  # directions kept
    assert out.meta["anchored"]["lanes"] == 2


def test_the_model_decides_the_count_where_the_tag_is_missing_and_the_tag_where_it_is_not():
    two = LaneGraph([wobbly(-30, 30, -1.3), wobbly(-30, 30, -4.9, 2)])
    out = anchor(two, [road()], "right")
    assert sorted(round(float(np.median(l[:, 1])), 3) for l in map(np.asarray, out.lanes)) == [-4.65, -1.55]
    far = LaneGraph([wobbly(-30, 30, -4.9)])  # a second lane out, on a road tagged one lane a direction: not its lane
    assert np.array_equal(anchor(far, [road(lanes=2)], "right").lanes[0], far.lanes[0])
    assert np.allclose(np.asarray(anchor(far, [road()], "right").lanes[0])[:, 1], -4.65)  # untagged: the second


def test_left_hand_traffic_and_one_way_roads_lay_lanes_as_the_rules_do():
    out = anchor(LaneGraph([wobbly(-30, 30, 1.2)]), [road()], "left")
    assert np.allclose(np.asarray(out.lanes[0])[:, 1], W / 2, atol=1e-6)
    oneway = anchor(LaneGraph([wobbly(-30, 30, 1.0), wobbly(-30, 30, -2.0, 3)]), [road(oneway=1)], "right")
    assert sorted(round(float(np.median(l[:, 1])), 3) for l in map(np.asarray, oneway.lanes)) == [-1.55, 1.55]


def test_a_connector_keeps_its_curve_and_joins_the_laid_lane_a_lane_nowhere_near_a_road_stays():
    lane = wobbly(-30, -6, -0.8)
    t = np.linspace(0, np.pi / 2, 12)[:, None]
    curve = lane[-1] + 6.0 * np.hstack([np.sin(t), -(1 - np.cos(t))])  # a right turn onto a road going south
    stray = np.array([[10.0, 20.0], [14.0, 24.0], [18.0, 28.0]])
    south = Road("s", np.array([[0.0, -6.0], [0.0, -60.0]]), "residential")
    graph = LaneGraph([lane, curve, stray], successors=[(0, 1)])
    out = anchor(graph, [road(), south], "right")
    laid, turn = np.asarray(out.lanes[0]), np.asarray(out.lanes[1])
    assert np.allclose(laid[:, 1], -W / 2, atol=1e-6)
    assert np.allclose(turn[0], laid[-1]) and (0, 1) in out.successors
    assert np.allclose(turn[-1], curve[-1], atol=0.5)  # its far end where the model drew it
    assert np.array_equal(np.asarray(out.lanes[2]), stray)


def test_frame_roads_are_in_the_frame_and_keep_the_travel_direction():
    sd = SDMap(roads=[Road("a", np.array([[100.0, 50.0], [300.0, 50.0]]), oneway=-1),
                      Road("far", np.array([[1000.0, 0.0], [1100.0, 0.0]]))])
    roads = frame_roads(sd, (150.0, 50.0, np.pi / 2))  # facing north: the road runs to the frame's right
    assert [r.id for r in roads] == ["a"] and roads[0].oneway == -1
    line = roads[0].polyline
    assert np.allclose(line[:, 0], 0.0) and line[0, 1] > line[-1, 1]  # polyline order kept: east is -y
    assert line[:, 1].max() <= 32 + 24 + 2 and line[:, 1].min() >= -32 - 24 - 2


def test_lent_lanes_join_the_map_or_are_not_lent():
    mine = wobbly(-30, -4, -1.55)
    rules = LaneGraph([np.array([[-2.0, -1.55], [31.5, -1.55]]),  # goes on where the model's lane ends: joined
                       np.array([[-10.0, -20.0], [-10.0, 20.0]]),  # crosses the model's lane: not lent
                       np.array([[5.0, 20.0], [15.0, 20.0]])])  # joined to nothing, inside the frame: not lent
    out = guarantee(LaneGraph([mine]), None, rules)
    assert len(out.lanes) == 2 and out.meta["guarantee"]["added"] == 1
    assert (0, 1) in out.successors and np.allclose(out.lanes[1][0], out.lanes[0][-1])
    assert check(out).counts().get("dangling", 0) == 0
