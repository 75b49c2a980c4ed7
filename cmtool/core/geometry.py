"""Small polyline helpers shared across the pipeline (numpy arrays of shape (N, 2), metres)."""

from __future__ import annotations

import math

import numpy as np

MAX_COORD_M = 1e8  # map coordinates are metres: a projected map of the whole Earth stays within 2e7


def as_polyline(points, min_points: int = 2) -> np.ndarray:
    """Return ``points`` as a float64 (N, 2) array, checking shape, finiteness and range (``MAX_COORD_M``)."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except OverflowError:
        raise ValueError("a coordinate is too large a number") from None
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < min_points:
        raise ValueError(f"expected at least {min_points} points of [x, y], got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("polyline has NaN or infinite coordinates")
    if arr.size and np.abs(arr).max() > MAX_COORD_M:
        raise ValueError(f"a coordinate lies beyond {MAX_COORD_M:.0e} m (metres are expected)")
    return arr


def segment_lengths(line: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(line, axis=0), axis=1)


def arc_length(line: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each vertex (starts at 0)."""
    return np.concatenate([[0.0], np.cumsum(segment_lengths(line))])


def unit(v: np.ndarray) -> np.ndarray:
    """Vectors (..., 2) scaled to length 1 along the last axis; zero vectors stay zero."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def polyline_length(line: np.ndarray) -> float:
    return float(segment_lengths(line).sum())


def resample(line: np.ndarray, n: int) -> np.ndarray:
    """Resample a polyline to ``n`` points equally spaced along its arc length."""
    cum = arc_length(line)
    if cum[-1] <= 0.0:
        return np.repeat(line[:1], n, axis=0)
    s = np.linspace(0.0, cum[-1], n)
    return np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], axis=1)


def resample_step(line: np.ndarray, step: float) -> np.ndarray:
    """Resample a polyline at (about) ``step`` metre spacing, keeping both end points."""
    n = max(2, int(np.ceil(polyline_length(line) / step)) + 1)
    return resample(line, n)


def bernstein_basis(num_points: int, control_points: int) -> np.ndarray:
    """(P, K): row i holds the weights of the K control points of a Bézier curve at the i-th of
    ``P = num_points`` evenly spaced curve parameters in [0, 1] (Bernstein polynomials of degree K - 1)."""
    if num_points < 2 or control_points < 2:
        raise ValueError(f"need at least 2 points and 2 control points, got {num_points} and {control_points}")
    t = np.linspace(0.0, 1.0, num_points)[:, None]
    degree = control_points - 1
    k = np.arange(control_points)
    binomial = np.array([math.comb(degree, i) for i in k], dtype=np.float64)
    return binomial * t**k * (1.0 - t) ** (degree - k)


def bezier_fit_matrix(num_points: int, control_points: int) -> np.ndarray:
    """The (P, P) matrix ``M`` such that ``M @ line`` replaces the ``P = num_points`` points of a polyline,
    taken at evenly spaced curve parameters, by the least-squares Bézier curve with ``control_points``
    control points, sampled at the same parameters. It is a projection (applying it twice changes
    nothing); curves of degree below ``control_points`` pass through unchanged, and with
    ``control_points >= num_points`` it is the identity."""
    basis = bernstein_basis(num_points, control_points)
    return basis @ np.linalg.pinv(basis)


def headings(line: np.ndarray) -> np.ndarray:
    """Heading (radians, atan2(dy, dx)) of each point, from its neighbouring segments."""
    d = np.gradient(line, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def wrap_angle(a):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def to_frame(points: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """Express world points in the frame of a pose (x forward along ``yaw``, y left); ``x``, ``y`` and ``yaw`` may be
    arrays that broadcast against the points' first axes (one pose per point or row)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(points, dtype=np.float64) - np.stack([x, y], axis=-1)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


CV_SHIFT = 4  # fraction bits of OpenCV's sub-pixel drawing coordinates


def ego_to_pixel(points, px_m: float, frame_m: float = 64.0) -> np.ndarray:
    """Ego-frame metres (..., 2) -> OpenCV fixed-point pixel coordinates (..., 2) int32, as
    (column, row) with ``CV_SHIFT`` fraction bits. The raster convention (docs/data.md: "Frames and rasters"): row 0 is
    the front edge (x = +frame/2), column 0 the left edge (y = +frame/2)."""
    half = frame_m / 2.0
    p = np.asarray(points, dtype=np.float64)
    cr = np.stack([(half - p[..., 1]) / px_m - 0.5, (half - p[..., 0]) / px_m - 0.5], axis=-1)
    return np.round(cr * (1 << CV_SHIFT)).astype(np.int32)


