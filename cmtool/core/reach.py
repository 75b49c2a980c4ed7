"""Where chains of directed edges lead: the nodes reachable from a node of a graph (scipy's breadth-first order),
each source searched once."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order


class Reach:
    """``reach(node)``: the set of nodes (``node`` itself included) that ``edges`` lead to from ``node``, in a graph of
    ``n`` nodes."""

    def __init__(self, n: int, edges):
        e = np.array(list(edges), np.int64).reshape(-1, 2)
        self.graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        self.found: dict[int, set[int]] = {}

    def __call__(self, node: int) -> set[int]:
        if node not in self.found:
            self.found[node] = set(breadth_first_order(self.graph, node, return_predecessors=False).tolist())
        return self.found[node]


def reachable_from(n: int, edges, sources) -> set[int]:
    """The nodes that ``edges`` lead to from any of ``sources`` (themselves included), in a graph of ``n`` nodes: one
    search from a node added before them all."""
    return Reach(n + 1, list(edges) + [(n, k) for k in sources])(n) - {n}
