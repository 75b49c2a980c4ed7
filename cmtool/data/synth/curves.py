"""Polyline pieces for road axes and connectors: arc-length cuts, tangents, bends and Bezier curves."""

from __future__ import annotations

import numpy as np

from cmtool.core.geometry import arc_length, unit


def cut(line: np.ndarray, s0: float, s1: float, eps: float = 0.1) -> np.ndarray:
    """The part of ``line`` between arc lengths ``s0 < s1``; vertices closer than ``eps`` to a cut
    point are dropped so the end segments keep a well-defined direction."""
    cum = arc_length(line)
    ends = np.stack([np.interp([s0, s1], cum, line[:, 0]), np.interp([s0, s1], cum, line[:, 1])], axis=1)
    inner = line[(cum > s0 + eps) & (cum < s1 - eps)]
    return np.concatenate([ends[:1], inner, ends[1:]])


def point_and_tangent(line: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Point at arc length ``s`` and the unit direction of the segment it lies on."""
    cum = arc_length(line)
    k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(line) - 2))
    d = line[k + 1] - line[k]
    p = np.array([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])])
    return p, d / np.linalg.norm(d)


def end_tangents(line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions of the first and the last segment."""
    return unit(line[1] - line[0]), unit(line[-1] - line[-2])


def bend(line: np.ndarray, amplitude: float) -> np.ndarray:
    """Displace ``line`` sideways by ``amplitude * sin^2(pi s / L)``: zero displacement and zero slope
    at both ends, so the road still meets its nodes head-on."""
    cum = arc_length(line)
    chord = unit(line[-1] - line[0])
    normal = np.array([-chord[1], chord[0]])
    return line + amplitude * np.sin(np.pi * cum / cum[-1])[:, None] ** 2 * normal


def bezier(p0, p1, p2, p3, n: int) -> np.ndarray:
    """Cubic Bezier curve through ``n`` parameter steps (end points exact)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    u = 1.0 - t
    return u**3 * p0 + 3 * u**2 * t * p1 + 3 * u * t**2 * p2 + t**3 * p3


def hermite(p0: np.ndarray, d0: np.ndarray, p1: np.ndarray, d1: np.ndarray, step: float = 2.0) -> np.ndarray:
    """Smooth curve from ``p0`` leaving along unit ``d0`` to ``p1`` arriving along unit ``d1``.

    Where the two lines meet at a corner ahead, the curve is the widest round turn that fits: straight
    along the longer leg until both legs are equal, then a cubic Bezier approximating a circular arc.
    Otherwise (an S-bend) the Bezier's handles follow the chord. Points about every ``step`` metres.
    """
    turn = min(float(np.arccos(np.clip(np.dot(d0, d1), -1.0, 1.0))), np.radians(170.0))
    corner = _corner(p0, d0, p1, d1) if turn > np.radians(10.0) else None
    if corner is None:
        chord = float(np.linalg.norm(p1 - p0))
        k = chord / 3 if turn < 1e-3 else chord * (2 / 3) * np.tan(turn / 4) / np.sin(turn / 2)
        return _sampled([p0], p0, p0 + k * d0, p1 - k * d1, p1, [p1], step)
    leg = min(corner)
    q0, q1 = p0 + (corner[0] - leg) * d0, p1 - (corner[1] - leg) * d1
    k = leg * (4 / 3) * np.tan(turn / 4) / np.tan(turn / 2)
    return _sampled(_straight(p0, q0, step), q0, q0 + k * d0, q1 - k * d1, q1, _straight(p1, q1, step)[::-1], step)


def _straight(a: np.ndarray, b: np.ndarray, step: float) -> list[np.ndarray]:
    """Points from ``a`` towards ``b`` (``b`` excluded) about every ``step`` metres."""
    n = int(np.ceil(np.linalg.norm(b - a) / step))
    return [a + (b - a) * i / n for i in range(n)]


def _sampled(head, c0, c1, c2, c3, tail, step: float) -> np.ndarray:
    """``head`` points, then the Bezier ``c0..c3``, then ``tail`` points, without repeated points."""
    n = max(6, int(np.ceil(float(np.linalg.norm(c1 - c0) + np.linalg.norm(c2 - c1) + np.linalg.norm(c3 - c2))
                           / step)) + 1)
    pts = np.concatenate([np.reshape(head, (-1, 2)), bezier(c0, c1, c2, c3, n), np.reshape(tail, (-1, 2))])
    keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]
    return pts[keep]


def _corner(p0, d0, p1, d1) -> tuple[float, float] | None:
    """Distances from ``p0`` forward along ``d0`` and back from ``p1`` along ``d1`` to where the two
    lines meet, or None when they do not meet ahead of ``p0`` and behind ``p1``."""
    a = np.array([d0, d1]).T
    if abs(np.linalg.det(a)) < 1e-9:
        return None
    t0, t1 = np.linalg.solve(a, p1 - p0)
    return (float(t0), float(t1)) if t0 > 0 and t1 > 0 else None


def round_corner(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """Join ``a`` (ending at the corner) and ``b`` (starting there), rounding the corner with a
    quadratic Bezier that starts ``radius`` metres before it and ends ``radius`` metres after."""
    la, lb = arc_length(a)[-1], arc_length(b)[-1]
    r = min(radius, 0.3 * la, 0.3 * lb)
    head, tail = cut(a, 0.0, la - r), cut(b, r, lb)
    t = np.linspace(0.0, 1.0, 7)[1:-1, None]
    corner = (1 - t) ** 2 * head[-1] + 2 * (1 - t) * t * a[-1] + t**2 * tail[0]
    return np.concatenate([head, corner, tail])
