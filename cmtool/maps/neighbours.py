"""Lanes beside each other: lane-change neighbours and oncoming lanes across a centre line.

Two lanes are beside each other when one runs about a lane width from the other along most of both.
In the same direction they are lane-change neighbours, recorded as ``left_neighbors`` pairs
``(i, j)``: lane ``j`` is lane ``i``'s left neighbour. In opposite directions they share the centre
line, recorded as ``oncoming`` pairs ``(i, j)``, ``i < j``: on each other's left in right-hand
traffic, on each other's right in left-hand traffic (:func:`side_of` tells which). Generated lanes get
both from the geometry alone (:func:`find_neighbours`); imported maps keep the lane-change
neighbours their source records and add the oncoming pairs, which no source records.

Lanes piled on each other, whose search would take more pairs than ``MAX_NEAR`` allows (estimated from the first
lanes searched, in a fixed-seed random order), are refused with :class:`Crowded` before the most of the work.
"""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.core.memory import in_batches
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
    left, right = _searched(lanes, widths, None, (1, -1))
    same = dict(zip(left + right, same_directions(lanes, left + right).tolist()))
    oncoming = sorted({(min(i, j), max(i, j)) for (i, j), s in same.items() if not s})
    if recorded is not None:
        left = infer_neighbours(lanes, widths, candidates=recorded)
        same = dict(zip(left, same_directions(lanes, left).tolist()))
    return [(i, j) for i, j in left if same[i, j]], oncoming


def relaned(graph, lanes, successors, meta: dict | None = None, found: bool = True):
    """A copy of lane graph ``graph`` with other ``lanes`` and ``successors`` (and ``meta``, when given): its
    neighbours and widths found anew from the geometry (``found`` False: left unrecorded, for a graph changed again
    before it is used), its lights, city and frame kept."""
    out = LaneGraph(lanes=lanes, successors=sorted(set(successors)), green_lights=graph.green_lights,
                    red_lights=graph.red_lights, city=graph.city, frame_m=graph.frame_m,
                    meta=graph.meta if meta is None else meta)
    return with_neighbours(out) if found else out


def with_neighbours(graph):
    """``graph`` with its neighbours and widths found from its geometry where it records none (the same object
    where it does)."""
    if graph.left_neighbors is not None:
        return graph
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    left, oncoming = find_neighbours(lanes)
    return replace(graph, left_neighbors=left, oncoming=oncoming, widths=lane_widths(lanes, left).round(2).tolist())


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
    return _searched(lanes, widths, candidates, (side,))[0]


def _searched(lanes, widths, candidates, sides) -> list[list[tuple[int, int]]]:
    """:func:`infer_neighbours` on each of ``sides``, from one search."""
    if len(lanes) < 2:
        return [[] for _ in sides]
    keys = None
    if candidates is None and len(lanes) >= CACHE_MIN_LANES:  # a huge map's export and checks ask several times
        keys = [_content_key(lanes, widths, side) for side in sides]
        if all(key in _FOUND for key in keys):
            return [list(_FOUND[key]) for key in keys]
    found = _beside_all(lanes, widths, candidates)
    out = [_nearest(*found, side) for side in sides]
    if keys is not None:
        if len(_FOUND) + len(keys) > 4:
            _FOUND.clear()
        _FOUND.update((key, list(pairs)) for key, pairs in zip(keys, out))
    return out


CACHE_MIN_LANES = 5_000  # maps from this many lanes keep their last few neighbour searches, keyed by content
_FOUND: dict[bytes, list[tuple[int, int]]] = {}


def _content_key(lanes, widths, side: int) -> bytes:
    """A digest of the lanes' coordinates (and vertex counts), the widths and the side: equal only for the same
    search."""
    digest = hashlib.blake2b(digest_size=32)
    digest.update(np.array([len(l) for l in lanes], np.int64).tobytes())
    digest.update(np.ascontiguousarray(np.concatenate([np.asarray(l, np.float64) for l in lanes])).tobytes())
    digest.update(b"none" if widths is None else np.asarray(widths, np.float64).tobytes())
    digest.update(str(side).encode())
    return digest.digest()


