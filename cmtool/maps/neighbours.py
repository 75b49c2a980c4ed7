"""Lanes beside each other: lane-change neighbours and oncoming lanes across a centre line.

Two lanes are beside each other when one runs about a lane width from the other along most of both.
In the same direction they are lane-change neighbours, recorded as ``left_neighbors`` pairs
``(i, j)``: lane ``j`` is lane ``i``'s left neighbour. In opposite directions they share the centre
line, recorded as ``oncoming`` pairs ``(i, j)``, ``i < j``: on each other's left in right-hand
traffic, on each other's right in left-hand traffic (:func:`side_of` tells which). Generated lanes get
both from the geometry alone (:func:`find_neighbours`); imported maps keep the lane-change
neighbours their source records and add the oncoming pairs, which no source records.
"""

from __future__ import annotations

import numpy as np
import shapely

from cmtool.maps.lanegraph import LaneGraph

LANE_WIDTH_M = 3.5
SAMPLES = 9  # points along each lane (at 10%, 20%, ..., 90% of its length) that look for the other
MIN_SHARE = 0.6  # of each lane's samples that must find the other beside them
MAX_SKEW_M = 0.75  # of a sample's offset along the lane where the other's nearest point lies
MAX_ANGLE_DEG = 20.0  # between the lanes' directions there (or their reverses)
LATERAL = (0.5, 1.5)  # the lateral gap, in lane widths
ABREAST_M = 5.0  # neighbours whose starts (or ends) lie further apart along the lanes are not abreast


