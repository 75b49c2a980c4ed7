"""The road graph of SD maps, frame kinds, the pose sampler and per-frame statistics."""

import json
import math

import numpy as np
import pytest
import shapely
from conftest import SHARED_DATA, in_process

from cmtool.data.frames import DEFAULT_MIX, FrameSampler, frame_stats, mix_table, pick
from cmtool.data.scene import Pose
from cmtool.maps.roadgraph import road_graph
from cmtool.maps.sdmap import Road, SDMap

FINLAND = SHARED_DATA / "osm" / "finland_test.osm.pbf"


def sd_of(*roads) -> SDMap:
    return SDMap("PIT", [Road(f"r{k}", np.array(p, float), *rest) for k, (p, *rest) in enumerate(roads)])


def test_junction_kinds_from_shared_points_snapped_ends_and_crossings():
    graph = road_graph(sd_of(
        ([[-100, 0], [0, 0], [100, 0]],),  # through road
        ([[0, 0], [0, 100]],),  # T: ends on its shared point
        ([[300, -100], [300, 100]],),  # crossing mid-way, no shared point: X
        ([[200, 0], [400, 0]],),
        ([[600, -1.5], [600, 100]],),  # ends 1.5 m short of the road below: snapped, T
        ([[500, -3], [700, -3]],),
    ))
    kinds = sorted((round(j.centre[0]), j.kind, j.arms) for j in graph.junctions)
    assert kinds == [(0, "T", 3), (300, "X", 4), (600, "T", 3)]


def test_y_join_bridge_and_dead_ends():
    graph = road_graph(sd_of(
        ([[0, 0], [100, 0]],),
        ([[100, 0], [200, 0]],),  # continues the first way: a join, no junction
        ([[200, 0], [300, 120]],),
        ([[200, 0], [300, -120]],),  # a fork into two roads at 50 degrees each: Y
        ([[50, -50], [50, 50]], "residential", None, 0, False, 1),  # a bridge over the first way
    ))
    assert [(j.kind, j.arms) for j in graph.junctions] == [("Y", 3)]
    assert len(graph.joins) == 1 and np.allclose(graph.joins[0], [100, 0])
    ends = {tuple(p) for p in np.round(graph.dead_ends)}
    assert ends == {(0, 0), (300, 120), (300, -120), (50, -50), (50, 50)}


def test_divided_roads_are_opposite_one_way_pairs():
    graph = road_graph(sd_of(
        ([[0, 5], [200, 5]], "secondary", 2, -1),  # travels west
        ([[0, -5], [200, -5]], "secondary", 2, 1),  # travels east: its partner
        ([[0, 300], [200, 300]], "residential", 1, 1),  # a one-way street alone
        ([[0, 500], [200, 500]], "residential", 1, 1),  # two one-way roads the same way: not divided
        ([[0, 510], [200, 510]], "residential", 1, 1),
    ))
    assert graph.divided.tolist() == [True, True, False, False, False]


def grid(n=5, step=120.0) -> SDMap:
    """A street grid with one one-way street and a curved road hanging off one corner."""
    roads = []
    for k in range(n):
        xs = np.linspace(0, (n - 1) * step, 4 * (n - 1) + 1)
        roads.append((np.stack([xs, np.full_like(xs, k * step)], 1), "residential", 2, 1 if k == 2 else 0))
        roads.append((np.stack([np.full_like(xs, k * step), xs], 1), "residential", 2, 0))
    arc = np.radians(np.linspace(0, 120, 40))
    roads.append((np.stack([-150 + 150 * np.cos(arc), -150 * np.sin(arc)], 1) + [0, 0], "tertiary", None, 0))
    return sd_of(*roads)


def test_frame_kinds_on_a_grid():
    sampler = FrameSampler(grid())
    # road 0 runs east along y = 0 from the corner junction at (0, 0)
    assert sampler.classify(0, 0.0).label == "junction T"  # the corner where the curved road joins
    assert sampler.classify(0, 120.0).label == "junction T"  # on the grid's edge
    assert sampler.classify(2, 120.0).label == "junction X"
    assert sampler.classify(0, 60.0).kind == "straight"  # both junctions 60 m away, out of the frame
    ahead = sampler.classify(0, 100.0)  # facing east, the junction at x = 120 is 20 m ahead
    behind = sampler.classify(0, 20.0)  # the junction at x = 0 is 20 m behind
    assert (ahead.kind, behind.kind) == ("approach", "exit")
    assert sampler.classify(0, 100.0, flip=True).kind == "exit"  # facing west, the same junction is behind
    assert sampler.classify(4, 60.0).tags == ("oneway", "multilane")  # the one-way street of 2 lanes (y = 240)
    assert sampler.classify(0, 60.0).tags == ()  # two-way, 2 lanes in all
    arc = sampler.classify(10, 110.0)  # 110 m along the 120-degree arc of radius 150 m
    assert arc.kind == "curve"


