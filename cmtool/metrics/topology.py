"""SLEDGE's urban-planning statistics of lane graphs and their Fréchet distances (docs/evaluation.md).

Per scene, the *keypoint graph*: every lane is a directed edge from its start keypoint to its end
keypoint, and for every successor edge (a, b) the end of a and the start of b are one keypoint
(merged transitively, union-find). Pooled over the scenes of a set:

- connectivity: each keypoint's in + out degree over distinct neighbouring keypoints (parallel lanes
  between the same two keypoints in the same direction count once; a lane from a keypoint back to
  itself counts 2);
- density: the number of keypoints of each scene;
- reach: for each keypoint, the number of other keypoints reachable from it;
- convenience: for each (source, reachable target) pair, the hop count of the shortest path.

The Fréchet distance of two 1-D samples is ``sqrt((m_a - m_b)^2 + v_a + v_b - 2 sqrt(v_a v_b))``
with sample variances (ddof 1); connectivity and convenience are reported x10, as SLEDGE does.
Shortest paths come from scipy's breadth-first ``csgraph.shortest_path``, one call per scene. A weakly connected set
of over ``EXACT_COMPONENT`` keypoints (a huge map; every path of it would take time and memory that grow with the
square of its size) contributes the reach and hop counts of ``SAMPLED_SOURCES`` of its keypoints, drawn with seed
``SEED``: a sample of their distribution, each sampled reach standing for as many keypoints as the sources for the
set, its hop counts counted once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, shortest_path

from cmtool.core.unionfind import UnionFind

STATISTICS = ("connectivity", "density", "reach", "convenience")
SCALE = {"connectivity": 10.0, "density": 1.0, "reach": 1.0, "convenience": 10.0}
CHUNK = 2048  # path searches per batch (a batch holds CHUNK x component-size hop counts)
EXACT_COMPONENT = 20_000  # keypoints: a larger weakly connected set is measured from sampled sources
SAMPLED_SOURCES, SEED = 1_000, 0


@dataclass
class KeypointGraph:
    """Keypoints ``0..n-1`` and the directed lane edges between them (duplicates removed)."""

    n: int
    edges: np.ndarray  # (E, 2) int, unique (source, target) keypoint pairs


def keypoint_graph(num_lanes: int, successors) -> KeypointGraph:
    """The keypoint graph of ``num_lanes`` lanes with successor pairs ``(a, b)``."""
    keypoints = UnionFind(range(2 * num_lanes))  # keypoint 2i: start of lane i, 2i + 1: its end
    for a, b in successors:
        keypoints.union(2 * a + 1, 2 * b)
    roots = np.array([keypoints.find(k) for k in range(2 * num_lanes)], dtype=np.int64)
    _, ids = np.unique(roots, return_inverse=True)
    edges = np.unique(ids.reshape(-1, 2), axis=0) if num_lanes else np.zeros((0, 2), np.int64)
    return KeypointGraph(int(ids.max(initial=-1)) + 1, edges)


def scene_statistics(graph: KeypointGraph) -> dict[str, np.ndarray]:
    """The four statistics' samples contributed by one scene."""
    n, e = graph.n, graph.edges
    if n == 0:
        return {"connectivity": np.zeros(0), "density": np.array([0.0]), "reach": np.zeros(0),
                "convenience": np.zeros(0)}
    degree = np.bincount(e[:, 0], minlength=n) + np.bincount(e[:, 1], minlength=n)
    adjacency = csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    reach, convenience = np.zeros(n), []
    # paths stay within a weakly connected component: search each on its own, CHUNK sources at a time, so memory
    # grows with the component and the chunk, not with the square of the scene's keypoints
    _, label = connected_components(adjacency, directed=True, connection="weak")
    order = np.argsort(label, kind="stable")
    pending: list[np.ndarray] = []  # small components, searched together (paths never leave a component)
    size = 0
    for nodes in np.split(order, np.flatnonzero(np.diff(label[order])) + 1):
        if len(nodes) > EXACT_COMPONENT:
            sources = np.random.default_rng(SEED).choice(len(nodes), SAMPLED_SOURCES, replace=False)
            _search(adjacency, nodes, reach, convenience, np.sort(sources))
            continue
        if len(nodes) < 2:
            continue
        pending.append(nodes)
        size += len(nodes)
        if size >= CHUNK:
            _search(adjacency, np.concatenate(pending), reach, convenience)
            pending, size = [], 0
    if pending:
        _search(adjacency, np.concatenate(pending), reach, convenience)
    return {"connectivity": degree.astype(float), "density": np.array([float(n)]), "reach": reach,
            "convenience": np.concatenate(convenience) if convenience else np.zeros(0)}


def _search(adjacency, nodes: np.ndarray, reach: np.ndarray, convenience: list, sources=None) -> None:
    """Hop counts from ``nodes`` (whole weakly connected components, in label order) among themselves, in batches of
    ``CHUNK`` sources (fewer in a set of over ``EXACT_COMPONENT`` keypoints): each node's reach into ``reach``, the
    hop counts of reachable pairs (row by row, the columns in order) appended to ``convenience``. Many small
    components go through one search, so a scene of 100,000 lanes is a few dozen calls, not one per component. With
    ``sources`` (positions in ``nodes``), only from those: their reaches stand for all the nodes', each for as many."""
    sub = adjacency[nodes][:, nodes]
    sources = np.arange(len(nodes)) if sources is None else sources
    found, step = np.zeros(len(sources)), max(1, min(CHUNK, CHUNK * EXACT_COMPONENT // len(nodes)))
    for start in range(0, len(sources), step):
        rows = sources[start:start + step]
        hops = shortest_path(sub, directed=True, unweighted=True, indices=rows)
        hops[np.arange(len(rows)), rows] = np.inf
        reachable = np.isfinite(hops)
        found[start:start + len(rows)] = reachable.sum(axis=1)
        convenience.append(hops[reachable])
    reach[nodes] = found[np.arange(len(nodes)) % len(sources)]


def pooled_statistics(graphs) -> dict[str, np.ndarray]:
    """The statistics of a set of lane graphs (anything with ``lanes`` and ``successors``), pooled."""
    parts = {k: [] for k in STATISTICS}
    for g in graphs:
        for k, v in scene_statistics(keypoint_graph(len(g.lanes), g.successors)).items():
            parts[k].append(v)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}


def frechet_1d(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance of two 1-D samples modelled as Gaussians (sample variances, ddof 1)."""
    if len(a) < 2 or len(b) < 2:
        return math.nan
    va, vb = float(np.var(a, ddof=1)), float(np.var(b, ddof=1))
    return math.sqrt(max((float(np.mean(a)) - float(np.mean(b))) ** 2 + va + vb - 2.0 * math.sqrt(va * vb), 0.0))


def frechet_distances(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    """Fréchet distance per statistic (connectivity and convenience x10) between two sets' pooled statistics."""
    return {k: SCALE[k] * frechet_1d(a[k], b[k]) for k in STATISTICS}


def topology_fd(generated, reference) -> dict[str, float]:
    """Fréchet distance per statistic (connectivity and convenience x10) between two sets of lane graphs."""
    return frechet_distances(pooled_statistics(generated), pooled_statistics(reference))
