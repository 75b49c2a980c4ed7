"""Huge lane graphs (docs/speed.md, "Huge scenes"): 100,000 lanes, spread like a city and packed into 1 km, through
``validate``, ``validate --repair``, ``metrics --no-features`` and every ``export`` format, in subprocesses with
generous timeouts (no timing asserted); and the fast paths behind them against the all-pairs ones they replaced."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import shapely

from cmtool.maps.lanegraph import LaneGraph

HUGE = 100_000
# these two 41 MB maps take 25 s to over 2 minutes a command on 2 shared cores (docs/speed.md, "Huge scenes"), some
# 15 minutes in all, too slow for every CI run: opt in. The scene of 100,000 lanes goes through every command
# in every run (tests/test_faults_bounds.py)
huge_commands = pytest.mark.skipif(not os.environ.get("CMTOOL_HUGE_MAPS"), reason="set CMTOOL_HUGE_MAPS=1 to run")


def random_lanes(n: int, half: float, seed: int = 0) -> list[list[list[float]]]:
    """``n`` random bent lanes of 5 to 30 m (20 points each, millimetres) in a square of side ``2 * half`` metres:
    the generator of docs/speed.md."""
    rng, t, lanes = np.random.default_rng(seed), np.linspace(0, 1, 20)[:, None], []
    for _ in range(n):
        p0, a = rng.uniform(-half, half, 2), rng.uniform(-np.pi, np.pi)
        length, bend = rng.uniform(5, 30), rng.normal(0, 0.3)
        d, side = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        lanes.append(np.round(p0 + length * t * d + bend * length * t * (1 - t) * side, 3).tolist())
    return lanes


def write_map(path, n: int, half: float) -> None:
    graph = {"format": "cmtool.lanegraph", "version": 1, "lanes": random_lanes(n, half),
             "successors": [[i, i + 1] for i in range(0, n - 1, 3)], "green_lights": [], "red_lights": []}
    path.write_text(json.dumps(graph) + "\n")


def cmtool(*args, timeout: float = 600) -> str:
    run = subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], capture_output=True, text=True,
                         timeout=timeout)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


@pytest.fixture(scope="module", params=[("spread", 32 * np.sqrt(HUGE / 20)), ("dense", 500.0)], ids=lambda p: p[0])
def huge_map(request, tmp_path_factory):
    name, half = request.param
    path = tmp_path_factory.mktemp("huge") / f"{name}.jsonl"
    write_map(path, HUGE, half)
    return path


@huge_commands
def test_validate_and_repair_a_huge_map(huge_map, tmp_path):
    report = tmp_path / "report.json"
    cmtool("validate", huge_map, "--json", report)
    first = json.loads(report.read_text())["reports"][0]
    assert first["lanes"] == HUGE and first["counts"]["bad_successor"] > 0 and 0.0 <= first["score"] <= 1.0
    assert 0.0 < first["routable_pairs"] < 1e-3  # chains of two lanes
    fixed = tmp_path / "fixed.jsonl"
    out = cmtool("validate", huge_map, "--repair", "--out", fixed)
    assert "repaired" in out and fixed.stat().st_size > 0


@huge_commands
def test_metrics_of_a_huge_map(huge_map, tmp_path):
    result = tmp_path / "metrics.json"
    cmtool("metrics", "--generated", huge_map, "--reference", huge_map, "--no-features", "--json", result)
    geometry = json.loads(result.read_text())["geometry"]
    assert geometry["lane_f1"]["mean"] == pytest.approx(1.0) and geometry["chamfer_m"]["mean"] == pytest.approx(0.0)


@huge_commands
@pytest.mark.parametrize("fmt,suffix", [("lanelet2", "osm"), ("opendrive", "xodr"), ("geojson", "geojson")])
def test_export_a_huge_map(huge_map, tmp_path, fmt, suffix):
    out = tmp_path / f"big.{suffix}"
    cmtool("export", "--format", fmt, huge_map, "--origin", "60,25", "--out", out)
    assert out.stat().st_size > HUGE * 100
    if fmt == "geojson":
        assert sum(f["properties"]["kind"] == "lane" for f in json.loads(out.read_text())["features"]) == HUGE


def _old_crossings(lanes, succ):
    """Crossings as the check listed them before: every crossing pair from an STR-tree query, one by one."""
    from cmtool.metrics.validity import JUNCTION_REACH_M

    out_deg, in_deg = np.bincount([i for i, _ in succ], minlength=len(lanes)), np.bincount([j for _, j in succ],
                                                                                            minlength=len(lanes))
    junction = [(i, j) for i, j in succ if out_deg[i] > 1 or in_deg[j] > 1]
    points = np.array([lanes[i][-1] for i, _ in junction]).reshape(-1, 2)
    exempt, linked = {k for e in junction for k in e}, {frozenset(e) for e in succ}
    shapes = [shapely.LineString(l) for l in lanes]
    found = []
    for i, j in zip(*shapely.STRtree(shapes).query(shapes, predicate="crosses")):
        if i >= j or frozenset((i, j)) in linked or i in exempt or j in exempt:
            continue
        p = shapes[i].intersection(shapes[j]).representative_point()
        if len(points) and np.min(np.linalg.norm(points - [p.x, p.y], axis=1)) <= JUNCTION_REACH_M:
            continue
        found.append([int(i), int(j)])
    return found


def _old_min_radius(lane):
    """The kink check's smallest turn radius, one lane at a time in Python, as before the batched check."""
    def spaced(line, spacing, kept):
        keep = [0]
        for i in range(1, len(line)):
            if kept[i] or np.linalg.norm(line[i] - line[keep[-1]]) >= spacing:
                keep.append(i)
        if keep[-1] != len(line) - 1:
            if len(keep) > 1 and not kept[keep[-1]]:
                keep[-1] = len(line) - 1
            else:
                keep.append(len(line) - 1)
        return line[keep]

    def turns(line):
        d = np.diff(line, axis=0)
        seg = np.linalg.norm(d, axis=1)
        cos = np.einsum("ij,ij->i", d[:-1], d[1:]) / np.maximum(seg[:-1] * seg[1:], 1e-12)
        return np.arccos(np.clip(cos, -1.0, 1.0)), seg

    corner = np.radians(45.0)
    line = spaced(lane, 0.01, np.zeros(len(lane), bool))
    sharp = np.r_[False, turns(line)[0] > corner, False] if len(line) >= 3 else np.zeros(len(line), bool)
    p = spaced(line, 2.0, sharp)
    if len(p) < 3:
        return float("inf")
    turn, seg = turns(p)
    legs = np.where(turn > corner, np.minimum(seg[:-1], seg[1:]), (seg[:-1] + seg[1:]) / 2.0)
    with np.errstate(divide="ignore"):
        return float(np.where(turn > 1e-9, legs / turn, np.inf).min())


