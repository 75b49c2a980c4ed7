"""Topology statistics and Fréchet distances on hand-made lane graphs with known answers."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cmtool.metrics.topology import frechet_1d, keypoint_graph, pooled_statistics, scene_statistics, topology_fd


def stats(num_lanes, successors):
    return scene_statistics(keypoint_graph(num_lanes, successors))


def test_a_fork_has_the_counted_degrees_reach_and_hops():
    # lane 0 (west -> centre) continues into lane 1 (-> east) and lane 2 (-> north)
    s = stats(3, [(0, 1), (0, 2)])
    assert s["density"].tolist() == [4.0]
    assert sorted(s["connectivity"].tolist()) == [1, 1, 1, 3]  # the centre: in 1 + out 2
    assert sorted(s["reach"].tolist()) == [0, 0, 2, 3]
    assert sorted(s["convenience"].tolist()) == [1, 1, 1, 2, 2]


def test_four_way_intersection():
    # 4 approaches end at 4 entry keypoints; from each, 3 connectors (left, straight, right) lead to the
    # 3 other arms' exits, each continuing into an outgoing lane
    approaches = list(range(4))
    exits = list(range(4, 8))  # exit lane of arm k starts where connectors into arm k end
    connectors, succ = [], []
    for k in range(4):
        for j in range(4):
            if j != k:
                c = 8 + len(connectors)
                connectors.append(c)
                succ += [(approaches[k], c), (c, exits[j])]
    s = stats(8 + len(connectors), succ)
    # keypoints: 4 approach starts, 4 entries, 4 exit starts, 4 exit ends
    assert s["density"].tolist() == [16.0]
    assert sorted(s["connectivity"].tolist()) == [1] * 8 + [4] * 8  # entries: in 1 + out 3; exits: in 3 + out 1
    assert sorted(s["reach"].tolist()) == [0] * 4 + [1] * 4 + [6] * 4 + [7] * 4  # exit ends, exit starts, entries, approach starts


def test_parallel_lanes_and_self_loops():
    # lanes 1 and 2 both run from the end of lane 0 to the start of lane 3: one edge between two keypoints
    s = stats(4, [(0, 1), (0, 2), (1, 3), (2, 3)])
    assert sorted(s["connectivity"].tolist()) == [1, 1, 2, 2]
    # a lane that loops back onto itself: one keypoint, degree 2, reaches nothing else
    s = stats(1, [(0, 0)])
    assert s["density"].tolist() == [1.0] and s["connectivity"].tolist() == [2.0]
    assert s["reach"].tolist() == [0.0] and len(s["convenience"]) == 0


def test_merges_are_transitive():
    # 0 -> 1 and 2 -> 1 share 1's start; 2 -> 3 puts 3's start there too: one keypoint for all four ends
    g = keypoint_graph(4, [(0, 1), (2, 1), (2, 3)])
    assert g.n == 5 and len(g.edges) == 4


def test_frechet_distance():
    a, b = np.array([1.0, 3.0]), np.array([2.0, 4.0, 6.0])
    expected = math.sqrt((2 - 4) ** 2 + 2 + 4 - 2 * math.sqrt(8))
    assert frechet_1d(a, b) == pytest.approx(expected)
    assert frechet_1d(a, a) == 0.0
    assert math.isnan(frechet_1d(a[:1], b))


def test_identical_sets_score_zero_and_scaling():
    graphs = [SimpleNamespace(lanes=[None] * 3, successors=[(0, 1), (0, 2)]),
              SimpleNamespace(lanes=[None] * 4, successors=[(0, 1), (1, 2), (2, 3)])]
    assert topology_fd(graphs, graphs) == {"connectivity": 0.0, "density": 0.0, "reach": 0.0, "convenience": 0.0}
    other = [SimpleNamespace(lanes=[None] * 2, successors=[]), SimpleNamespace(lanes=[None] * 5, successors=[(0, 1)])]
    a, b = pooled_statistics(graphs), pooled_statistics(other)
    fd = topology_fd(graphs, other)
    assert fd["connectivity"] == pytest.approx(10 * frechet_1d(a["connectivity"], b["connectivity"]))
    assert fd["density"] == pytest.approx(frechet_1d(a["density"], b["density"]))


def test_component_search_equals_the_all_pairs_matrix(monkeypatch):
    """Statistics searched per weakly connected component, in chunks of sources, against the slow path (one dense
    all-pairs hop matrix), on 300 random scenes: forks, merges, cycles, self-loops and isolated lanes."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    from cmtool.metrics import topology

    def dense(graph):
        n, e = graph.n, graph.edges
        hops = shortest_path(csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=True,
                             unweighted=True)
        np.fill_diagonal(hops, np.inf)
        return np.isfinite(hops).sum(axis=1), np.sort(hops[np.isfinite(hops)])

    rng = np.random.default_rng(5)
    for scene in range(300):
        lanes = int(rng.integers(1, 60))
        successors = [tuple(p) for p in rng.integers(0, lanes, (int(rng.integers(0, 2 * lanes)), 2))]
        graph = topology.keypoint_graph(lanes, successors)
        monkeypatch.setattr(topology, "CHUNK", int(rng.integers(1, 8)) if scene % 2 else 2048)  # batches used
        stats = topology.scene_statistics(graph)
        reach, convenience = dense(graph)
        np.testing.assert_array_equal(stats["reach"], reach)
        np.testing.assert_array_equal(np.sort(stats["convenience"]), convenience)


def test_a_huge_connected_set_is_measured_from_sampled_sources(monkeypatch):
    """A chain of 100,000 lanes has 5 billion reachable pairs: a set of over EXACT_COMPONENT keypoints contributes the
    reach and hop counts of SAMPLED_SOURCES keypoints, each reach standing for as many keypoints."""
    from cmtool.metrics import topology

    monkeypatch.setattr(topology, "EXACT_COMPONENT", 500)
    monkeypatch.setattr(topology, "SAMPLED_SOURCES", 100)
    graph = keypoint_graph(2000, [(i, i + 1) for i in range(1999)])  # one chain of 2,001 keypoints
    stats = topology.scene_statistics(graph)
    assert len(stats["reach"]) == graph.n and 0 < len(stats["convenience"]) <= 100 * graph.n
    assert stats["reach"].mean() == pytest.approx((graph.n - 1) / 2, rel=0.15)  # each reaches those after it
    assert stats["convenience"].mean() == pytest.approx(graph.n / 3, rel=0.15)  # the mean hop count of all pairs
