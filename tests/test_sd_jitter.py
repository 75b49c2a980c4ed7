"""OpenStreetMap-like imperfections of derived SD maps (cmtool.data.sd_jitter)."""

import numpy as np
import pytest
import shapely

from cmtool.data.sd_jitter import SDJitter, apply_jitter
from cmtool.maps.sdmap import Road, SDMap


def town() -> SDMap:
    """Two long roads crossing at a shared point, a curved minor road ending on one, and a service road."""
    xs = np.linspace(-300.0, 300.0, 61)
    arc = np.radians(np.linspace(0.0, 90.0, 46))
    roads = [
        Road("a", np.stack([xs, np.zeros_like(xs)], 1), "secondary", 4, 0),
        Road("b", np.stack([np.zeros_like(xs), xs], 1), "residential", 2, 0),
        Road("c", np.stack([100.0 + 150.0 * np.sin(arc), 150.0 - 150.0 * np.cos(arc) + 0.0], 1), "residential", 2, 0),
        Road("d", np.array([[-200.0, -100.0], [-200.0, -250.0]]), "service", 1, 1),
    ]
    roads[2].polyline[0] = [100.0, 0.0]  # starts on road a, at one of its points
    return SDMap("PIT", roads, "test")


def shared_points(sd: SDMap) -> set:
    seen, shared = {}, set()
    for r in sd.roads:
        for p in {tuple(np.round(p, 3)) for p in r.polyline}:
            if p in seen and seen[p] != r.id:
                shared.add(p)
            seen[p] = r.id
    return shared


def test_off_is_identity_and_seeded():
    sd = town()
    assert not SDJitter().enabled
    assert apply_jitter(sd, SDJitter(), 3).to_json() == sd.to_json()
    j = SDJitter(offset_m=2.0, wobble_m=1.0, simplify_m=1.0, lanes_known_minor=0.5, service_stubs_per_km=5.0)
    assert j.enabled
    assert apply_jitter(sd, j, 7).to_json() == apply_jitter(sd, j, 7).to_json()
    assert apply_jitter(sd, j, 7).to_json() != apply_jitter(sd, j, 8).to_json()


def test_lane_counts_dropped_by_class():
    sd = SDMap("PIT", [Road(f"r{k}", np.array([[0.0, 10.0 * k], [50.0, 10.0 * k]]),
                            "secondary" if k % 2 else "residential", 2, 0) for k in range(400)])
    out = apply_jitter(sd, SDJitter(lanes_known_major=0.5, lanes_known_minor=0.0), 0)
    major = [r.lanes for r in out.roads if r.road_class == "secondary"]
    minor = [r.lanes for r in out.roads if r.road_class == "residential"]
    assert all(v is None for v in minor)
    assert 0.4 < np.mean([v is not None for v in major]) < 0.6 and {v for v in major} == {None, 2}


def test_simplify_keeps_nodes_and_stays_within_tolerance():
    sd = town()
    out = apply_jitter(sd, SDJitter(simplify_m=2.0), 0)
    assert shared_points(out) == shared_points(sd) != set()
    for before, after in zip(sd.roads, out.roads):
        assert len(after.polyline) <= len(before.polyline)
        assert shapely.hausdorff_distance(shapely.LineString(before.polyline),
                                          shapely.LineString(after.polyline)) <= 2.0 + 1e-9
    curve = out.roads[2].polyline
    assert 3 <= len(curve) < 20  # the quarter circle of 46 points needs only a few within 2 m


def test_wobble_moves_smoothly_and_keeps_shared_points():
    sd = town()
    out = apply_jitter(sd, SDJitter(wobble_m=1.5, wobble_wavelength_m=150.0), 2)
    assert len(shared_points(out)) == len(shared_points(sd)) == 2  # moved, still shared
    moves = [np.linalg.norm(a.polyline - b.polyline, axis=1) for a, b in zip(out.roads, sd.roads)]
    rms = np.sqrt(np.mean(np.concatenate(moves) ** 2))
    assert 0.5 < rms < 3.0
    steps = np.abs(np.diff(out.roads[0].polyline - sd.roads[0].polyline, axis=0))  # neighbours 10 m apart
    assert steps.max() < 0.5  # move alike: smooth, not per-point noise


def test_service_stubs_branch_at_a_shared_point_and_keep_clear():
    sd = town()
    out = apply_jitter(sd, SDJitter(service_stubs_per_km=20.0), 1)
    stubs = [r for r in out.roads if r.id.startswith("s")]
    assert len(stubs) >= 5
    others = [shapely.LineString(r.polyline) for r in sd.roads]
    parents = {tuple(np.round(p, 3)) for r in out.roads if not r.id.startswith("s") for p in r.polyline}
    for stub in stubs:
        assert (stub.road_class, stub.lanes, stub.oneway) == ("service", None, 0)
        assert tuple(np.round(stub.polyline[0], 3)) in parents  # branches at a point of its road
        assert 15.0 <= shapely.length(shapely.LineString(stub.polyline)) <= 40.0
        tip = shapely.Point(stub.polyline[-1])
        assert min(shapely.distance(tip, o) for o in others) >= 8.0


@pytest.mark.parametrize("bad, message", [({"offset_m": -1.0}, "offset_m"), ({"lanes_known_major": 1.5}, "probability"),
                                          ({"wobble_wavelength_m": 0.0}, "wobble_wavelength_m"),
                                          ({"simplify_m": float("nan")}, "simplify_m")])
def test_problems_name_the_field(bad, message):
    assert any(message in p for p in SDJitter(**bad).problems())
