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
