"""Scene extraction on hand-built HD maps."""

import numpy as np
import pytest

from cmtool.data.scene import Pose, Scene, extract_scene
from cmtool.maps.hdmap import HDMap, Lane, StopLine


def straight(x0, y0, x1, y1, n=30):
    return np.linspace([x0, y0], [x1, y1], n)


def make_map(lanes, links=(), stop_lines=()):
    hd = HDMap(city="PIT", source="test")
    for lane_id, line, *rest in lanes:
        hd.add_lane(Lane(lane_id, np.asarray(line, float), lane_type=rest[0] if rest else "vehicle"))
    for a, b in links:
        hd.link(a, b)
    hd.stop_lines = list(stop_lines)
    return hd


def test_lane_crossing_border_is_clipped_and_points_forward():
    hd = make_map([("a", straight(-100, 0, 100, 0))])
    scene = extract_scene(hd, Pose(0.0, 0.0, 0.0))
    assert scene.line_mask.sum() == 1
    line = scene.lines[0]
    assert line.shape == (20, 2)
    np.testing.assert_allclose(line[0], [-32, 0], atol=1e-4)
    np.testing.assert_allclose(line[-1], [32, 0], atol=1e-4)
    assert np.all(np.diff(line[:, 0]) > 0)  # along the ego heading -> +x


def test_pose_rotation_maps_lane_heading_to_plus_x():
    hd = make_map([("a", straight(50, -100, 50, 100))])  # runs north
    scene = extract_scene(hd, Pose(50.0, 0.0, np.pi / 2))
    line = scene.lines[0]
    np.testing.assert_allclose(line[:, 1], 0.0, atol=1e-4)
    assert line[-1, 0] > line[0, 0]
    # a pose looking east sees the same lane run to the left (+y)
    scene = extract_scene(hd, Pose(40.0, 0.0, 0.0))
    line = scene.lines[0]
    np.testing.assert_allclose(line[:, 0], 10.0, atol=1e-4)
    assert line[-1, 1] > line[0, 1]


def test_lane_leaving_and_reentering_is_split_without_edge():
    # a U-shaped detour that leaves the frame at x = 32 and comes back
    u = np.array([[-20, 5], [20, 5], [60, 5], [60, -5], [20, -5], [-20, -5]], float)
    hd = make_map([("u", u)])
    scene = extract_scene(hd, Pose(0.0, 0.0, 0.0))
    assert scene.line_mask.sum() == 2
    assert len(scene.edges) == 0
    ends = {tuple(np.round(scene.lines[i][-1], 3)) for i in range(2)}
    assert (32.0, 5.0) in ends and (-20.0, -5.0) in ends
    assert scene.cut == 0 and extract_scene(hd, Pose(0.0, 0.0, 0.0), num_lines=1).cut == 1  # pieces, not lanes


def test_successor_edges_survive_clipping():
    hd = make_map(
        [("a", straight(-80, 0, 0, 0)), ("b", straight(0, 0, 10, 0)), ("c", straight(10, 0, 80, 0)),
         ("d", straight(10, 0, 10, 80))],
        links=[("a", "b"), ("b", "c"), ("b", "d")],
    )
    scene = extract_scene(hd, Pose(0.0, 1.0, 0.0))
    graph = scene.to_lanegraph()
    ends = {(tuple(np.round(l[0], 3)), tuple(np.round(l[-1], 3))): i for i, l in enumerate(graph.lanes)}
    a = ends[((-32.0, -1.0), (0.0, -1.0))]  # start clipped at the rear edge
    b = ends[((0.0, -1.0), (10.0, -1.0))]
    c = ends[((10.0, -1.0), (32.0, -1.0))]  # end clipped at the front edge
    d = ends[((10.0, -1.0), (10.0, 32.0))]  # end clipped at the left edge
    assert set(graph.successors) == {(a, b), (b, c), (b, d)}


def test_clipped_start_or_end_breaks_edge():
    hd = make_map([("a", straight(-80, 0, -40, 0)), ("b", straight(-40, 0, 80, 0))], links=[("a", "b")])
    scene = extract_scene(hd, Pose(0.0, 0.0, 0.0))
    assert scene.line_mask.sum() == 1  # a lies outside the frame
    assert len(scene.edges) == 0


def test_nearest_lines_kept_in_order_and_short_pieces_dropped():
    lanes = [(f"l{k}", straight(-40, 1.0 * k, 40, 1.0 * k)) for k in range(-20, 21)]
    lanes.append(("tiny", straight(0, -0.5, 1.5, -0.5)))
    lanes.append(("bike", straight(-40, 0.5, 40, 0.5), "bike"))
    hd = make_map(lanes)
    scene = extract_scene(hd, Pose(0.0, 0.2, 0.0), num_lines=30)
    assert scene.lines.shape == (30, 20, 2) and scene.line_mask.all()
    assert scene.cut == 11  # 41 drivable pieces of at least 2 m, 30 kept
    assert extract_scene(hd, Pose(0.0, 0.2, 0.0), num_lines=41).cut == 0
    offsets = scene.lines[:, 0, 1] + 0.2  # lateral offset of each kept line in world y
    dist = np.abs(scene.lines[:, 0, 1])
    assert np.all(np.diff(dist) >= -1e-6)  # nearest first
    assert set(np.round(offsets).astype(int)) == set(range(-14, 16))
    assert not np.any(np.isclose(scene.lines[:, 0, 1], -0.7, atol=1e-3))  # the 1.5 m lane is dropped
    assert not np.any(np.isclose(scene.lines[:, 0, 1], 0.3, atol=1e-3))  # bike lanes are not drivable


def test_light_lines_follow_stop_line_states():
    hd = make_map(
        [("a", straight(-30, 0, 30, 0)), ("b", straight(0, -30, 0, 30)), ("c", straight(-30, 10, 30, 10))],
        stop_lines=[StopLine("s1", straight(-1, -2, -1, 2, 2), "green", ["a"]),
                    StopLine("s2", straight(-2, -1, 2, -1, 2), "red", ["b", "c"]),
                    StopLine("s3", straight(-2, -1, 2, -1, 2), "unknown", ["a"])],
    )
    scene = extract_scene(hd, Pose(0.0, 0.0, 0.0), num_lights=1)
    assert scene.green_mask.tolist() == [True]
    np.testing.assert_allclose(scene.green[0][[0, -1]], [[-30, 0], [30, 0]], atol=1e-4)
    assert scene.red_mask.tolist() == [True]  # b (distance 0) before c, one kept
    np.testing.assert_allclose(scene.red[0][:, 0], 0.0, atol=1e-4)


def test_scene_round_trips_through_lanegraph_fields():
    hd = make_map([("a", straight(-10, 0, 10, 0))])
    scene = extract_scene(hd, Pose(0.0, 0.0, 0.0))
    rebuilt = Scene(scene.lines, scene.line_mask, scene.edges, scene.green, scene.green_mask, scene.red,
                    scene.red_mask, scene.city, scene.source, scene.pose)
    graph = rebuilt.to_lanegraph()
    assert graph.city == "PIT" and graph.meta["source"] == "test"
    assert len(graph.lanes) == 1 and graph.lanes[0].shape == (20, 2)
    assert graph.lanes[0][0] == pytest.approx([-10, 0], abs=1e-5)