def test_sample_follows_the_mix_spacing_and_roads():
    sd = grid(7)
    frames = FrameSampler(sd).sample(120, np.random.default_rng(0), min_spacing_m=10.0)
    assert len(frames) == 120
    counts = mix_table(frames)
    junctions = sum(v for k, v in counts.items() if k.startswith("junction"))
    assert junctions == pytest.approx(120 * DEFAULT_MIX["junction"], abs=3)
    assert counts["straight"] >= 120 * DEFAULT_MIX["straight"] - 3
    lines = [shapely.LineString(r.polyline) for r in sd.roads]
    for f in frames:
        assert shapely.distance(lines[f.road], shapely.Point(f.pose.x, f.pose.y)) < 1e-6
        if sd.roads[f.road].oneway == 1:  # faces the travel direction: east on the one-way street
            assert math.cos(f.pose.yaw) > 0.99
    xy = np.array([[f.pose.x, f.pose.y] for f in frames])
    gaps = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy)) * 1e9
    assert gaps.min() >= 10.0
    again = FrameSampler(sd).sample(120, np.random.default_rng(0), min_spacing_m=10.0)
    assert [f.pose for f in again] == [f.pose for f in frames]
    only = FrameSampler(sd).sample(10, np.random.default_rng(1), {"straight": 1.0})
    assert {f.kind for f in only} == {"straight"}


def test_frame_stats_on_known_frames():
    sd = sd_of(([[-200, 0], [200, 0]], "secondary", 2, 0),
               ([[-200, 40], [200, 40]], "secondary", None, 1),
               ([[200, 52], [-200, 52]], "secondary", None, 1))
    stats = frame_stats(sd, [Pose(0.0, 0.0, 0.0)])
    assert stats["roads"] == 1 and stats["road_m"] == pytest.approx(64.0)
    assert stats["oneway"] == 0 and stats["lanes_known"] == 1 and stats["junctions"] == 0
    both = frame_stats(sd, [Pose(0.0, 0.0, 0.0), Pose(0.0, 30.0, 0.0)])
    # the second frame (y from -2 to 62) holds all three roads, 64 m each
    assert both["roads"] == pytest.approx((1 + 3) / 2)
    assert both["divided"] == pytest.approx(128.0 / (64 + 64 + 128))
    assert both["oneway"] == both["divided"]


def test_stats_and_sampler_on_real_osm():
    pytest.importorskip("osmium")
    from cmtool.formats.osm import read_osm

    sd = read_osm(FINLAND)
    sampler = FrameSampler(sd)
    frames = sampler.sample(200, np.random.default_rng(0))
    counts = mix_table(frames)
    assert counts["divided"] > 0 and counts["oneway"] >= counts["divided"]
    assert {k for k in counts if k.startswith("junction")} >= {"junction T", "junction X"}
    stats = frame_stats(sd, [f.pose for f in frames], sampler.graph)
    assert 0.0 < stats["lanes_known"] < 0.3  # mappers tagged few lane counts in this extract
    assert 0.5 < stats["junctions"] < 2.0