def _random_scene(rng):
    n, half = int(rng.integers(2, 80)), rng.uniform(10, 60)
    lanes = []
    for _ in range(n):
        m = int(rng.integers(2, 25))
        p0, a, length, bend = rng.uniform(-half, half, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 30), \
            rng.normal(0, 0.6)
        t = np.sort(rng.uniform(0, 1, m))
        t[0], t[-1] = 0.0, 1.0
        d, side = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        lane = p0 + length * t[:, None] * d + bend * length * (t * (1 - t))[:, None] * side
        if rng.random() < 0.2:
            lane = lane + rng.normal(0, 0.5, lane.shape)  # kinks and loops
        lanes.append(np.round(lane, 3))
    succ = [(int(i), int(j)) for i, j in rng.integers(0, n, (int(rng.integers(0, n + 1)), 2))]
    return lanes, succ


def test_batched_kinks_and_crossings_equal_the_one_by_one_check():
    """The check's batched kink radii and chunked crossing search against the per-lane and all-pairs code they
    replaced, on 300 random scenes with bent, noisy and looping lanes, forks and merges."""
    from cmtool.core.radius import min_radii
    from cmtool.metrics.validity import check

    rng = np.random.default_rng(1)
    for _ in range(300):
        lanes, succ = _random_scene(rng)
        radius, _ = min_radii(lanes)
        assert radius.tolist() == [_old_min_radius(lane) for lane in lanes]
        report = check(LaneGraph(lanes=[l.tolist() for l in lanes], successors=succ, frame_m=64.0))
        assert [p.lanes for p in report.problems if p.kind == "crossing"] == _old_crossings(lanes, succ)
        assert not report.unlisted and not report.estimated


def test_crossings_and_routability_of_a_pathological_map_are_capped(monkeypatch):
    """Above the caps, crossings are counted on a share of the lanes and listed up to a number, and routability of
    a huge weakly connected set comes from sampled sources; each says so."""
    from cmtool.metrics import validity

    monkeypatch.setattr(validity, "MAX_CROSSING_TESTS", 2_000)
    monkeypatch.setattr(validity, "MAX_LISTED", 100)
    monkeypatch.setattr(validity, "EXACT_COMPONENT", 50)
    monkeypatch.setattr(validity, "CHUNK_LANES", 64)
    n = 600
    lanes = random_lanes(n, 20.0)
    chain = [(i, i + 1) for i in range(n - 1)]
    report = validity.check(LaneGraph(lanes=lanes, successors=chain, frame_m=40.0))
    counts = report.counts()
    assert len([p for p in report.problems if p.kind == "crossing"]) == 100
    assert counts["crossing"] > 100 and report.unlisted["crossing"] == counts["crossing"] - 100
    assert set(report.estimated) >= {"crossing", "routable_pairs"}
    assert report.routable_pairs == pytest.approx(0.5, abs=0.05)  # a chain: half of all ordered pairs
    assert "estimated" in report.to_json() and "unlisted" in report.to_json()


