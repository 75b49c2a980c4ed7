"""Lane neighbours: found from the geometry, kept from imported maps, written in the lane graph JSON, and
counted by routability with lane changes."""

import re

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.maps.lanegraph import LaneGraph, read_jsonl, write_jsonl
from cmtool.maps.neighbours import abreast, find_neighbours, infer_neighbours, lane_widths, same_direction, side_of
from cmtool.metrics.validity import check
from tests.conftest import SHARED_DATA


def line(x0, y0, x1, y1, n=10):
    return np.stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n)], axis=-1)


def road():
    """Two lanes one way (right-hand), one the other way, a lane 7 m out and a lane crossing them all."""
    return [line(-30, -1.75, 30, -1.75), line(-30, -5.0, 30, -5.0), line(30, 1.75, -30, 1.75),
            line(-30, -12.0, 30, -12.0), line(0, -30, 0, 30)]


def test_neighbours_from_geometry():
    lanes = road()
    assert infer_neighbours(lanes) == [(0, 2), (1, 0), (2, 0)]  # the nearest lane on the left, either way
    assert infer_neighbours(lanes, side=-1) == [(0, 1)]
    left, oncoming = find_neighbours(lanes)
    assert left == [(1, 0)] and oncoming == [(0, 2)]  # 0 is 1's left neighbour; 0 and 2 share the centre line
    assert same_direction(lanes, 1, 0) and not same_direction(lanes, 0, 2)
    assert side_of(lanes, 0, 2) == 1 and side_of(lanes, 0, 1) == -1
    mirrored = [lane * [1.0, -1.0] for lane in lanes]  # left-hand traffic: oncoming lanes on each other's right
    assert find_neighbours(mirrored) == ([(0, 1)], [(0, 2)]) and side_of(mirrored, 0, 2) == -1
    np.testing.assert_allclose(lane_widths(lanes, left), [3.25, 3.25, 3.25, 3.25, 3.25])  # the one spacing known
    np.testing.assert_allclose(lane_widths(lanes, left, [3.0] * 5), [3.0] * 5)
    shifted = [line(-30, -1.75, 30, -1.75), line(-20, -5.25, 40, -5.25)]  # beside over 2/3 of each: neighbours,
    assert infer_neighbours(shifted) == [(1, 0)] and not abreast(*shifted)  # but not abreast (10 m apart)
    assert abreast(lanes[0], lanes[1]) and abreast(lanes[0], lanes[2], same=False)
    assert infer_neighbours([line(-30, 0, 30, 0), line(-30, 0, 30, 0.1, n=5)]) == []  # on top of each other
    assert infer_neighbours(lanes[:1]) == []


def test_source_neighbours_are_kept_and_agree_with_the_geometry():
    """Argoverse 2 crops: the pairs the map records (same direction) and those the geometry finds agree."""
    from cmtool.data.frames import hd_poses
    from cmtool.data.scene import SceneCropper
    from cmtool.formats.importers import import_hd_map

    recorded = found = both = oncoming = 0
    for path in sorted((SHARED_DATA / "av2").glob("*.json")):
        hd = import_hd_map("av2", path)
        cropper = SceneCropper(hd)
        for pose in hd_poses(hd, 6, np.random.default_rng(0)):
            graph = cropper.extract(pose).to_lanegraph()
            lanes = graph.lanes
            kept = set(graph.left_neighbors)
            geometric = set(find_neighbours(lanes, graph.widths)[0])
            recorded, found, both = recorded + len(kept), found + len(geometric), both + len(kept & geometric)
            oncoming += len(graph.oncoming)
            assert graph.widths is not None and len(graph.widths) == len(lanes)
    assert recorded >= 30 and oncoming >= 30, (recorded, oncoming)
    assert both >= 0.9 * recorded and both >= 0.9 * found, (recorded, found, both)


