"""Whether an area's lanes let traffic go where its SD map does: of the ordered pairs of the SD map's road ends in an
area (its dead ends and where its roads leave the area) that a drive along the SD roads joins (one-way roads one
way, no U-turns; roads meet where they share a point, as OpenStreetMap ways share nodes), the share that the lanes
route.

A pair (a, b) is routed when a chain of successor joins and lane changes leads from a lane that starts within
``END_M`` of a to a lane that ends within ``END_M`` of b."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import shapely
from scipy.spatial import cKDTree

from cmtool.core.reach import Reach
from cmtool.maps.sdmap import SDMap

END_M = 15.0  # a lane end this close to an SD road end serves it
MAX_PAIRS = 2000  # at most this many connected pairs are checked (evenly spread)


def sd_end_pairs(sd: SDMap, box) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The SD road ends inside ``box`` (x0, y0, x1, y1) as points (K, 2), and the ordered pairs (a, b) of them that
    a drive along the SD roads joins."""
    area = shapely.box(*box)
    index: dict[tuple[float, float], int] = {}
    points, edges, degree = [], [], []

    def node(p) -> int:
        key = (round(float(p[0]), 2), round(float(p[1]), 2))
        if key not in index:
            index[key] = len(points)
            points.append(key)
            degree.append(0)
        return index[key]

    for road in sd.roads:
        clipped = shapely.intersection(shapely.LineString(road.polyline), area)
        for piece in getattr(clipped, "geoms", [clipped]):
            if not isinstance(piece, shapely.LineString) or piece.is_empty:
                continue
            ids = [node(p) for p in shapely.get_coordinates(piece)]
            for k, i in enumerate(ids):
                degree[i] += 1 if k in (0, len(ids) - 1) else 2  # the road's arms at the point
            for a, b in zip(ids[:-1], ids[1:]):
                if a != b:
                    edges += [(a, b)] * (road.oneway >= 0) + [(b, a)] * (road.oneway <= 0)
    ends = [k for k, d in enumerate(degree) if d == 1]  # one arm: a dead end or the edge of the area
    if not ends or not edges:
        return np.zeros((0, 2)), []
    edges = sorted(set(edges))
    leaving = defaultdict(list)  # node -> the edges that leave it
    for n, (a, b) in enumerate(edges):
        leaving[a].append(n)
    turns = [(n, m) for n, (a, b) in enumerate(edges) for m in leaving[b] if edges[m][1] != a]  # no U-turns
    reach = Reach(len(edges), turns)
    position = {k: n for n, k in enumerate(ends)}
    pairs = set()
    for a in ends:
        for first in leaving[a]:
            for n in reach(first):
                b = edges[n][1]
                if b in position and b != a:
                    pairs.add((position[a], position[b]))
    return np.array([points[k] for k in ends]), sorted(pairs)


def routed_share(graph, ends: np.ndarray, pairs: list[tuple[int, int]], max_pairs: int = MAX_PAIRS) -> float:
    """The share of ``pairs`` of SD road ``ends`` that the lane graph routes (module doc); NaN without pairs."""
    if not pairs:
        return float("nan")
    if len(pairs) > max_pairs:
        pairs = [pairs[k] for k in np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int)]
    return 1.0 - len(unrouted(graph, ends, pairs)) / len(pairs)


def unrouted(graph, ends: np.ndarray, pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The ``pairs`` of SD road ``ends`` that the lane graph does not route (module doc)."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    if not lanes:
        return list(pairs)
    starts = cKDTree(np.array([l[0] for l in lanes])).query_ball_point(ends, END_M)
    stops = cKDTree(np.array([l[-1] for l in lanes])).query_ball_point(ends, END_M)
    joins = [(int(i), int(j)) for i, j in graph.successors]
    for i, j in graph.left_neighbors or []:
        joins += [(int(i), int(j)), (int(j), int(i))]
    reach = Reach(len(lanes), joins)
    return [(a, b) for a, b in pairs if not any(reach(lane) & set(stops[b]) for lane in starts[a])]
