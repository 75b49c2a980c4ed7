"""Validity checks on hand-made lane graphs: each problem found with the right lane ids."""

import numpy as np
import pytest

from cmtool.data.synth import generate_city
from cmtool.maps.lanegraph import LaneGraph
from cmtool.metrics.validity import check


def straight(x0, y0, x1, y1, n=20):
    return np.stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n)], axis=-1)


def arc(cx, cy, r, a0, a1, n=30):
    a = np.linspace(a0, a1, n)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=-1)


def kinds(report):
    return sorted((p.kind, tuple(p.lanes)) for p in report.problems)


def test_a_clean_road_scores_one():
    lanes = [straight(-32, -1.75, 0, -1.75), straight(0, -1.75, 32, -1.75), straight(32, 1.75, -32, 1.75)]
    r = check(LaneGraph(lanes=lanes, successors=[(0, 1)]))
    assert r.problems == [] and r.score == 1.0
    assert r.routable_pairs == 1 / 6 and r.largest_scc == 1
    assert check(LaneGraph(lanes=[])).score == 1.0


def test_each_problem_is_found_with_its_lanes():
    lanes = [
        straight(-32, 0, -5, 0),             # 0 -> 1 with a 4 m gap
        straight(-1, 0, 32, 0),              # 1
        straight(-10, 10, 10, 10),           # 2: floats in the middle: dangling
        straight(0, -32, 0, -20),            # 3 -> 4 turns back by 180 degrees
        straight(0, -20, 0, -31),            # 4
        straight(-20, -10, -18.5, -10),      # 5: 1.5 m long, dangling too
        np.array([[10, -15], [20, -15], [20, -10], [15, -20]], float),  # 6: crosses itself (and kinks)
        straight(-32, 25, 32, 25),           # 7 and 8 cross far from any junction
        straight(25, -32, 25, 32),           # 8
        np.concatenate([straight(-32, -28, -20, -28), straight(-20, -27.5, -20, -20)[1:]]),  # 9: a 90 degree corner
    ]
    succ = [(0, 1), (3, 4)]
    r = check(LaneGraph(lanes=lanes, successors=succ))
    found = kinds(r)
    assert ("bad_successor", (0, 1)) in found and ("bad_successor", (3, 4)) in found
    assert ("dangling", (2,)) in found and ("dangling", (5,)) in found and ("short", (5,)) in found
    assert ("self_intersection", (6,)) in found and ("kink", (6,)) in found
    assert ("crossing", (7, 8)) in found and ("kink", (9,)) in found
    assert ("kink", (7,)) not in found and ("dangling", (7,)) not in found  # border lanes are fine
    bad = {i for _, ids in found for i in ids}
    assert r.score == 1.0 - len(bad) / len(lanes)
    assert r.to_json()["counts"]["bad_successor"] == 2


def test_crossings_at_forks_and_merges_are_intersections():
    approach = straight(-32, -1.75, -8, -1.75)
    left_turn = arc(-8, 8.25, 10, -np.pi / 2, 0)  # from (-8, -1.75) turning left to (2, 8.25)
    straight_on = straight(-8, -1.75, 32, -1.75)
    oncoming_left = arc(8, -8.25, 10, np.pi / 2, np.pi)  # from (8, 1.75) turning to (-2, -8.25)
    oncoming = straight(32, 1.75, 8, 1.75)
    lanes = [approach, left_turn, straight_on, oncoming, oncoming_left]
    r = check(LaneGraph(lanes=lanes, successors=[(0, 1), (0, 2), (3, 4)]))
    assert [p for p in r.problems if p.kind == "crossing"] == []


def test_wide_curves_are_not_kinks():
    r = check(LaneGraph(lanes=[arc(0, 0, 6.0, 0, np.pi / 2)]))
    assert not any(p.kind == "kink" for p in r.problems)
    r = check(LaneGraph(lanes=[arc(0, 0, 3.0, 0, np.pi / 2)]))
    (kink,) = [p for p in r.problems if p.kind == "kink"]
    assert abs(float(kink.detail.split()[1]) - 3.0) < 0.1
    # the same turn sampled sparsely (a vertex every 2.4 m, as a 20-point lane of 45 m has) or densely
    for n in (5, 200):
        assert not any(p.kind == "kink" for p in check(LaneGraph(lanes=[arc(0, 0, 6.0, 0, np.pi / 2, n)])).problems)
        assert any(p.kind == "kink" for p in check(LaneGraph(lanes=[arc(0, 0, 3.5, 0, np.pi / 2, n)])).problems)


