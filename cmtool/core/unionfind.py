"""A small disjoint-set (union-find) over hashable keys, with path halving."""

from __future__ import annotations

from collections import defaultdict


class UnionFind:
    def __init__(self, keys):
        self.parent = {k: k for k in keys}

    def find(self, k):
        while self.parent[k] != k:
            self.parent[k] = self.parent[self.parent[k]]
            k = self.parent[k]
        return k

    def union(self, a, b) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[rb] = ra

    def groups(self) -> list[list]:
        """The sets, each a list of keys in insertion order."""
        out = defaultdict(list)
        for k in self.parent:
            out[self.find(k)].append(k)
        return list(out.values())
