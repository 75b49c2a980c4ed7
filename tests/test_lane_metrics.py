"""Lane precision / recall / F1 (cmtool.metrics.lanes) on hand-made polylines."""

import numpy as np
import pytest

from cmtool.metrics.lanes import distance_to_polylines, lane_scores, lane_scores_of_scenes, near_polylines

STRAIGHT = np.array([[0.0, 0.0], [20.0, 0.0]])
BEND = np.array([[0.0, 5.0], [10.0, 5.0], [10.0, 20.0]])
CURVE = np.stack([np.linspace(-30, 30, 20), 10.0 * np.sin(np.linspace(0, 3, 20))], axis=1)


def test_identical_sets_score_one():
    scores = lane_scores([STRAIGHT, BEND, CURVE], [STRAIGHT, BEND, CURVE])
    assert scores == {"precision": 1.0, "recall": 1.0, "f1": 1.0}


def test_point_to_segment_distance():
    pts = np.array([[5.0, 2.0], [-3.0, 4.0], [25.0, 0.0], [10.0, 0.0]])
    np.testing.assert_allclose(distance_to_polylines(pts, [STRAIGHT]), [2.0, 5.0, 5.0, 0.0])
    np.testing.assert_allclose(distance_to_polylines(pts, [STRAIGHT, BEND]), [2.0, np.sqrt(10.0), 5.0, 0.0])
    assert np.isinf(distance_to_polylines(pts, [])).all()


@pytest.mark.parametrize("shift, expected", [(0.5, 1.0), (2.0, 0.0)])
def test_shifted_lane(shift, expected):
    moved = STRAIGHT + [0.0, shift]
    scores = lane_scores([moved], [STRAIGHT], tol=1.0)
    assert scores["precision"] == expected and scores["recall"] == expected and scores["f1"] == expected


def test_missing_lane_lowers_recall_only():
    scores = lane_scores([STRAIGHT], [STRAIGHT, CURVE + [0.0, 40.0]])
    assert scores["precision"] == 1.0
    assert 0.0 < scores["recall"] < 0.5  # the missing curve is longer than the kept straight lane
    assert scores["f1"] == pytest.approx(2 * scores["recall"] / (1 + scores["recall"]))


def test_extra_lane_lowers_precision_only():
    scores = lane_scores([STRAIGHT, BEND + [50.0, 0.0]], [STRAIGHT])
    assert scores["recall"] == 1.0 and scores["precision"] == pytest.approx(20 / 45, abs=0.03)


def test_points_are_resampled_so_long_lanes_weigh_more():
    half_wrong = np.array([[0.0, 0.0], [20.0, 0.0], [40.0, 10.0]])  # second leg is off every reference
    scores = lane_scores([half_wrong], [STRAIGHT], tol=1.0, step=0.5)
    assert scores["precision"] == pytest.approx(20 / (20 + np.hypot(20, 10)), abs=0.03)


def test_empty_sets():
    assert lane_scores([], []) == {"precision": 1.0, "recall": 1.0, "f1": 1.0}
    assert lane_scores([], [STRAIGHT]) == {"precision": 1.0, "recall": 0.0, "f1": 0.0}
    assert lane_scores([STRAIGHT], []) == {"precision": 0.0, "recall": 1.0, "f1": 0.0}


