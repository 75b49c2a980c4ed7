"""Polyline pieces for road axes and connectors: arc-length cuts, tangents, bends and Bezier curves."""

from __future__ import annotations

import numpy as np

from cmtool.geometry import arc_length, unit


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

    The handle lengths are those of a cubic Bezier approximating a circular arc that turns by the
    angle between ``d0`` and ``d1``, so turns come out round; points about every ``step`` metres.
    """
    chord = float(np.linalg.norm(p1 - p0))
    turn = min(float(np.arccos(np.clip(np.dot(d0, d1), -1.0, 1.0))), np.radians(170.0))
    k = chord / 3 if turn < 1e-3 else chord * (2 / 3) * np.tan(turn / 4) / np.sin(turn / 2)
    n = max(6, int(np.ceil((chord + 2 * k) / step)) + 1)
    curve = bezier(p0, p0 + k * d0, p1 - k * d1, p1, n)
    curve[0], curve[-1] = p0, p1
    return curve


def round_corner(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """Join ``a`` (ending at the corner) and ``b`` (starting there), rounding the corner with a
    quadratic Bezier that starts ``radius`` metres before it and ends ``radius`` metres after."""
    la, lb = arc_length(a)[-1], arc_length(b)[-1]
    r = min(radius, 0.3 * la, 0.3 * lb)
    head, tail = cut(a, 0.0, la - r), cut(b, r, lb)
    t = np.linspace(0.0, 1.0, 7)[1:-1, None]
    corner = (1 - t) ** 2 * head[-1] + 2 * (1 - t) * t * a[-1] + t**2 * tail[0]
    return np.concatenate([head, corner, tail])