def test_sub_millimetre_steps_are_no_kinks_and_rounding_changes_no_score():
    straight = np.array([[-20.0, 0.0], [0.0, 0.0], [0.0002, 0.0004], [20.0, 0.0]])  # a 0.45 mm step turning 63 degrees
    corner = np.array([[-20.0, 0.0], [-1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, 20.0]])  # a right angle: a kink
    for lanes, kinks in (([straight], 0), ([corner], 1)):
        graph = LaneGraph(lanes=lanes)
        rounded = LaneGraph(lanes=[np.round(lane, 3) for lane in lanes])
        assert check(graph).counts().get("kink", 0) == kinks
        assert check(graph).score == check(rounded).score


def test_validate_command(tmp_path, capsys):
    import json

    from cmtool.maps.lanegraph import write_jsonl
    from tests.conftest import in_process

    good = LaneGraph(lanes=[straight(-32, 0, 32, 0)])
    bad = LaneGraph(lanes=[straight(-10, 0, 10, 0), straight(-32, 20, 32, 20)])
    write_jsonl(tmp_path / "maps.jsonl", [good, bad])
    code, out, err = in_process(capsys, "validate", tmp_path / "maps.jsonl", "--json", tmp_path / "v.json")
    assert code == 0, err
    report = json.loads((tmp_path / "v.json").read_text())
    assert [r["score"] for r in report["reports"]] == [1.0, 0.5] and report["problems"] == {"dangling": 1}
    assert report["reports"][1]["problems"][0]["lanes"] == [0]
    assert "mean validity score 0.750" in out
    code, _, err = in_process(capsys, "validate", tmp_path / "none.jsonl")
    assert code == 1 and "no such file" in err


def test_repair_snaps_drops_and_merges_and_reports_each_change(tmp_path, capsys):
    import json

    from cmtool.maps.lanegraph import read_jsonl, write_jsonl
    from cmtool.metrics.repair import repair
    from tests.conftest import in_process

    lanes = [
        straight(-32, 0, -1, 0),      # 0 ends 1 m short of 1: a near miss, no successor edge yet
        straight(0, 0, 32, 0),        # 1
        straight(10, 10, 11, 10),     # 2: a 1 m fragment
        straight(-32, 5, 32, 5),      # 3
        straight(-32, 5.2, 32, 5.2),  # 4: a duplicate of 3
    ]
    graph = LaneGraph(lanes=lanes, successors=[(4, 3)])
    fixed, changes = repair(graph)
    assert len(fixed.lanes) == 3 and fixed.successors == [(0, 1)]
    assert "dropped lane 2 (1.00 m long)" in changes and "merged lane 4 into lane 3 (duplicate)" in changes
    assert "linked lane 0 to lane 1 as its successor" in changes
    assert any(c.startswith("snapped lane 0 end, lane 1 start to (-0.50, 0.00)") for c in changes)
    np.testing.assert_allclose(fixed.lanes[0][-1], fixed.lanes[1][0])
    assert check(fixed).score == 1.0 and check(graph).score < 1.0
    write_jsonl(tmp_path / "m.jsonl", [graph])
    code, out, err = in_process(capsys, "validate", tmp_path / "m.jsonl", "--repair", "--out", tmp_path / "r.jsonl",
                                "--json", tmp_path / "v.json")
    assert code == 0, err
    assert "scene 0: dropped lane 2" in out and "(4 changes)" in out
    assert json.loads((tmp_path / "v.json").read_text())["mean_score"] == 1.0
    assert len(read_jsonl(tmp_path / "r.jsonl")[0].lanes) == 3
    code, _, err = in_process(capsys, "validate", tmp_path / "m.jsonl", "--repair")
    assert code == 1 and "--repair needs --out" in err


@pytest.mark.parametrize("city", ["LAV", "PIT", "SGP", "BOS"])
def test_procedural_cities_are_valid(city):
    """Whole procedural maps (no crop border hiding the junctions) have no problems at all."""
    hd = generate_city(city, seed=1, extent=500.0)
    ids = list(hd.lanes)
    index = {lane_id: i for i, lane_id in enumerate(ids)}
    graph = LaneGraph(lanes=[hd.lanes[k].centerline - 250.0 for k in ids],
                      successors=[(index[k], index[s]) for k in ids for s in hd.lanes[k].successors],
                      frame_m=500.0)
    report = check(graph)
    assert report.lanes > 100 and report.problems == [] and report.score == 1.0


