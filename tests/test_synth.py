"""Procedural cities: consistent lane graphs, correct handedness, no crossing road lanes, and four
measurably different styles."""

from functools import lru_cache

import numpy as np
import pytest
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.data.synth import CITIES, generate_city
from cmtool.maps.hdmap import HDMap

CASES = [(city, seed, extent) for city in CITIES for seed, extent in ((0, 800.0), (5, 500.0))]


@lru_cache(maxsize=None)
def city_map(city: str, seed: int, extent: float) -> HDMap:
    return generate_city(city, seed, extent)


def road_lanes(hd):
    return [l for l in hd.lanes.values() if not l.is_intersection]


def connectors(hd):
    return [l for l in hd.lanes.values() if l.is_intersection]


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def directions(hd):
    """road_id -> lanes grouped by travel direction (two groups for two-way roads)."""
    out = {}
    for lane in road_lanes(hd):
        groups = out.setdefault(lane.road_id, [])
        d = unit(lane.centerline[-1] - lane.centerline[0])
        for g in groups:
            if np.dot(d, unit(g[0].centerline[-1] - g[0].centerline[0])) > 0:
                g.append(lane)
                break
        else:
            groups.append([lane])
    return out


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}-{int(c[2])}")
def test_consistent_and_round_trips(case):
    city, seed, extent = case
    hd = city_map(*case)
    assert hd.city == city and hd.source == f"procedural:{city}:seed={seed}"
    assert hd.drives_on == ("left" if city == "SGP" else "right")
    assert hd.meta["style"]["block"] and hd.meta["seed"] == seed
    assert hd.reference_errors() == []
    back = HDMap.from_json(hd.to_json())
    assert len(back.lanes) == len(hd.lanes)
    assert all(back.lanes[i].successors == l.successors for i, l in hd.lanes.items())
    assert all(l.road_id and not l.intersection_id for l in road_lanes(hd))
    assert all(l.intersection_id and not l.road_id for l in connectors(hd))
    widths = np.array([l.width for l in hd.lanes.values()])
    assert widths.min() >= 3.0 and widths.max() <= 3.7
    xmin, ymin, xmax, ymax = hd.bounds()
    assert xmin < 0.1 * extent and ymin < 0.1 * extent and xmax > 0.9 * extent and ymax > 0.9 * extent


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}-{int(c[2])}")
def test_connectors_join_road_lanes_of_their_intersection(case):
    hd = city_map(*case)
    centres = {}
    for c in connectors(hd):
        centres.setdefault(c.intersection_id, []).append(c.centerline.mean(axis=0))
    for c in connectors(hd):
        assert len(c.predecessors) == 1 and len(c.successors) == 1, c.id
        a, b = hd.lanes[c.predecessors[0]], hd.lanes[c.successors[0]]
        assert not a.is_intersection and not b.is_intersection
        assert a.road_id != b.road_id  # no U-turns
        assert np.abs(a.centerline[-1] - c.centerline[0]).max() < 1e-6
        assert np.abs(b.centerline[0] - c.centerline[-1]).max() < 1e-6
        centre = np.mean(centres[c.intersection_id], axis=0)
        assert np.linalg.norm(a.centerline[-1] - centre) < 60.0
        assert np.linalg.norm(b.centerline[0] - centre) < 60.0
        # tangent continuity at both ends
        assert np.dot(unit(c.centerline[1] - c.centerline[0]), unit(a.centerline[-1] - a.centerline[-2])) > 0.9
        assert np.dot(unit(c.centerline[-1] - c.centerline[-2]), unit(b.centerline[1] - b.centerline[0])) > 0.9
    # road lanes only link to connectors; away from the map border every lane goes on and is reached
    extent = case[2]
    assert all(hd.lanes[s].is_intersection for l in road_lanes(hd) for s in l.successors)
    for lane in road_lanes(hd):
        inside = lambda p: bool(np.all((p > 15.0) & (p < extent - 15.0)))  # noqa: E731
        assert lane.successors or not inside(lane.centerline[-1]), lane.id
        assert lane.predecessors or not inside(lane.centerline[0]), lane.id


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}-{int(c[2])}")
def test_handedness_is_geometric(case):
    """Seen in its travel direction, a lane has the opposite direction of its road on its left
    (right-hand traffic) or on its right (SGP); the near-side turn is the short one."""
    hd = city_map(*case)
    side = 1.0 if hd.drives_on == "right" else -1.0
    two_way = [g for g in directions(hd).values() if len(g) == 2]
    assert len(two_way) >= 2
    for ga, gb in two_way:
        for mine, theirs in ((ga, gb), (gb, ga)):
            other = shapely.MultiLineString([l.centerline for l in theirs])
            for lane in mine:
                k = len(lane.centerline) // 2
                p = lane.centerline[k]
                tangent = lane.centerline[min(k + 1, len(lane.centerline) - 1)] - lane.centerline[max(k - 1, 0)]
                q = np.array(shapely.shortest_line(shapely.Point(p), other).coords[1])
                assert side * cross(tangent, q - p) > 0, lane.id
    turns = {"right": [], "left": []}
    for c in connectors(hd):
        a = unit(c.centerline[1] - c.centerline[0])
        b = unit(c.centerline[-1] - c.centerline[-2])
        angle = np.degrees(np.arctan2(cross(a, b), np.dot(a, b)))
        if abs(angle) > 60:
            turns["left" if angle > 0 else "right"].append(shapely.LineString(c.centerline).length)
    short, long_ = ("right", "left") if side > 0 else ("left", "right")
    assert np.median(turns[short]) < np.median(turns[long_])


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}-{int(c[2])}")
def test_road_lanes_never_cross(case):
    hd = city_map(*case)
    lanes = road_lanes(hd)
    lines = [shapely.LineString(l.centerline) for l in lanes]
    a, b = shapely.STRtree(lines).query(lines, predicate="intersects")
    for i, j in zip(a, b):
        if i < j:
            li, lj = lanes[i], lanes[j]
            assert lj.id in li.successors or li.id in lj.successors, (li.id, lj.id)
            assert shapely.intersection(lines[i], lines[j]).geom_type == "Point"
    # lanes of a road keep at least a lane width apart
    for groups in directions(hd).values():
        group_lines = [shapely.LineString(l.centerline) for g in groups for l in g]
        for i, li in enumerate(group_lines):
            for lj in group_lines[i + 1:]:
                assert li.distance(lj) > 2.9


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1]}-{int(c[2])}")
def test_lights_and_crosswalks(case):
    hd = city_map(*case)
    assert hd.stop_lines and hd.crosswalks
    by_node = {}
    for sl in hd.stop_lines:
        assert sl.state in ("green", "red") and sl.lane_ids
        starts = np.array([hd.lanes[i].centerline[0] for i in sl.lane_ids])
        assert {hd.lanes[i].intersection_id for i in sl.lane_ids} == {hd.lanes[sl.lane_ids[0]].intersection_id}
        assert shapely.LineString(sl.line).distance(shapely.MultiPoint(starts)) < 1e-6
        by_node.setdefault(hd.lanes[sl.lane_ids[0]].intersection_id, set()).add(sl.state)
    assert all(states == {"green", "red"} for states in by_node.values())
    roads = shapely.MultiLineString([l.centerline for l in road_lanes(hd)])
    conns = shapely.MultiLineString([l.centerline for l in connectors(hd)])
    for cw in hd.crosswalks:
        poly = shapely.Polygon(cw.polygon)
        assert len(cw.polygon) == 4 and poly.is_valid
        assert not poly.intersects(roads) and poly.intersects(conns)