def test_neighbour_search_equals_the_lane_against_lane_search(monkeypatch):
    """infer_neighbours' point-to-lane candidate search and distance cut find what it found before, searching every
    pair of lanes within reach and testing each, on 200 random scenes with neighbours either way."""
    from cmtool.maps import neighbours

    def every_pair_within_reach(tree, middles, lanes, reach):  # lane to lane, not middle to lane
        q, b = shapely.STRtree(tree.geometries).query(tree.geometries[lanes], predicate="dwithin", distance=reach)
        return lanes[q], b

    rng = np.random.default_rng(2)
    for _ in range(200):
        lanes = []
        for _ in range(int(rng.integers(2, 40))):
            p0, a, length, bend = rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi), rng.uniform(3, 40), \
                rng.normal(0, 0.3)
            t = np.linspace(0, 1, int(rng.integers(2, 20)))[:, None]
            d, side = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
            lane = p0 + length * t * d + bend * length * t * (1 - t) * side
            lanes.append(lane)
            if rng.random() < 0.5:  # a neighbour beside it, either way
                lanes.append((lane + rng.uniform(2, 6) * rng.choice([-1, 1]) * side)[::rng.choice([-1, 1])])
        widths = None if rng.random() < 0.5 else rng.uniform(2.5, 5, len(lanes))
        with monkeypatch.context() as m:
            m.setattr(neighbours, "NEAR_BATCH", int(rng.integers(1, 9)))  # batches of a few lanes
            fast = [neighbours.infer_neighbours(lanes, widths, side=side) for side in (1, -1)]
        with monkeypatch.context() as m:
            m.setattr(neighbours, "_near", every_pair_within_reach)
            m.setattr(neighbours, "_may_be_beside", lambda geoms, spots, a, *rest: np.ones(len(a), bool))
            assert fast == [neighbours.infer_neighbours(lanes, widths, side=side) for side in (1, -1)]


def test_kd_tree_lane_distances_equal_geos_nearest_segments(monkeypatch):
    """Many sample points go through a KD-tree of segment pieces (huge maps): the same numbers, bit for bit, as
    GEOS's STR-tree nearest-segment search, in sparse, crowded (ball search) and degenerate scenes."""
    from cmtool.metrics import lanes as module

    rng = np.random.default_rng(5)
    for trial in range(12):
        lanes, _ = _random_scene(rng)
        if trial % 3 == 0:  # crowded: many lanes through one spot, a zero-length segment, a long one
            lanes += [np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]), np.array([[-500.0, 3.0], [500.0, 3.2]])]
            lanes += [np.round(rng.normal(0, 0.3, (2, 2)), 3) for _ in range(600)]
        points = np.concatenate([module.sample_points(lanes, 0.5), rng.uniform(-80, 80, (3000, 2))])
        monkeypatch.setattr(module, "KD_MIN_POINTS", 1 << 60)
        geos = module.distance_to_polylines(points, lanes)
        monkeypatch.setattr(module, "KD_MIN_POINTS", 0)
        monkeypatch.setattr(module, "CROWDED_POINTS", 0 if trial % 2 else 1_000)  # odd: the finer pieces' search
        np.testing.assert_array_equal(module.distance_to_polylines(points, lanes), geos)