def test_data_poses_on_sd_map_and_osm_feeds_sample(tmp_path, capsys, sampling_ckpt):
    sd_path = tmp_path / "grid.json"
    grid().save(sd_path)
    code, out, err = in_process(capsys, "data", "poses", sd_path, "--n", "6", "--seed", "1")
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == 6 and all(set(r) == {"x", "y", "yaw", "kind"} for r in rows)
    code, _, err = in_process(capsys, "data", "poses", sd_path, "--latlon")
    assert code != 0 and "geographic origin" in err and "Traceback" not in err

    pytest.importorskip("osmium")
    centres = tmp_path / "centres.jsonl"
    code, out, err = in_process(capsys, "data", "poses", FINLAND, "--n", "2", "--latlon", "--kind", "junction",
                                "--out", centres)
    assert code == 0, err
    rows = [json.loads(line) for line in centres.read_text().splitlines()]
    assert len(rows) == 2 and all(r["kind"].startswith("junction") for r in rows)
    assert all(abs(r["lat"] - 60.53) < 0.02 and abs(r["lon"] - 26.95) < 0.04 for r in rows)
    code, out, err = in_process(capsys, "sample", "--ckpt", sampling_ckpt["controlmap"], "--osm", FINLAND,
                                "--center", centres, "--steps", "2", "--no-log", "--quiet", "--out", tmp_path / "s")
    assert code == 0, err
    for k in range(2):  # the SD raster of each frame has its road through the centre
        assert (tmp_path / "s" / f"finland_test_{k}.json").is_file()


def test_data_poses_bad_inputs(tmp_path, capsys):
    empty = tmp_path / "empty.osm"
    empty.write_text('<?xml version="1.0"?>\n<osm version="0.6">\n  <node id="1" lat="60.5" lon="26.9"/>\n'
                     '  <node id="2" lat="60.6" lon="26.9"/>\n  <way id="3"><nd ref="1"/><nd ref="2"/>'
                     '<tag k="highway" v="footway"/></way>\n</osm>\n')
    code, out, err = in_process(capsys, "data", "poses", empty, "--out", tmp_path / "p.jsonl")
    assert code != 0 and "no drivable roads" in err and err.count("\n") == 1
    assert not (tmp_path / "p.jsonl").exists()
    code, _, err = in_process(capsys, "data", "poses", empty, "--kind", "roundabout")
    assert code != 0 and "--kind" in err
    sd_path = tmp_path / "grid.json"
    grid().save(sd_path)
    code, _, err = in_process(capsys, "data", "poses", sd_path, "--n", "3", "--near-junction", "0")
    assert code != 0 and "found 0 of 3 poses within 0 m of a junction" in err


def test_sample_at_a_centre_outside_the_extract(tmp_path, capsys, sampling_ckpt):
    pytest.importorskip("osmium")
    code, _, err = in_process(capsys, "sample", "--ckpt", sampling_ckpt["controlmap"], "--osm", FINLAND,
                              "--center", "60.60,26.95", "--no-log", "--quiet", "--out", tmp_path / "s")
    assert code != 0 and "no roads within the 64 m frame" in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()


def test_data_frames_compares_sources_with_a_recipe(tmp_path, capsys):
    from conftest import REPO

    sd_path = tmp_path / "grid.json"
    grid().save(sd_path)
    code, out, err = in_process(capsys, "data", "frames", sd_path, "--recipe", REPO / "recipes" / "data_tiny.toml",
                                "--maps", "1", "--n", "30", "--png", tmp_path / "f.png", "--json", tmp_path / "f.json")
    assert code == 0, err
    header = out.splitlines()[0].split()
    assert header[-6:] == ["grid", "LAV", "PIT", "SGP", "BOS", "derived"]
    numbers = json.loads((tmp_path / "f.json").read_text())["columns"]
    assert numbers["grid"]["frames"] == 30 and numbers["derived"]["frames"] == 4 * 8  # data_tiny: 8 scenes a map
    assert 0.5 < numbers["grid"]["lanes_known"] < 1.0  # the arc has no lane count, the streets have
    assert numbers["grid"]["oneway"] > 0 and numbers["grid"]["divided"] == 0
    per_city = [numbers[c]["roads"] for c in ("LAV", "PIT", "SGP", "BOS")]
    assert numbers["derived"]["roads"] == pytest.approx(np.mean(per_city))  # equal frames per city
    assert (tmp_path / "f.png").stat().st_size > 10_000
    code, _, err = in_process(capsys, "data", "frames")
    assert code != 0 and "nothing to measure" in err


def test_frames_only_on_the_roads_given():
    sampler = FrameSampler(grid())
    frames = sampler.sample(40, np.random.default_rng(3), roads={0, 5})
    assert len(frames) == 40 and {f.road for f in frames} == {0, 5}
    assert sampler.sample(5, np.random.default_rng(3), roads=set()) == []