def test_styles_differ():
    stats = {}
    for city in CITIES:
        lanes_per_dir, one_way, medians, lengths = [], [], [], []
        for seed in (0, 5):
            hd = city_map(city, seed, 800.0 if seed == 0 else 500.0)
            for road_id, groups in directions(hd).items():
                lanes_per_dir += [len(g) for g in groups]
                one_way.append(len(groups) == 1)
                lengths.append(shapely.LineString(groups[0][0].centerline).length)
                if len(groups) == 2:
                    a = shapely.MultiLineString([l.centerline for l in groups[0]])
                    b = shapely.MultiLineString([l.centerline for l in groups[1]])
                    medians.append(a.distance(b) - groups[0][0].width)
        stats[city] = dict(lanes=np.mean(lanes_per_dir), one_way=np.mean(one_way), median=np.max(medians),
                           length=np.median(lengths))
    assert stats["LAV"]["lanes"] > 2.0 and stats["PIT"]["lanes"] == pytest.approx(1.0, abs=0.05)
    assert stats["LAV"]["lanes"] > stats["SGP"]["lanes"] > stats["PIT"]["lanes"]
    assert 0.35 <= stats["BOS"]["one_way"] <= 0.7
    assert stats["BOS"]["one_way"] > 2 * max(stats[c]["one_way"] for c in ("LAV", "PIT", "SGP"))
    assert stats["SGP"]["median"] >= 1.9 and max(stats[c]["median"] for c in ("LAV", "PIT", "BOS")) < 0.1
    assert stats["LAV"]["length"] > stats["PIT"]["length"] > stats["BOS"]["length"]
    lav, sgp = city_map("LAV", 0, 800.0), city_map("SGP", 0, 800.0)
    assert any(l.lane_type == "bus" for l in [*lav.lanes.values(), *sgp.lanes.values()])


def test_deterministic_and_seeded():
    a = generate_city("BOS", 3, 300.0).to_json()
    assert a == generate_city("BOS", 3, 300.0).to_json()
    assert a != generate_city("BOS", 4, 300.0).to_json()
    small = generate_city("LAV", 1, 200.0)
    assert small.reference_errors() == [] and connectors(small)


def test_bad_arguments():
    with pytest.raises(CmtoolError, match=r"^unknown city 'XYZ' \(choose from LAV, PIT, SGP, BOS\)$"):
        generate_city("XYZ")
    with pytest.raises(CmtoolError, match="extent"):
        generate_city("PIT", 0, 150.0)
    with pytest.raises(CmtoolError, match="seed"):
        generate_city("PIT", -1)