def brute_force_distance(points, polylines):
    """The reference: every point against every segment (what the package did before its STR-tree)."""
    start = np.concatenate([p[:-1] for p in polylines])
    vec = np.concatenate([np.diff(p, axis=0) for p in polylines])
    rel = points[:, None] - start
    t = np.clip((rel * vec).sum(-1) / np.maximum((vec ** 2).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * vec, axis=-1).min(axis=1)


def random_lanes(rng, n):
    """Wandering lanes over the frame, some with repeated points or a single segment."""
    lanes = []
    for _ in range(n):
        k = int(rng.integers(2, 25))
        lane = rng.uniform(-32, 32, 2) + np.cumsum(rng.normal(scale=rng.uniform(0.5, 4.0), size=(k, 2)), axis=0)
        if k > 3 and rng.random() < 0.2:
            lane[2] = lane[1]  # a zero-length segment
        lanes.append(lane)
    return lanes


def test_distances_equal_the_brute_force_reference_on_varied_scenes():
    rng = np.random.default_rng(0)
    for _ in range(300):
        lanes = random_lanes(rng, int(rng.integers(1, 40)))
        points = rng.uniform(-40, 40, (int(rng.integers(1, 200)), 2))
        np.testing.assert_allclose(distance_to_polylines(points, lanes), brute_force_distance(points, lanes),
                                   rtol=0, atol=1e-9)
        tol = float(rng.uniform(0.5, 5.0))
        np.testing.assert_array_equal(near_polylines(points, lanes, tol), brute_force_distance(points, lanes) <= tol)
    assert distance_to_polylines(np.zeros((0, 2)), [STRAIGHT]).shape == (0,)
    assert not near_polylines(np.zeros((3, 2)), [], 1.0).any()
    assert near_polylines(np.zeros((0, 2)), [STRAIGHT], 1.0).shape == (0,)


def test_settled_points_get_the_answers_geos_gives_every_point():
    """near_polylines and within_distance settle most points by a KD-tree of segment pieces: the same answers as GEOS's
    dwithin and its nearest distances for every point, also on points a hair either side of tol from axis-aligned
    lanes and on a pixel grid exactly tol from lane vertices."""
    import shapely

    from cmtool.metrics.lanes import _tree, within_distance

    rng = np.random.default_rng(7)
    for _ in range(80):
        lanes = [np.round(lane, 3) for lane in random_lanes(rng, int(rng.integers(1, 30)))]
        lanes.append(np.array([[-20.125, 4.125], [20.125, 4.125], [20.125, -9.0]]))  # on the grid
        tol = float(rng.choice([1.0, 3.0, 5.0, rng.uniform(0.5, 5.0)]))
        grid = np.stack(np.meshgrid(np.arange(-32, 32, 0.5) + 0.125, np.arange(-32, 32, 0.5) + 0.125), -1).reshape(-1, 2)
        points = np.concatenate([grid[rng.random(len(grid)) < 0.2], rng.uniform(-40, 40, (300, 2)),
                                 [[0.0, 4.125 + tol], [0.0, np.nextafter(4.125 + tol, 9)], [0.0, 4.125 - tol]]])
        dwithin = np.zeros(len(points), bool)
        dwithin[_tree(lanes).query(shapely.points(points), predicate="dwithin", distance=tol)[0]] = True
        np.testing.assert_array_equal(near_polylines(points, lanes, tol), dwithin)
        np.testing.assert_array_equal(within_distance(points, lanes, tol), distance_to_polylines(points, lanes) <= tol)
    assert not within_distance(np.zeros((3, 2)), [], 1.0).any()
    assert within_distance(np.zeros((0, 2)), [STRAIGHT], 1.0).shape == (0,)


def test_scores_of_many_scenes_at_once_equal_each_scene_alone():
    rng = np.random.default_rng(5)
    preds, gts = [], []
    for k in range(40):
        gt = [np.cumsum(rng.normal(0, 3, (rng.integers(2, 12), 2)), axis=0) + rng.uniform(-30, 30, 2)
              for _ in range(rng.integers(0, 8) if k % 7 else 0)]  # every seventh scene without lanes
        pred = [l + rng.normal(0, 0.6, l.shape) for l in gt[:rng.integers(0, len(gt) + 1)]]
        pred += [np.cumsum(rng.normal(0, 3, (5, 2)), axis=0) for _ in range(rng.integers(0, 3) if k % 5 else 0)]
        preds.append(pred)
        gts.append(gt)
    together = lane_scores_of_scenes(preds, gts, tol=1.0)
    assert together == [lane_scores(p, g, tol=1.0) for p, g in zip(preds, gts)]
    assert lane_scores_of_scenes([], []) == []