def find_neighbours(lanes, widths=None, recorded=None) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(left neighbours, oncoming pairs) of a map's lanes (see the module docstring). With ``recorded``
    pairs (an imported map's neighbours, in either order), the left neighbours are those of them that
    run beside each other; without, all that the geometry finds."""
    left, right = infer_neighbours(lanes, widths), infer_neighbours(lanes, widths, side=-1)
    oncoming = sorted({(min(i, j), max(i, j)) for i, j in left + right if not same_direction(lanes, i, j)})
    if recorded is not None:
        left = infer_neighbours(lanes, widths, candidates=recorded)
    return [(i, j) for i, j in left if same_direction(lanes, i, j)], oncoming


def relaned(graph, lanes, successors, meta: dict | None = None):
    """A copy of lane graph ``graph`` with other ``lanes`` and ``successors`` (and ``meta``, when given): its
    neighbours and widths found anew from the geometry, its lights, city and frame kept."""
    left, oncoming = find_neighbours(lanes)
    return LaneGraph(lanes=lanes, successors=sorted(set(successors)), left_neighbors=left, oncoming=oncoming,
                     widths=lane_widths(lanes, left).round(2).tolist(), green_lights=graph.green_lights,
                     red_lights=graph.red_lights, city=graph.city, frame_m=graph.frame_m,
                     meta=graph.meta if meta is None else meta)


def graph_neighbours(graph) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """A lane graph's (left neighbours, oncoming pairs): as recorded, else found from its geometry."""
    if graph.left_neighbors is not None and graph.oncoming is not None:
        return list(graph.left_neighbors), list(graph.oncoming)
    return find_neighbours([np.asarray(l, np.float64) for l in graph.lanes], graph.widths)


def infer_neighbours(lanes, widths=None, candidates=None, side: int = 1) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``: lane ``j`` is the nearest lane beside lane ``i`` on its left (``side`` 1) or
    right (``side`` -1), running either way.

    ``widths`` (one per lane, metres; default :data:`LANE_WIDTH_M`) set the lateral gap expected
    between two lane centres; ``candidates`` (pairs in either order) limits the search to those
    pairs, with no lateral limit: how imported maps keep their recorded neighbours.
    """
    n = len(lanes)
    if n < 2:
        return []
    geoms = _lines(lanes)
    points, tangents = _samples(geoms)
    w = np.full(n, LANE_WIDTH_M) if widths is None else np.asarray(widths, np.float64)
    if candidates is None:
        a, b = shapely.STRtree(geoms).query(geoms, predicate="dwithin", distance=float(LATERAL[1] * w.max()))
        lateral = LATERAL
    else:
        pairs = np.array([(i, j) for i, j in candidates if i != j], np.int64).reshape(-1, 2)
        a, b = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
        lateral = (0.0, np.inf)
    width = 0.5 * (w[a] + w[b])
    middle = SAMPLES // 2  # each lane's middle must lie beside the other: a cheap first cut
    gaps = [shapely.distance(shapely.points(points[i, middle]), geoms[j]) / width for i, j in ((a, b), (b, a))]
    keep = (a != b) & np.all([(g >= lateral[0]) & (g <= lateral[1]) for g in gaps], axis=0)
    a, b, width = a[keep], b[keep], width[keep]
    if len(a) == 0:
        return []
    offset, beside = _beside(geoms, points, tangents, a, b, width, lateral)
    _, beside_back = _beside(geoms, points, tangents, b, a, width, lateral)
    ok = (beside.mean(1) >= MIN_SHARE) & (beside_back.mean(1) >= MIN_SHARE)
    there = np.array([side * np.median(o[m]) > 0 if m.any() else False for o, m in zip(offset, beside)])
    gap = np.array([np.median(np.abs(o[m])) if m.any() else np.inf for o, m in zip(offset, beside)])
    best: dict[int, tuple[float, int]] = {}  # i -> (gap, j): only the nearest lane on that side
    for i, j, g in zip(a[ok & there], b[ok & there], gap[ok & there]):
        if int(i) not in best or g < best[int(i)][0]:
            best[int(i)] = (float(g), int(j))
    return sorted((i, j) for i, (_, j) in best.items())


def _samples(geoms) -> tuple[np.ndarray, np.ndarray]:
    """(n, SAMPLES, 2) points at 10%, 20%, ..., 90% of each lane's length, and the lane's unit direction there."""
    s = np.linspace(0.1, 0.9, SAMPLES)[None, :] * shapely.length(geoms)[:, None]
    lines = np.repeat(geoms[:, None], SAMPLES, 1)
    return shapely.get_coordinates(shapely.line_interpolate_point(lines, s)).reshape(-1, SAMPLES, 2), _tangent(lines, s)


def _beside(geoms, points, tangents, a, b, width, lateral):
    """For each pair (a[k], b[k]): the signed lateral offsets (+ = left) of lane b seen from the
    samples of lane a, and whether b lies beside a there."""
    p, tangent_a = points[a], tangents[a]
    gb = np.repeat(geoms[b][:, None], SAMPLES, 1)
    sb = shapely.line_locate_point(gb, shapely.points(p))
    q = shapely.get_coordinates(shapely.line_interpolate_point(gb, sb)).reshape(-1, SAMPLES, 2)
    tangent_b = _tangent(gb, sb)
    d = q - p
    along = np.einsum("...k,...k", d, tangent_a)
    normal = np.stack([-tangent_a[..., 1], tangent_a[..., 0]], -1)
    offset = np.einsum("...k,...k", d, normal)
    cos = np.abs(np.einsum("...k,...k", tangent_a, tangent_b))
    length_b = shapely.length(geoms[b])[:, None]
    inside = (sb > 1e-6) & (sb < length_b - 1e-6)  # the nearest point is not an end of b
    gap = np.abs(offset) / width[:, None]
    beside = (inside & (np.abs(along) <= MAX_SKEW_M) & (cos >= np.cos(np.radians(MAX_ANGLE_DEG)))
              & (gap >= lateral[0]) & (gap <= lateral[1]))
    return offset, beside


def _tangent(geoms, s, h: float = 0.5) -> np.ndarray:
    """Unit direction of each line at arc length ``s`` (a central difference of ``h`` metres)."""
    length = shapely.length(geoms)
    lo, hi = np.clip(s - h, 0.0, length), np.clip(s + h, 0.0, length)
    shape = np.shape(s) + (2,)
    d = (shapely.get_coordinates(shapely.line_interpolate_point(geoms, hi)).reshape(shape)
         - shapely.get_coordinates(shapely.line_interpolate_point(geoms, lo)).reshape(shape))
    return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def same_direction(lanes, i: int, j: int) -> bool:
    """Whether lanes i and j run the same way (their directions at their middles within 90 degrees)."""
    a, b = _lines([lanes[i], lanes[j]])
    ta = _tangent(a, 0.5 * shapely.length(a))
    sb = shapely.line_locate_point(b, shapely.line_interpolate_point(a, 0.5 * shapely.length(a)))
    return float(np.dot(ta, _tangent(b, sb))) > 0.0


def side_of(lanes, i: int, j: int) -> int:
    """1 where lane j lies on lane i's left (seen from i's middle), else -1."""
    a, b = _lines([lanes[i], lanes[j]])
    middle = shapely.line_interpolate_point(a, 0.5, normalized=True)
    d = shapely.get_coordinates(shapely.line_interpolate_point(b, shapely.line_locate_point(b, middle)))[0]
    t = _tangent(a, 0.5 * shapely.length(a))
    p = shapely.get_coordinates(middle)[0]
    return 1 if t[0] * (d[1] - p[1]) - t[1] * (d[0] - p[0]) > 0 else -1


def abreast(a, b, same: bool = True) -> bool:
    """Whether two neighbouring lanes start and end abreast: along each lane, the other's ends lie within
    ``ABREAST_M`` (and a third of the shorter lane) of its own, so one bound can serve both. ``same``:
    whether they run the same way (else ``b`` is compared reversed)."""
    la = shapely.LineString(np.asarray(a, np.float64))
    lb = shapely.LineString(np.asarray(b, np.float64)[:: 1 if same else -1])
    tolerance = min(ABREAST_M, la.length / 3.0, lb.length / 3.0)
    for line, other in ((la, lb), (lb, la)):
        ends = np.array([line.project(shapely.Point(other.coords[0])), line.project(shapely.Point(other.coords[-1]))])
        if np.any(np.abs(ends - [0.0, line.length]) > tolerance):
            return False
    return True


def lane_widths(lanes, left_neighbors, widths=None, default: float = LANE_WIDTH_M) -> np.ndarray:
    """A width per lane: the given ``widths``, else the mean centre spacing to its lane-change
    neighbours, else the median of all those spacings, else ``default``; clipped to [2.5, 5] m."""
    if widths is not None:
        return np.asarray(widths, np.float64)
    spacing: list[list[float]] = [[] for _ in range(len(lanes))]
    for i, j in left_neighbors:
        g = _gap(lanes[i], lanes[j])
        spacing[i].append(g)
        spacing[j].append(g)
    every = [g for s in spacing for g in s]
    fallback = float(np.median(every)) if every else default
    out = np.array([np.mean(s) if s else fallback for s in spacing], np.float64)
    return np.clip(out, 2.5, 5.0)


def _gap(a, b) -> float:
    """Mean distance from the middle 80% of lane a to lane b."""
    ga, gb = _lines([a, b])
    pts = shapely.line_interpolate_point(ga, np.linspace(0.1, 0.9, SAMPLES), normalized=True)
    return float(shapely.distance(pts, gb).mean())


def _lines(lanes) -> np.ndarray:
    return np.array([shapely.LineString(np.asarray(l, np.float64)) for l in lanes], dtype=object)