def from_frame(points: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """Inverse of :func:`to_frame`."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.asarray(points, dtype=np.float64)
    return np.stack([c * p[..., 0] - s * p[..., 1] + x, s * p[..., 0] + c * p[..., 1] + y], axis=-1)


def offset(line: np.ndarray, distance) -> np.ndarray:
    """Offset a polyline sideways by ``distance`` metres (positive = to the left of travel); or (m, L, 2) polylines
    of one vertex count, each by its own of ``distance`` (m,) (:func:`equal_count_batches`), the same numbers.

    Uses per-vertex normals averaged over neighbouring segments (good for gently curved lines;
    use shapely's ``offset_curve`` where corners are sharp).
    """
    d = np.gradient(line, axis=-2)
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    normal = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return line + np.asarray(distance)[..., None, None] * normal


def equal_count_batches(lines, size: int = 4096):
    """(indices, (m, L, 2) array) of ``lines`` of equal vertex counts L, at most ``size`` at a time: for computing on
    many lines at once with the same floating-point operations as on each alone."""
    count = np.array([len(line) for line in lines])
    for m in np.unique(count).tolist():
        which = np.flatnonzero(count == m).tolist()
        for start in range(0, len(which), size):
            yield which[start:start + size], np.stack([lines[k] for k in which[start:start + size]])


def insert_vertex(line: np.ndarray, point: np.ndarray, snap: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """``line`` with the point of it nearest ``point`` as a vertex (an existing vertex within ``snap``
    is used instead, and ``point`` itself when it lies within ``snap`` of the line, so that two lines
    given the same point share it exactly); returns (new line, that vertex)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.clip(np.sum((point - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-18), 0.0, 1.0)
    foot = a + t[:, None] * ab
    k = int(np.argmin(np.linalg.norm(foot - point, axis=1)))
    p = point.astype(np.float64) if np.linalg.norm(foot[k] - point) <= snap else foot[k]
    for v in (k, k + 1):
        if np.linalg.norm(line[v] - p) <= snap:
            return line, line[v].copy()
    return np.concatenate([line[:k + 1], p[None], line[k + 1:]]), p


def rounded_corners(line: np.ndarray, radius: float, step_deg: float = 10.0) -> np.ndarray:
    """``line`` with each interior vertex replaced by a circular arc of ``radius`` tangent to its two segments (a
    smaller one where the segments are too short: each gives at most half its length to each arc), a point every
    ``step_deg`` of it; the ends stay."""
    out = [line[0]]
    for k in range(1, len(line) - 1):
        u1, u2 = line[k] - line[k - 1], line[k + 1] - line[k]
        l1, l2 = float(np.linalg.norm(u1)), float(np.linalg.norm(u2))
        if l1 < 1e-9 or l2 < 1e-9:
            continue
        u1, u2 = u1 / l1, u2 / l2
        turn = math.atan2(u1[0] * u2[1] - u1[1] * u2[0], float(u1 @ u2))
        if abs(turn) < 1e-3 or abs(turn) > math.pi - 1e-3:
            out.append(line[k])
            continue
        t = min(radius * math.tan(abs(turn) / 2.0), l1 / 2.0, l2 / 2.0)
        r = t / math.tan(abs(turn) / 2.0)
        start = line[k] - t * u1
        normal = np.array([-u1[1], u1[0]]) * math.copysign(1.0, turn)  # towards the centre
        centre = start + r * normal
        a0 = math.atan2(*(start - centre)[::-1])
        n = max(2, int(math.ceil(math.degrees(abs(turn)) / step_deg)) + 1)
        angles = a0 + np.linspace(0.0, turn, n)
        out.extend(centre + r * np.stack([np.cos(angles), np.sin(angles)], axis=1))
    out.append(line[-1])
    return np.array(out)


def moved_start(points: np.ndarray, to: np.ndarray, fade_m: float) -> np.ndarray:
    """``points`` with its first point moved to ``to``, the move fading linearly to none ``fade_m`` along it, or at
    its other end if that comes first (so a join bends a lane without a kink and leaves its other end in place)."""
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    weight = np.clip(1.0 - along / max(min(fade_m, along[-1]), 1e-9), 0.0, 1.0)[:, None]
    moved = points + weight * (to - points[0])
    moved[0] = to
    return moved


def padded(lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lines of different vertex counts as one (m, L, 2) array, each padded with copies of its last point, and their
    vertex counts: for computing on many lines at once."""
    count = np.array([len(line) for line in lines])
    out = np.repeat(np.array([line[-1] for line in lines])[:, None], count.max(), axis=1)
    for k, line in enumerate(lines):
        out[k, :len(line)] = line
    return out, count
