"""Lane geometry metrics between a predicted and a reference set of polylines (ego-frame metres).

Both sets are resampled at a fixed spacing and every sample point is scored by its distance to the
nearest segment of the other set (an STR-tree nearest-neighbour search, so a scene of thousands of
lanes takes seconds). Conventions for empty sets: a score over zero points is vacuously
1 (an empty prediction has precision 1, an empty reference gives recall 1), so both empty -> 1/1/1,
and when exactly one set is empty the score of the side that has points is 0 and F1 is 0.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import shapely
from scipy.spatial import cKDTree

from cmtool.core.geometry import as_polyline, equal_count_batches


def sample_points(polylines: Sequence[np.ndarray], step: float) -> np.ndarray:
    """All polylines resampled every ``step`` metres (``resample_step``), stacked into (N, 2) points
    (:func:`resampled`)."""
    pts = resampled([as_polyline(p) for p in polylines], step)
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def resampled(lines: Sequence[np.ndarray], step: float) -> list[np.ndarray]:
    """``resample_step(line, step)`` of each of ``lines`` (float (N, 2) arrays), lines of equal vertex counts together
    (:func:`_resampled`): the same numbers, a few NumPy calls per batch instead of per line."""
    out: list = [None] * len(lines)
    for which, batch in equal_count_batches(lines):
        for k, points in zip(which, _resampled(batch, step)):
            out[k] = points
    return out


def _resampled(lines: np.ndarray, step: float) -> list[np.ndarray]:
    """``resample_step(line, step)`` of each of (m, L, 2) lines, operation for operation as ``np.linspace`` and
    ``np.interp`` do it (the tests compare them bit for bit), a few NumPy calls per batch instead of per line."""
    seg = np.linalg.norm(np.diff(lines, axis=1), axis=2)
    total = seg.sum(axis=1)
    cum = np.concatenate([np.zeros((len(lines), 1)), np.cumsum(seg, axis=1)], axis=1)
    n = np.maximum(2, np.ceil(total / step).astype(np.int64) + 1)
    row = np.repeat(np.arange(len(lines)), n)
    k = np.arange(len(row)) - np.repeat(np.cumsum(n) - n, n)
    end = cum[:, -1][row]
    s = k * (cum[:, -1] / (n - 1))[row] + 0.0  # np.linspace(0, end, n): k * step + start, the last point end
    s[k == n[row] - 1] = end[k == n[row] - 1]
    j = (cum[row] <= s[:, None]).sum(axis=1) - 1  # np.interp's interval: the last vertex at or before s
    last = j >= lines.shape[1] - 1
    jj = np.minimum(j, lines.shape[1] - 2)
    x0, x1, s = cum[row, jj][:, None], cum[row, jj + 1][:, None], s[:, None]
    y0, y1 = lines[row, jj], lines[row, jj + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        value = (y1 - y0) / (x1 - x0) * (s - x0) + y0
    out = np.where(last[:, None], lines[row, -1], np.where(x0 == s, y0, value))
    zero = end <= 0.0  # a line of no length: its first point, repeated
    out[zero] = lines[row[zero], 0]
    return np.split(out, np.cumsum(n)[:-1])


def distance_to_polylines(points: np.ndarray, polylines: Sequence[np.ndarray]) -> np.ndarray:
    """Distance (N,) from each point (N, 2) to the nearest of ``polylines`` (inf if none): the exact distance to
    the nearest segment. A few points go through GEOS's nearest-neighbour search over an STR-tree of the segments;
    many (a scene of 100,000 lanes has millions of sample points) through a KD-tree of short pieces of the
    segments (:func:`_nearest_segments`), the same numbers some ten times faster."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(points), np.inf)
    if len(polylines) and len(points):
        lines = [as_polyline(p) for p in polylines]
        starts, ends = np.concatenate([l[:-1] for l in lines]), np.concatenate([l[1:] for l in lines])
        if len(points) >= KD_MIN_POINTS:
            return _nearest_segments(points, starts, ends)
        segments = shapely.linestrings(np.stack([starts, ends], axis=1))
        (which, _), dist = shapely.STRtree(segments).query_nearest(shapely.points(points), return_distance=True,
                                                                   all_matches=False)
        out[which] = dist
    return out


KD_MIN_POINTS = 20_000  # points from which distance_to_polylines searches a KD-tree instead of GEOS's STR-tree
PIECE_M = 1.0  # the KD-tree holds the middles of pieces of the segments at most this long (longer on vast maps)
KD_BATCH = 1 << 22  # point-candidate pairs a step of the search holds
CROWDED_POINTS, FINEST_M = 1_000, 1e-3  # more points crowded beyond 64 pieces are searched again over finer pieces


