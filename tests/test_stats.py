import numpy as np
import pytest
from fixtures.hdmaps import add_road, connect_intersection, crossroads

from cmtool.data.stats import map_stats
from cmtool.maps.hdmap import HDMap

KEYS = {"lanes_per_road", "block_length_m", "intersection_degree", "curvature_deg_per_100m", "oneway_share",
        "lane_width_m", "lanes", "intersections", "road_km"}


def test_crossroads_stats():
    hd = crossroads()
    s = map_stats(hd)
    assert set(s) == KEYS and all(isinstance(v, float) for v in s.values())
    assert s["intersections"] == 1.0 and s["intersection_degree"] == 4.0
    assert s["lanes"] == float(len(hd.lanes))
    # the EW road (2 lanes) and NS road (4 lanes) have the same length
    assert s["lanes_per_road"] == pytest.approx(3.0, abs=0.05)
    assert s["road_km"] == pytest.approx(0.2 * 2, abs=0.01)
    assert s["curvature_deg_per_100m"] == pytest.approx(0.0, abs=1e-6)
    assert s["oneway_share"] == 0.0 and s["lane_width_m"] == pytest.approx(3.5)
    assert s["block_length_m"] == 0.0  # no piece lies between two intersections


def two_blocks(oneway: bool) -> HDMap:
    """Three parallel-ish crossings on an east-west road: blocks of 100 m between them."""
    hd = HDMap(city="TST")
    xs = (0.0, 100.0, 200.0)
    for k, (a, b) in enumerate(((-80.0, -12.0), (12.0, 88.0), (112.0, 188.0), (212.0, 280.0))):
        add_road(hd, "ABCD"[k], (a, 0), (b, 0), forward=1, backward=0 if oneway else 1, width=3.0)
    for k, x in enumerate(xs):
        add_road(hd, "SNTU"[k], (x, -80), (x, -12))
        add_road(hd, "nuvw"[k], (x, 12), (x, 80))
    for k, x in enumerate(xs):
        connect_intersection(hd, f"I{k}", (x, 0))
    return hd


def test_block_length_degree_and_oneway_share():
    s = map_stats(two_blocks(oneway=False))
    assert s["intersections"] == 3.0 and s["intersection_degree"] == 4.0
    assert s["block_length_m"] == pytest.approx(100.0, abs=0.5)
    assert s["lane_width_m"] == pytest.approx((3.0 * 8 * 68 + 3.0 * 2 * 76 * 2 + 3.5 * 12 * 68) / (
        8 * 68 + 2 * 76 * 2 + 12 * 68), abs=0.1)
    one = map_stats(two_blocks(oneway=True))
    # the one-way east-west road is 360 m long, the six two-way streets 3 * 160 m
    assert one["oneway_share"] == pytest.approx(360 / (360 + 480), abs=0.03)


def test_curvature_of_a_bent_road():
    hd = HDMap(city="TST")
    add_road(hd, "A", (0, 0), (100, 0), road_id=False)  # two lane pieces, linked, bent by 30 degrees
    add_road(hd, "B", (100, 0), (100 + 100 * np.cos(np.radians(30)), 100 * np.sin(np.radians(30))), road_id=False)
    hd.link("Af0", "Bf0")
    hd.link("Bb0", "Ab0")
    s = map_stats(hd)
    assert s["curvature_deg_per_100m"] == pytest.approx(30.0 / 2.0, rel=0.1)  # 30 degrees over 200 m


@pytest.fixture(scope="module")
def city_stats():
    synth = pytest.importorskip("cmtool.data.synth")
    out = {}
    for city in ("LAV", "PIT", "SGP", "BOS"):
        runs = [map_stats(synth.generate_city(city, seed=seed, extent=600.0)) for seed in (0, 1)]
        out[city] = {k: float(np.mean([r[k] for r in runs])) for k in KEYS}
    return out


def test_city_styles_differ(city_stats):
    lav, pit, bos = city_stats["LAV"], city_stats["PIT"], city_stats["BOS"]
    assert lav["lanes_per_road"] > bos["lanes_per_road"]
    assert lav["block_length_m"] > bos["block_length_m"]
    assert pit["curvature_deg_per_100m"] > lav["curvature_deg_per_100m"]
    assert bos["oneway_share"] > lav["oneway_share"]
    assert pit["lane_width_m"] < lav["lane_width_m"]
    for s in city_stats.values():
        assert s["intersections"] > 3 and s["road_km"] > 1.0 and 2.5 <= s["intersection_degree"] <= 5.0