def _beside_all(lanes, widths, candidates):
    """The pairs (a, b) of lanes beside each other, either side, with the signed offsets of b seen from a's samples
    and where b lies beside a (:func:`_beside_pairs`): (a, b, offset, beside)."""
    n = len(lanes)
    geoms = _lines(lanes)
    points, tangents = _samples(geoms)
    spots = shapely.points(points)  # the samples as geometries, made once
    w = np.full(n, LANE_WIDTH_M) if widths is None else np.asarray(widths, np.float64)
    middle = SAMPLES // 2  # each lane's middle must lie beside the other: a cheap first cut
    if candidates is not None:
        pairs = np.array([(i, j) for i, j in candidates if i != j], np.int64).reshape(-1, 2)
        a, b = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
        lateral = (0.0, np.inf)
        return _beside_pairs(geoms, points, spots, tangents, *_cut(geoms, spots, w, a, b, lateral), lateral)
    reach, tree = float(LATERAL[1] * w.max()), shapely.STRtree(geoms)
    order, found, count = np.random.default_rng(0).permutation(n), [], np.zeros(3, np.int64)

    def crowded() -> bool:  # either count of pairs, estimated over all lanes from at least 256 of them, over its limit
        return bool(np.any(count[1:] * n > np.array(MAX_NEAR) * max(count[0], min(n, 256))))

    def search(lo: int, hi: int) -> int:  # lanes in a random order, so the first batches tell how crowded the map is
        a, b = _near(tree, spots[:, middle], np.sort(order[lo:hi]), reach)
        near = len(a)
        count[:2] += [hi - lo, near]  # lanes searched, candidate pairs
        if not crowded():
            a, b, width = _cut(geoms, spots, w, a, b, LATERAL)
            count[2] += len(a)  # pairs left to the full test
            if not crowded():
                found.append(_beside_pairs(geoms, points, spots, tangents, a, b, width, LATERAL))
        return near

    if in_batches(n, search, most=NEAR_BATCH, until=crowded) < n or crowded():
        near, full = (count[1:] * n // count[0]).tolist()
        what = (f"{near:,} candidate pairs (a lane's middle within {reach:.2f} m of the other)" if near > MAX_NEAR[0]
                else f"{full:,} pairs to test in full")
        raise Crowded(f"lanes piled on each other: about {what}, over the {MAX_NEAR[near <= MAX_NEAR[0]]:,} that the "
                      "lane-change neighbour search takes")
    return tuple(np.concatenate([f[k] for f in found]) for k in range(4))


def _nearest(a, b, offset, beside, side: int) -> list[tuple[int, int]]:
    """The pairs (i, j) of :func:`_beside_all` where j lies on i's ``side`` (by the median offset where beside),
    and no lane beside i on that side lies nearer (by the median gap; the first found of equals)."""
    there = side * _medians(offset, beside) > 0
    gap = _medians(np.abs(offset), beside)
    best: dict[int, tuple[float, int]] = {}  # i -> (gap, j): only the nearest lane on that side
    for i, j, g in zip(a[there].tolist(), b[there].tolist(), gap[there].tolist()):
        if i not in best or g < best[i][0]:
            best[i] = (g, j)
    return sorted((i, j) for i, (_, j) in best.items())


def _medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``np.median`` of each row of ``values`` where ``mask`` holds (NaN where it holds nowhere), the same numbers
    from one sort."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    rows = np.arange(len(values))
    low, high = ordered[rows, (count - 1) // 2], ordered[rows, count // 2]
    return np.where(count > 0, (low + high) / 2.0, np.nan)


NEAR_BATCH = 4096  # lanes whose candidate pairs are sought and tested together, at most
MAX_NEAR = (5_000_000, 500_000)  # candidate pairs, and pairs tested in full (a dense city: 30 and 2 a lane), at most


class Crowded(CmtoolError):
    """Lanes piled so thick that the neighbour search would take more pairs than ``MAX_NEAR`` allows."""


def _near(tree, middles, lanes: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b), a in ``lanes``, in order of a, then of the STR-tree, where a's middle point lies within
    ``reach`` (a hair wider) of lane b. The gap test after asks both middles to lie within 1.5 widths, no more than
    ``reach``, of the other lane, so the pairs where only one does need no cut here."""
    q, b = tree.query(middles[lanes], predicate="dwithin", distance=reach * (1 + 1e-9))
    return lanes[q], b


def _cut(geoms, spots, w, a, b, lateral):
    """The candidate pairs (a, b) that the cheap cuts leave (both middles at a lateral gap from the other lane, then
    :func:`_may_be_beside` both ways), and their mean widths: (a, b, width)."""
    middle, m = SAMPLES // 2, len(a)
    width = 0.5 * (w[a] + w[b])
    gap = shapely.distance(spots[np.r_[a, b], middle], geoms[np.r_[b, a]]) / np.r_[width, width]
    near = (gap >= lateral[0]) & (gap <= lateral[1])
    keep = (a != b) & near[:m] & near[m:]
    a, b, width = a[keep], b[keep], width[keep]
    m = len(a)
    keep = _may_be_beside(geoms, spots, np.r_[a, b], np.r_[b, a], np.r_[width, width], lateral)
    keep = keep[:m] & keep[m:]
    return a[keep], b[keep], width[keep]


def _beside_pairs(geoms, points, spots, tangents, a, b, width, lateral):
    """The pairs (a, b) of :func:`_cut` that lie beside each other along most of both lanes, with the signed offsets
    of b seen from a's samples and where b lies beside a: (a, b, offset, beside). Each test looks both ways at once."""
    m = len(a)
    offset, beside = _beside(geoms, points, spots, tangents, np.r_[a, b], np.r_[b, a], np.r_[width, width], lateral)
    ok = (beside[:m].mean(1) >= MIN_SHARE) & (beside[m:].mean(1) >= MIN_SHARE)
    return a[ok], b[ok], offset[:m][ok], beside[:m][ok]


def _may_be_beside(geoms, spots, a, b, width, lateral) -> np.ndarray:
    """Whether lane b may lie beside enough of lane a's samples for :func:`_beside` to find it beside: a necessary
    cut before that exact test, by distances alone. A sample beside b lies between ``lateral[0]`` widths and the
    reach of ``lateral[1]`` widths and ``MAX_SKEW_M`` from b (1 mm wider, for rounding)."""
    near = shapely.distance(spots[a], geoms[b][:, None])
    lo, hi = lateral[0] * width - 1e-3, np.hypot(lateral[1] * width, MAX_SKEW_M) + 1e-3
    return ((near >= lo[:, None]) & (near <= hi[:, None])).mean(axis=1) >= MIN_SHARE


def _samples(geoms) -> tuple[np.ndarray, np.ndarray]:
    """(n, SAMPLES, 2) points at 10%, 20%, ..., 90% of each lane's length, and the lane's unit direction there."""
    s = np.linspace(0.1, 0.9, SAMPLES)[None, :] * shapely.length(geoms)[:, None]
    lines = np.repeat(geoms[:, None], SAMPLES, 1)
    return shapely.get_coordinates(shapely.line_interpolate_point(lines, s)).reshape(-1, SAMPLES, 2), _tangent(lines, s)


def _beside(geoms, points, spots, tangents, a, b, width, lateral):
    """For each pair (a[k], b[k]): the signed lateral offsets (+ = left) of lane b seen from the
    samples of lane a, and whether b lies beside a there."""
    p, tangent_a = points[a], tangents[a]
    gb = np.repeat(geoms[b][:, None], SAMPLES, 1)
    sb = shapely.line_locate_point(gb, spots[a])
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
    return bool(same_directions(lanes, [(i, j)])[0])


def same_directions(lanes, pairs) -> np.ndarray:
    """:func:`same_direction` of each pair ``(i, j)``, in one pass of vectorised GEOS calls."""
    geoms = _pair_lines(lanes, pairs)
    a, b = geoms[:, 0], geoms[:, 1]
    half = 0.5 * shapely.length(a)
    sb = shapely.line_locate_point(b, shapely.line_interpolate_point(a, half))
    return np.einsum("...k,...k", _tangent(a, half), _tangent(b, sb)) > 0.0


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
    return bool(abreasts([a, b], [(0, 1)], [same])[0])


def abreasts(lanes, pairs, same) -> np.ndarray:
    """:func:`abreast` of each pair ``(i, j)`` (``same``: whether each pair runs the same way), in one pass of
    vectorised GEOS calls."""
    geoms = _pair_lines(lanes, pairs).reshape(-1, 2)
    geoms[:, 1] = np.where(same, geoms[:, 1], shapely.reverse(geoms[:, 1]))
    length = shapely.length(geoms)
    tolerance = np.minimum(ABREAST_M, length.min(axis=1) / 3.0)
    ends = [shapely.get_point(geoms[:, k], e) for k in (1, 0) for e in (0, -1)]  # the other lane's ends, on each
    along = shapely.line_locate_point(geoms[:, [0, 0, 1, 1]], np.stack(ends, axis=1))
    want = np.stack([np.zeros(len(geoms)), length[:, 0], np.zeros(len(geoms)), length[:, 1]], axis=1)
    return ~np.any(np.abs(along - want) > tolerance[:, None], axis=1)


def lane_widths(lanes, left_neighbors, widths=None, default: float = LANE_WIDTH_M) -> np.ndarray:
    """A width per lane: the given ``widths``, else the mean centre spacing to its lane-change
    neighbours, else the median of all those spacings, else ``default``; clipped to [2.5, 5] m."""
    if widths is not None:
        return np.asarray(widths, np.float64)
    spacing: list[list[float]] = [[] for _ in range(len(lanes))]
    for (i, j), g in zip(left_neighbors, _gaps(lanes, left_neighbors).tolist()):
        spacing[i].append(g)
        spacing[j].append(g)
    every = [g for s in spacing for g in s]
    fallback = float(np.median(every)) if every else default
    out = np.array([np.mean(s) if s else fallback for s in spacing], np.float64)
    return np.clip(out, 2.5, 5.0)


def _gaps(lanes, pairs) -> np.ndarray:
    """Of each pair (i, j): the mean distance from the middle 80% of lane i to lane j."""
    geoms = _pair_lines(lanes, pairs)
    pts = shapely.line_interpolate_point(geoms[:, :1], np.linspace(0.1, 0.9, SAMPLES), normalized=True)
    return shapely.distance(pts, geoms[:, 1:]).mean(axis=1)


def _pair_lines(lanes, pairs) -> np.ndarray:
    """The LineStrings (P, 2) of the lanes of each pair (i, j), each lane made once and only the lanes of the pairs
    (one pair of a huge map must not build them all)."""
    used, index = np.unique(np.asarray(pairs, np.int64).reshape(-1, 2), return_inverse=True)
    return _lines([lanes[k] for k in used.tolist()])[index.reshape(-1, 2)]


def _lines(lanes) -> np.ndarray:
    """The lanes as shapely LineStrings, made in one call."""
    if not len(lanes):
        return np.empty(0, object)
    coords = np.concatenate([np.asarray(l, np.float64) for l in lanes])
    return shapely.linestrings(coords, indices=np.repeat(np.arange(len(lanes)), [len(l) for l in lanes]))