def _nearest_segments(points: np.ndarray, starts: np.ndarray, ends: np.ndarray, piece: float | None = None
                      ) -> np.ndarray:
    """The distance from each point to the nearest segment (``starts[k]``-``ends[k]``), exact (GEOS's own formula,
    :func:`_segment_distances`): every segment is cut into pieces of at most ``piece`` metres (:func:`_pieces`),
    whose middles a KD-tree holds. A segment within d of a point has a piece whose middle lies within d + half a
    piece, so once the nearest k middles reach beyond (the best segment among theirs) + half a piece, or a point
    lies on a segment, no other segment can be nearer; points where they do not are searched again with 8 times as
    many, then by a ball search, or, where over ``CROWDED_POINTS`` are left (lanes piled on each other), over pieces
    8 times shorter of the segments near them (down to pieces of ``FINEST_M``)."""
    tree, owner, reach = _pieces(len(points), starts, ends, piece)
    out = np.full(len(points), np.inf)
    todo, k = np.arange(len(points)), 8
    while len(todo) and k <= 64:
        left, size = [], max(1, KD_BATCH // k)
        for begin in range(0, len(todo), size):
            rows = todo[begin:begin + size]
            near, piece_of = tree.query(points[rows], k=min(k, len(owner)))
            near, piece_of = near.reshape(len(rows), -1), piece_of.reshape(len(rows), -1)
            p, seg = points[rows], owner[np.minimum(piece_of, len(owner) - 1)]
            dist = np.full(near.shape, np.inf)
            dist[:, 0] = _segment_distances(p, starts[seg[:, 0]], ends[seg[:, 0]])
            maybe = near < dist[:, :1] + reach  # only pieces that may hold a nearer segment
            maybe[:, 0] = False
            r, c = np.nonzero(maybe)
            dist[r, c] = _segment_distances(p[r], starts[seg[r, c]], ends[seg[r, c]])
            best = dist.min(axis=1)
            out[rows] = best
            done = (near.shape[1] == len(owner)) | (near[:, -1] >= best + reach) | (best == 0.0)  # none is nearer
            left.append(rows[~done])
        todo, k = np.concatenate(left), 8 * k
    if len(todo) > CROWDED_POINTS and reach > FINEST_M:  # lanes piled: the segments that may be nearer, finer cut
        lo = points[todo].min(axis=0) - out[todo].max() - reach
        hi = points[todo].max(axis=0) + out[todo].max() + reach
        near = np.flatnonzero(np.all((np.minimum(starts, ends) <= hi) & (np.maximum(starts, ends) >= lo), axis=1))
        out[todo] = _nearest_segments(points[todo], starts[near], ends[near], reach / 4.0)
        return out
    for row in todo.tolist():  # a few crowded points: every piece within reach
        seg = np.unique(owner[tree.query_ball_point(points[row], out[row] + reach)])
        out[row] = _segment_distances(points[row], starts[seg], ends[seg]).min()
    return out


def _pieces(points: int, starts: np.ndarray, ends: np.ndarray, piece: float | None = None
            ) -> tuple[cKDTree, np.ndarray, float]:
    """A KD-tree of the middles of the segments cut into pieces of at most ``piece`` metres (default ``PIECE_M``, longer
    where the segments are longer in all than ``PIECE_M`` per one of ``points`` query points or segments), the
    segment of each piece, and the most any point of a segment lies from its nearest piece middle (a hair more, for
    rounding)."""
    vector = ends - starts
    length = np.hypot(vector[:, 0], vector[:, 1])
    piece = max(PIECE_M, float(length.sum()) / max(points, len(starts))) if piece is None else piece
    count = np.maximum(np.ceil(length / piece), 1).astype(np.int64)
    owner = np.repeat(np.arange(len(starts)), count)
    at = (np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count) + 0.5) / count[owner]
    reach = 0.5 * float((length / count).max()) * (1 + 1e-9) + 1e-9
    return cKDTree(starts[owner] + at[:, None] * vector[owner]), owner, reach


def _segment_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from points ``p`` to segments ``a``-``b`` (broadcast), computed as GEOS's
    ``Distance::pointToSegment`` does, operation for operation, so the numbers are GEOS's."""
    px, py, ax, ay, bx, by = p[..., 0], p[..., 1], a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    ex, ey = bx - ax, by - ay
    with np.errstate(divide="ignore", invalid="ignore"):
        len2 = ex * ex + ey * ey
        r = ((px - ax) * ex + (py - ay) * ey) / len2
        s = ((ay - py) * ex - (ax - px) * ey) / len2
        to_a = np.sqrt((px - ax) * (px - ax) + (py - ay) * (py - ay))
        to_b = np.sqrt((px - bx) * (px - bx) + (py - by) * (py - by))
        inner = np.abs(s) * np.sqrt(len2)
    point = (ax == bx) & (ay == by)
    return np.where(point | (r <= 0.0), to_a, np.where(r >= 1.0, to_b, inner))