def test_routability_equals_an_all_pairs_path_search():
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    from cmtool.metrics.validity import _routability

    def reference(n, succ):  # every pair by breadth-first search, as the check did before
        adj = csr_matrix((np.ones(len(succ)), ([i for i, _ in succ], [j for _, j in succ])), shape=(n, n))
        reach = np.isfinite(shortest_path(adj, directed=True, unweighted=True))
        np.fill_diagonal(reach, False)
        return reach.sum() / (n * (n - 1))

    rng = np.random.default_rng(0)
    for _ in range(300):
        n = int(rng.integers(2, 60))
        succ = [(int(i), int(j)) for i, j in rng.integers(0, n, (int(rng.integers(0, 2 * n)), 2))]  # cycles, loops
        pairs, largest, sampled = _routability(n, succ)
        assert pairs == pytest.approx(reference(n, succ), abs=1e-12) and 1 <= largest <= n and not sampled
    chain = [(i, i + 1) for i in range(9999)]  # 10,000 lanes in a row: half of all ordered pairs
    assert _routability(10000, chain) == (pytest.approx(0.5), 1, False)
    assert _routability(10000, chain + [(9999, 0)]) == (1.0, 10000, False)


def test_duplicate_search_finds_what_comparing_every_pair_finds():
    """The KD-tree search of repair's duplicate lanes against the slow path (every pair compared), on 300 lanes of
    which many are shifted, stretched or reversed copies of others."""
    from cmtool.core.geometry import polyline_length, resample
    from cmtool.metrics.repair import DUPLICATE_M, duplicate_pairs

    rng = np.random.default_rng(3)
    lines = []
    for _ in range(100):
        start, angle, length = rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi), rng.uniform(3, 40)
        t = np.linspace(0, 1, 20)[:, None]
        base = start + length * t * np.array([np.cos(angle), np.sin(angle)]) + rng.normal(0, 1) * t * (1 - t)
        lines.append(base)
        for _ in range(2):  # copies: shifted about 0.35 m, stretched by up to 10%, sometimes reversed
            copy = base + rng.normal(0, 0.25, 2)
            copy = copy[0] + (copy - copy[0]) * rng.uniform(0.9, 1.1)
            lines.append(copy[::-1] if rng.random() < 0.2 else copy)

    def slow(a, b):
        la, lb = polyline_length(a), polyline_length(b)
        if min(la, lb) <= 0 or abs(la - lb) > 0.2 * max(la, lb):
            return False
        return float(np.linalg.norm(resample(a, 20) - resample(b, 20), axis=1).mean()) < DUPLICATE_M

    ids = list(range(7, 7 + len(lines)))
    expected = [(ids[p], ids[q]) for p in range(len(lines)) for q in range(p + 1, len(lines))
                if slow(lines[p], lines[q])]
    assert 30 < len(expected) < 250  # the copies make some duplicates, not all
    assert duplicate_pairs(lines, ids) == expected


def test_successor_joints_of_all_edges_equal_those_of_each_edge():
    """The gap and turn of every successor edge at once: the numbers of np.linalg.norm and np.dot of each edge, bit
    for bit, so the reports and their details stay as they were."""
    from cmtool.core.geometry import unit
    from cmtool.metrics.validity import _joints

    rng = np.random.default_rng(1)
    lanes = [np.round(np.cumsum(rng.normal(0, rng.choice([0.01, 1.0, 10.0]), (int(rng.integers(2, 6)), 2)), axis=0), 3)
             for _ in range(400)]
    succ = [(int(i), int(j)) for i, j in rng.integers(0, len(lanes), (3000, 2))]
    gaps, turns = _joints(lanes, succ)
    for (i, j), gap, turn in zip(succ, gaps.tolist(), turns.tolist()):
        a, b = lanes[i], lanes[j]
        assert gap == float(np.linalg.norm(a[-1] - b[0]))
        assert turn == float(np.degrees(np.arccos(np.clip(np.dot(unit(a[-1] - a[-2]), unit(b[1] - b[0])), -1.0, 1.0))))
    assert [len(x) for x in _joints(lanes, [])] == [0, 0]