def test_lane_graph_json_keeps_neighbours_and_widths(tmp_path):
    graph = LaneGraph(lanes=road(), left_neighbors=[(1, 0)], oncoming=[(0, 2)], widths=[3.5, 3.0, 3.5, 3.5, 3.5])
    write_jsonl(tmp_path / "g.jsonl", [graph, LaneGraph(lanes=road())])
    back, old = read_jsonl(tmp_path / "g.jsonl")
    assert (back.left_neighbors, back.oncoming, back.widths) == (graph.left_neighbors, graph.oncoming, graph.widths)
    assert old.left_neighbors is None and old.oncoming is None and old.widths is None  # older files still read
    for bad, message in (({"left_neighbors": [[0, 9]]}, "left_neighbors[0]: lane index out of range"),
                         ({"widths": [3.5]}, "expected one width per lane (5)"),
                         ({"widths": [3.5, 3.5, 3.5, 3.5, float("nan")]}, "widths[4]"),
                         ({"meta": {"geo": {"lat": 95, "lon": 0, "heading": 0}}}, "latitude must be in [-90, 90]")):
        obj = LaneGraph(lanes=road()).to_json() | bad
        with pytest.raises(CmtoolError, match=re.escape(message)):
            LaneGraph.from_json(obj)


def test_routability_counts_lane_changes_between_same_direction_neighbours():
    lanes = road()[:3]
    report = check(LaneGraph(lanes=lanes, left_neighbors=[(1, 0)], oncoming=[(0, 2)]))
    assert report.routable_pairs == 0.0
    assert report.routable_with_changes == pytest.approx(2 / 6)  # 0 <-> 1; never into the oncoming lane 2
    assert check(LaneGraph(lanes=lanes)).routable_with_changes == pytest.approx(2 / 6)  # inferred when not recorded
    assert check(LaneGraph(lanes=lanes, left_neighbors=[])).routable_with_changes == 0.0


def random_road_lanes(rng):
    """Bent lanes over a 64 m frame, some with a neighbour or two beside them, either way (millimetre coordinates)."""
    lanes = []
    for _ in range(int(rng.integers(2, 30))):
        p0, a, length, bend = rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi), rng.uniform(3, 40), rng.normal(0, 0.3)
        t = np.linspace(0, 1, int(rng.integers(2, 21)))[:, None]
        d, side = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        lane = np.round(p0 + length * t * d + bend * length * t * (1 - t) * side, 3)
        lanes.append(lane)
        for _ in range(int(rng.integers(0, 3))):
            lanes.append(np.round((lane + rng.uniform(2, 6) * rng.choice([-1, 1]) * side)[::rng.choice([-1, 1])], 3))
    return lanes


def test_one_search_for_both_sides_finds_what_a_search_per_side_finds():
    """find_neighbours searches once for both sides and lane_widths measures every pair at once: the same pairs and
    widths, bit for bit, as a search per side with np.median per pair, same_direction per pair and a LineString pair
    per gap (as before), on 100 random scenes."""
    import shapely

    from cmtool.maps import neighbours

    def per_side(lanes, widths, side):
        a, b, offset, beside = neighbours._beside_all(lanes, widths, None)
        best = {}
        for i, j, o, m in zip(a.tolist(), b.tolist(), offset, beside):
            if side * np.median(o[m]) > 0 and (i not in best or np.median(np.abs(o[m])) < best[i][0]):
                best[i] = (np.median(np.abs(o[m])), j)
        return sorted((i, j) for i, (_, j) in best.items())

    def gap(a, b):
        points = shapely.line_interpolate_point(shapely.LineString(a), np.linspace(0.1, 0.9, 9), normalized=True)
        return float(shapely.distance(points, shapely.LineString(b)).mean())

    rng, pairs = np.random.default_rng(3), 0
    for _ in range(100):
        lanes = random_road_lanes(rng)
        widths = None if rng.random() < 0.5 else rng.uniform(2.5, 5, len(lanes))
        left, right = per_side(lanes, widths, 1), per_side(lanes, widths, -1)
        assert infer_neighbours(lanes, widths) == left and infer_neighbours(lanes, widths, side=-1) == right
        oncoming = sorted({(min(i, j), max(i, j)) for i, j in left + right if not same_direction(lanes, i, j)})
        same = [(i, j) for i, j in left if same_direction(lanes, i, j)]
        assert find_neighbours(lanes, widths) == (same, oncoming)
        spacing = [[] for _ in lanes]
        for i, j in same:
            spacing[i].append(gap(lanes[i], lanes[j]))
            spacing[j].append(gap(lanes[i], lanes[j]))
        every = [g for s in spacing for g in s]
        expected = np.clip([np.mean(s) if s else (np.median(every) if every else 3.5) for s in spacing], 2.5, 5.0)
        np.testing.assert_array_equal(lane_widths(lanes, same), expected)
        pairs += len(same) + len(oncoming)
    assert pairs > 300