def near_polylines(points: np.ndarray, polylines: Sequence[np.ndarray], tol: float) -> np.ndarray:
    """Whether each point (N, 2) lies within ``tol`` of one of ``polylines``, as GEOS's ``dwithin`` answers it
    (``distance_to_polylines <= tol``): asked only of the points :func:`_settled` leaves, about three times faster
    than asking it of every point over an STR-tree of the lanes."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not len(polylines) or not len(points):
        return np.zeros(len(points), bool)
    lines = [as_polyline(p) for p in polylines]
    out, unsure = _settled(points, lines, tol)
    if len(unsure):
        out[unsure[_tree(lines).query(shapely.points(points[unsure]), predicate="dwithin", distance=tol)[0]]] = True
    return out


def within_distance(points: np.ndarray, polylines: Sequence[np.ndarray], tol: float) -> np.ndarray:
    """``distance_to_polylines(points, polylines) <= tol``, the same answers: the distances only of the points
    :func:`_settled` leaves."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not len(polylines) or not len(points):
        return np.zeros(len(points), bool)
    lines = [as_polyline(p) for p in polylines]
    out, unsure = _settled(points, lines, tol)
    out[unsure] = distance_to_polylines(points[unsure], lines) <= tol
    return out


def _settled(points: np.ndarray, lines: list[np.ndarray], tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Whether each point lies within ``tol`` of ``lines`` where the nearest piece middle (:func:`_pieces`) settles it,
    and the indices of the points it leaves unsettled, near that border: a point within ``tol`` of a segment has a
    piece middle within ``tol`` plus half a piece, and one that has a piece middle within ``tol`` is within it
    (both with a margin for rounding)."""
    starts, ends = np.concatenate([l[:-1] for l in lines]), np.concatenate([l[1:] for l in lines])
    tree, _, reach = _pieces(len(points), starts, ends)
    rounding = ROUNDING * (1.0 + max(np.abs(points).max(), np.abs(starts).max(), np.abs(ends).max()))
    dist = tree.query(points, distance_upper_bound=tol + reach + rounding)[0]
    within = dist <= tol - rounding
    return within, np.flatnonzero(~within & (dist <= tol + reach + rounding))


ROUNDING = 1e-12  # of the largest coordinate: more than the rounding of a distance between points


def _tree(polylines: Sequence[np.ndarray]) -> shapely.STRtree:
    lines = [as_polyline(p) for p in polylines]
    owner = np.repeat(np.arange(len(lines)), [len(l) for l in lines])
    return shapely.STRtree(shapely.linestrings(np.concatenate(lines), indices=owner))


def pair_distances(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray],
                   step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The distances of ``pred``'s sample points (every ``step`` m) to ``gt``, and of ``gt``'s to ``pred``:
    what the lane scores and the Chamfer distance are made of."""
    return (distance_to_polylines(sample_points(pred, step), gt),
            distance_to_polylines(sample_points(gt, step), pred))


def scores_at(distances: tuple[np.ndarray, np.ndarray], tol: float) -> dict:
    """Precision / recall / F1 at ``tol`` m from :func:`pair_distances` (a score over no points is 1)."""
    return _scores(*(float(np.mean(d <= tol)) if len(d) else 1.0 for d in distances))


def _scores(precision: float, recall: float) -> dict:
    f1 = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"precision": precision, "recall": recall, "f1": f1}


def lane_scores(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray], tol: float = 1.0, step: float = 0.5) -> dict:
    """Point precision / recall / F1 of predicted lanes against reference lanes at tolerance ``tol`` m.

    precision: share of predicted sample points within ``tol`` of a reference polyline; recall: share
    of reference sample points within ``tol`` of a predicted polyline (see the module docstring for
    empty sets). Returns ``{"precision", "recall", "f1"}`` floats.
    """
    return scores_at(pair_distances(pred, gt, step), tol)


def lane_scores_of_scenes(preds: Sequence[Sequence[np.ndarray]], gts: Sequence[Sequence[np.ndarray]],
                          tol: float = 1.0, step: float = 0.5) -> list[dict]:
    """:func:`lane_scores` of many scenes (``preds[k]`` against ``gts[k]``) in one search each way: the scenes are laid
    side by side on a grid, further apart than any of their points lie from their origin plus ``tol``, so no point
    finds another scene's lane within ``tol``. The same scores, but for a point within rounding (about 1e-11 m) of
    ``tol``."""
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted scenes for {len(gts)} reference scenes")
    if not len(preds):
        return []
    sides = [[[as_polyline(p) for p in scene] for scene in group] for group in (preds, gts)]
    extent = max([float(np.abs(l).max()) for group in sides for scene in group for l in scene] or [0.0])
    spacing, columns = 2.0 * extent + tol + 1.0, max(1, int(np.ceil(np.sqrt(len(preds)))))
    offsets = [np.array([k % columns, k // columns], np.float64) * spacing for k in range(len(preds))]
    placed = [[[l + o for l in scene] for scene, o in zip(group, offsets)] for group in sides]
    shares = []
    for own, other in ((0, 1), (1, 0)):
        samples = resampled([l for scene in placed[own] for l in scene], step)  # every scene's lines at once
        points = np.concatenate(samples) if samples else np.zeros((0, 2))
        within = within_distance(points, [l for scene in placed[other] for l in scene], tol)
        per_line = np.cumsum([0] + [len(p) for p in samples])
        ends = per_line[np.cumsum([len(scene) for scene in placed[own]])]
        shares.append([float(np.mean(w)) if len(w) else 1.0 for w in np.split(within, ends[:-1])])
    return [_scores(p, r) for p, r in zip(*shares)]