def _old_scene_statistics(graph):
    """The topology statistics as before: one path search per weakly connected component."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components, shortest_path

    n, e = graph.n, graph.edges
    degree = np.bincount(e[:, 0], minlength=n) + np.bincount(e[:, 1], minlength=n)
    adjacency = csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    reach, convenience = np.zeros(n), []
    _, label = connected_components(adjacency, directed=True, connection="weak")
    order = np.argsort(label, kind="stable")
    for nodes in np.split(order, np.flatnonzero(np.diff(label[order])) + 1):
        if len(nodes) < 2:
            continue
        sub = adjacency[nodes][:, nodes]
        hops = shortest_path(sub, directed=True, unweighted=True)
        hops[np.arange(len(nodes)), np.arange(len(nodes))] = np.inf
        reach[nodes] = np.isfinite(hops).sum(axis=1)
        convenience.append(hops[np.isfinite(hops)])
    return {"connectivity": degree.astype(float), "density": np.array([float(n)]), "reach": reach,
            "convenience": np.concatenate(convenience) if convenience else np.zeros(0)}


def test_batched_topology_search_equals_one_search_per_component(monkeypatch):
    from cmtool.metrics import topology

    monkeypatch.setattr(topology, "CHUNK", 64)  # batches of small components and one component over a chunk
    rng = np.random.default_rng(2)
    for trial in range(20):
        n = int(rng.integers(1, 400))
        succ = rng.integers(0, n, (int(rng.integers(0, 2 * n)), 2)).tolist()
        if trial % 2:
            succ = [[i, i + 1] for i in range(0, n - 1, int(rng.integers(1, 4)))] + succ[:3]
        graph = topology.keypoint_graph(n, succ)
        new, old = topology.scene_statistics(graph), _old_scene_statistics(graph)
        for k in topology.STATISTICS:
            np.testing.assert_array_equal(new[k], old[k])


def test_batched_lanelet_bound_test_equals_the_one_by_one_test():
    from cmtool.formats.lanelet2_export import _read_reversed, _reads_reversed

    rng, bounds = np.random.default_rng(4), []
    for _ in range(3000):
        left = np.cumsum(rng.normal(0, 1, (int(rng.integers(2, 9)), 2)), axis=0)
        right = np.cumsum(rng.normal(0, 1, (int(rng.integers(2, 9)), 2)), axis=0)
        if rng.random() < 0.4:
            right = left + rng.normal(0, 0.5, 2) if rng.random() < 0.8 else left.copy()
        bounds.append([left, right])
    np.testing.assert_array_equal(_reads_reversed(bounds), [_read_reversed(l, r) for l, r in bounds])


def test_neighbour_searches_are_remembered_by_content(monkeypatch):
    from cmtool.maps import neighbours

    monkeypatch.setattr(neighbours, "CACHE_MIN_LANES", 0)
    monkeypatch.setattr(neighbours, "_FOUND", {})
    lanes = [np.array([[0.0, 0.0], [20.0, 0.0]]), np.array([[0.0, 3.5], [20.0, 3.5]]),
             np.array([[20.0, 7.0], [0.0, 7.0]])]
    first = neighbours.infer_neighbours(lanes)
    assert first == neighbours._nearest(*neighbours._beside_all(lanes, None, None), 1) and (0, 1) in first
    assert neighbours.infer_neighbours(lanes) == first and len(neighbours._FOUND) == 1
    moved = [lane + [0.0, 10.0 * k] for k, lane in enumerate(lanes)]  # same shapes, other places: searched again
    unremembered = neighbours._nearest(*neighbours._beside_all(moved, None, None), 1)
    assert neighbours.infer_neighbours(moved) == unremembered == []


def test_batched_sample_points_equal_resampling_lane_by_lane():
    from cmtool.core.geometry import resample_step
    from cmtool.metrics.lanes import sample_points

    rng = np.random.default_rng(6)
    lanes = [np.cumsum(rng.normal(0, rng.choice([0.01, 1.0, 10.0]), (int(rng.integers(2, 30)), 2)), axis=0)
             for _ in range(3000)]
    odd = [np.zeros((3, 2)), np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]), np.array([[0.0, 0.0], [1e-3, 0.0]])]
    lanes += odd * 200
    for step in (0.5, 0.37):
        expected = np.concatenate([resample_step(lane, step) for lane in lanes])
        np.testing.assert_array_equal(sample_points(lanes, step), expected)


def _old_abreast(a, b, same: bool) -> bool:
    """The abreast test one pair at a time, as the exports asked it before the batched test."""
    la, lb = shapely.LineString(a), shapely.LineString(b[:: 1 if same else -1])
    tolerance = min(5.0, la.length / 3.0, lb.length / 3.0)
    for line, other in ((la, lb), (lb, la)):
        ends = np.array([line.project(shapely.Point(other.coords[0])), line.project(shapely.Point(other.coords[-1]))])
        if np.any(np.abs(ends - [0.0, line.length]) > tolerance):
            return False
    return True


def test_batched_abreast_test_equals_the_pair_by_pair_test():
    from cmtool.maps.neighbours import abreasts

    rng = np.random.default_rng(8)
    lanes, pairs = [], []
    for _ in range(60):
        scene, _ = _random_scene(rng)
        base = len(lanes)
        lanes += scene
        for i in range(len(scene)):  # each lane beside a copy of itself, shifted along and across, either way
            side = np.array([[0.0, rng.uniform(2.0, 5.0)]]) + rng.normal(0.0, [[3.0, 0.3]])
            lanes.append(np.round((scene[i] + side)[::rng.choice([-1, 1])], 3))
            pairs += [(base + i, len(lanes) - 1), (base + i, base + int(rng.integers(0, len(scene))))]
    same = rng.random(len(pairs)) < 0.5
    assert abreasts(lanes, pairs, same).tolist() == [_old_abreast(lanes[i], lanes[j], s)
                                                     for (i, j), s in zip(pairs, same.tolist())]
