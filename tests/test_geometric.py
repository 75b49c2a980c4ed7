"""Geometric metrics on hand-made lanes and SD rasters with known answers."""

import math

import numpy as np
import pytest

from cmtool.data.sd_raster import rasterize_sd
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.geometric import chamfer, driving_side, legal_oneway, oncoming_side, sd_adherence


def line(y, x0=-30.0, x1=30.0, n=20):
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=-1)


def straight_road(oneway=0):
    sd = SDMap(roads=[Road("r", np.array([[-40.0, 0.0], [40.0, 0.0]]), lanes=2, oneway=oneway)])
    return rasterize_sd(sd, 0.0, 0.0, 0.0)


def test_chamfer():
    assert chamfer([line(0.0)], [line(0.0)]) == pytest.approx(0.0, abs=1e-9)
    assert chamfer([line(0.0)], [line(2.0)]) == pytest.approx(2.0)
    assert chamfer([line(0.0)], [line(2.0), line(0.0)]) == pytest.approx(0.5 * (0.0 + 1.0))
    assert math.isnan(chamfer([], [line(0.0)]))


def test_sd_adherence():
    sd = straight_road()
    both = [line(-1.75), line(1.75)[::-1]]
    assert sd_adherence(both, sd) == {"sd_coverage": 1.0, "lane_on_sd": 1.0}
    far = sd_adherence([line(20.0)], sd)
    assert far == {"sd_coverage": 0.0, "lane_on_sd": 0.0}
    half = sd_adherence([line(-1.75, x0=0.0, x1=31.9)], sd)  # the front half of the road, +3 m behind it
    assert half["sd_coverage"] == pytest.approx(35 / 64, abs=0.02) and half["lane_on_sd"] == 1.0
    assert math.isnan(sd_adherence([], sd)["lane_on_sd"]) and sd_adherence([], sd)["sd_coverage"] == 0.0
    assert math.isnan(sd_adherence(both, np.zeros_like(sd))["sd_coverage"])


def test_driving_side():
    sd = straight_road()
    right_hand = [line(-1.75), line(1.75)[::-1]]  # forward on the right half, backward on the left half
    share, judged = driving_side(right_hand, sd, "right")
    assert share == 1.0 and judged > 200
    assert driving_side(right_hand, sd, "left")[0] == 0.0
    left_hand = [line(1.75), line(-1.75)[::-1]]
    assert driving_side(left_hand, sd, "left")[0] == 1.0
    # lanes on the centre line, on one-way roads or away from roads are not judged
    assert driving_side([line(0.0)], sd, "right")[1] == 0
    assert math.isnan(driving_side(right_hand, straight_road(oneway=1), "right")[0])
    assert math.isnan(driving_side([line(25.0)], sd, "right")[0])
    with pytest.raises(ValueError):
        driving_side(right_hand, sd, "middle")


def test_oncoming_side_needs_no_sd_map():
    right_hand = [line(-1.75), line(1.75)[::-1]]  # oncoming lane on the left of each
    share, judged = oncoming_side(right_hand, "right")
    assert share == 1.0 and judged > 100
    assert oncoming_side(right_hand, "left")[0] == 0.0
    assert oncoming_side([line(1.75), line(-1.75)[::-1]], "left")[0] == 1.0
    # two lanes of one direction, lanes too far apart, or a single lane: nothing to judge
    assert oncoming_side([line(-1.75), line(1.75)], "right")[1] == 0
    assert oncoming_side([line(-8.0), line(8.0)[::-1]], "right")[1] == 0
    assert math.isnan(oncoming_side([line(-1.75)], "right")[0])
    # a crossing road's lane (perpendicular) does not count; a second road, left-hand, halves the share
    crossing = [np.stack([np.full(65, 10.0), np.linspace(-32, 32, 65)], 1)]
    assert oncoming_side(right_hand + crossing, "right")[0] == 1.0
    assert oncoming_side(right_hand + [line(21.75), line(18.25)[::-1]], "right")[0] == pytest.approx(0.5)
    with pytest.raises(ValueError):
        oncoming_side(right_hand, "middle")


def test_legal_oneway_judges_lanes_along_one_way_roads_by_their_heading():
    forward = straight_road(oneway=1)  # travel along +x
    lanes = [line(-1.75), line(1.75)]
    share, length = legal_oneway(lanes, forward)
    assert share == 1.0 and length == pytest.approx(2 * 60.0, abs=2.0)
    assert legal_oneway([l[::-1] for l in lanes], forward)[0] == 0.0
    assert legal_oneway([line(-1.75), line(1.75)[::-1]], forward)[0] == pytest.approx(0.5, abs=0.02)
    assert legal_oneway(lanes, straight_road(oneway=-1))[0] == 0.0
    # lanes across the road, far from it, or on two-way roads are not judged
    across = np.stack([np.full(20, 5.0), np.linspace(-30.0, 30.0, 20)], axis=-1)
    assert math.isnan(legal_oneway([across], forward)[0])
    assert legal_oneway([line(20.0)], forward) == (pytest.approx(math.nan, nan_ok=True), 0.0)
    assert math.isnan(legal_oneway(lanes, straight_road())[0])
    assert math.isnan(legal_oneway([], forward)[0])


def test_headings_of_all_pieces_equal_np_gradient_of_each():
    from cmtool.metrics.geometric import _headings

    rng = np.random.default_rng(2)
    pieces = [np.cumsum(rng.normal(0, 1, (int(rng.integers(2, 12)), 2)), axis=0) for _ in range(300)]
    points, dirs = _headings(pieces)
    gradient = np.concatenate([np.gradient(p, axis=0) for p in pieces])
    np.testing.assert_array_equal(points, np.concatenate(pieces))
    np.testing.assert_array_equal(dirs, gradient / np.maximum(np.linalg.norm(gradient, axis=1, keepdims=True), 1e-9))


def test_remembered_rasters_and_lanes_answer_only_for_equal_ones():
    """The scores remember the last rasters and lane sets they saw: a raster or lanes changed in place, or another
    frame size, are measured anew."""
    from cmtool.metrics import geometric

    sd, lanes = straight_road(oneway=1), [line(-1.75), line(1.75)[::-1]]
    first = legal_oneway(lanes, sd), geometric.legal_oneway_by_lane(lanes, sd)[0].tolist(), sd_adherence(lanes, sd)
    assert first[0] == (0.5, pytest.approx(120.0, abs=2.0)) and first[1] == [1.0, 0.0]
    assert (legal_oneway(lanes, sd), geometric.legal_oneway_by_lane(lanes, sd)[0].tolist(), sd_adherence(lanes, sd)) \
        == first
    lanes[1][:] = lanes[1][::-1].copy()  # turned round in place: now legal
    assert legal_oneway(lanes, sd)[0] == 1.0
    sd[..., 0] = 0  # the roads gone
    assert math.isnan(legal_oneway(lanes, sd)[0]) and math.isnan(sd_adherence(lanes, sd)["sd_coverage"])
    assert sd_adherence(lanes, straight_road(), frame_m=128.0) != sd_adherence(lanes, straight_road())