def _old_frame(sampler: FrameSampler, road: int, at: float, flip: bool) -> tuple:
    """A pose's frame as the sampler classified it one pose at a time, before the batched search (its fields)."""
    from cmtool.core.geometry import to_frame
    from cmtool.data.frames import CURVE_DEG, JUNCTION_M

    line, info, half = sampler.graph.lines[road], sampler.sd.roads[road], sampler.frame_m / 2.0
    p0, p1 = (shapely.get_coordinates(shapely.line_interpolate_point(line, [at - 1.0, at + 1.0]))
              if sampler.lengths[road] > 0 else (np.zeros(2), np.array([1.0, 0.0])))
    d = p0 - p1 if info.oneway == -1 or (info.oneway == 0 and flip) else p1 - p0
    x, y = shapely.get_coordinates(shapely.line_interpolate_point(line, at))[0]
    pose = Pose(float(x), float(y), float(np.arctan2(d[1], d[0])))
    centres, nearest_m, kind = sampler.graph.centres, float("inf"), None
    if len(centres):
        ego = to_frame(centres, pose.x, pose.y, pose.yaw)
        dist = np.linalg.norm(ego, axis=1)
        k = int(np.argmin(dist))
        nearest_m = float(dist[k])
        inside = np.flatnonzero(np.all(np.abs(ego) <= half, axis=1))
        if dist[k] <= JUNCTION_M:
            kind = f"junction {sampler.graph.junctions[k].kind}"
        elif len(inside):
            kind = "approach" if ego[inside[np.argmin(dist[inside])], 0] > 0 else "exit"
    ends = sampler.graph.dead_ends
    if kind is None and len(ends) and np.any(np.all(np.abs(to_frame(ends, pose.x, pose.y, pose.yaw)) <= half, 1)):
        kind = "end"
    if kind is None:
        ahead = np.clip([at - half, at - half + 2.0, at + half - 2.0, at + half], 0.0, shapely.length(line))
        pts = shapely.get_coordinates(shapely.line_interpolate_point(line, ahead))
        d0, d1 = pts[1] - pts[0], pts[3] - pts[2]
        kind = "curve" if abs(np.degrees(np.arctan2(d0[0] * d1[1] - d0[1] * d1[0], d0 @ d1))) >= CURVE_DEG \
            else "straight"
    return pose, kind, nearest_m


def test_batched_classification_and_spacing_equal_the_pose_by_pose_ones():
    """The sampler classifies all candidates at once (KD-trees of junctions and dead ends) and spaces them with a grid
    of the poses taken: the same frames as pose by pose and against every pose taken, on the Finland extract."""
    from cmtool.data.frames import read_sd_source

    sampler = FrameSampler(read_sd_source(FINLAND) if FINLAND.exists() else grid())
    rng = np.random.default_rng(3)
    road = rng.integers(0, len(sampler.sd.roads), 400)
    at, flip = rng.uniform(0.0, 1.0, 400) * sampler.lengths[road], rng.random(400) < 0.5
    frames = sampler._frames(sampler._classify(road, at, flip), np.arange(len(road)))  # all at once
    for frame, r, a, f in zip(frames, road.tolist(), at.tolist(), flip.tolist()):
        assert (frame.pose, frame.label, frame.junction_m) == _old_frame(sampler, r, a, f)
    kinds, xy = np.array([f.kind for f in frames], object), np.array([[f.pose.x, f.pose.y] for f in frames])
    for n, spacing in ((50, 25.0), (300, 25.0), (400, 0.0), (400, 3.0)):
        assert pick(kinds, xy, n, DEFAULT_MIX, spacing) == _old_pick(kinds, xy, n, DEFAULT_MIX, spacing)


def _old_pick(kinds, xy, n: int, mix: dict, spacing: float) -> list[int]:
    """The sampler's choice of frames as it was: every candidate against every frame taken so far."""
    weights = {k: w for k, w in mix.items() if k in set(kinds) and w > 0}
    quota = {k: int(np.ceil(n * w / (sum(weights.values()) or 1.0))) for k, w in weights.items()}
    taken, count = [], {}
    for rule in ("quota", "spacing", "any"):
        for i, kind in enumerate(kinds):
            if len(taken) == n:
                break
            if i in taken or (rule != "any" and taken and np.min(np.linalg.norm(xy[taken] - xy[i], axis=1)) < spacing):
                continue
            if rule == "quota" and count.get(kind, 0) >= quota.get(kind, 0):
                continue
            taken.append(i)
            count[kind] = count.get(kind, 0) + 1
    return taken
