"""The smallest turn radius along a line, as the validity check's kink test and the rules' connectors measure it."""

from __future__ import annotations

import numpy as np

from cmtool.core.geometry import padded

STEP_M = 0.01  # vertices closer than this to the one before carry no direction
CHUNK_LINES = 2_048  # lines per batch of padded arrays


def min_radii(lanes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each lane's smallest turn radius and where it lies (:func:`_min_radius`), lanes of similar vertex counts
    in batches of padded arrays, so a map of 100,000 lanes takes a loop over vertex positions, not over lanes."""
    radius, where = np.full(len(lanes), np.inf), np.array([lane[0] for lane in lanes])
    order = sorted(range(len(lanes)), key=lambda k: len(lanes[k]))
    for start in range(0, len(order), CHUNK_LINES):
        batch = order[start:start + CHUNK_LINES]
        r, w = _min_radius(*padded([lanes[k] for k in batch]))
        radius[batch] = r
        where[batch] = np.where(np.isfinite(r)[:, None], w, where[batch])
    return radius, where


def _min_radius(p: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest turn radius along each padded line (``p``: (m, L, 2), ``count`` vertices each) and the vertex where
    it lies: at each vertex, the mean length of its two segments (the shorter one at a corner) over the angle it
    turns by, on the vertices thinned to at least 2 m apart with corners (turns over 45 degrees) always kept, so
    sparse and dense samplings of one curve measure alike and a corner reads as sharp however long its sides."""
    corner = np.radians(45.0)
    p, count = _thinned(p, count, 2.0, corner)
    turn, seg = _turns(p)
    legs = np.where(turn > corner, np.minimum(seg[:, :-1], seg[:, 1:]), (seg[:, :-1] + seg[:, 1:]) / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(turn > 1e-9, legs / turn, np.inf)
    radius[np.arange(radius.shape[1])[None, :] >= count[:, None] - 2] = np.inf  # past each line's last corner
    k = np.argmin(radius, axis=1) if radius.shape[1] else np.zeros(len(p), int)
    rows = np.arange(len(p))
    return (radius[rows, k] if radius.shape[1] else np.full(len(p), np.inf)), p[rows, np.minimum(k + 1, p.shape[1] - 1)]


def _turns(line: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angle each interior vertex of (m, L, 2) lines turns by, (m, L - 2), and the segment lengths."""
    d = np.diff(line, axis=1)
    seg = np.linalg.norm(d, axis=2)
    cos = np.einsum("mij,mij->mi", d[:, :-1], d[:, 1:]) / np.maximum(seg[:, :-1] * seg[:, 1:], 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0)), seg


def _thinned(line: np.ndarray, count: np.ndarray, spacing: float, corner: float) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of padded lines with each kept one at least ``spacing`` from the one before, except that
    vertices turning by more than ``corner`` are always kept; the last vertex replaces a kept one closer than that.
    Steps under ``STEP_M`` go first: they have no direction worth measuring, and rounding a file's coordinates to
    the millimetre must not change the judgement."""
    line, count = _spaced(line, count, STEP_M, np.zeros(line.shape[:2], bool))
    sharp = np.zeros(line.shape[:2], bool)
    if line.shape[1] >= 3:
        sharp[:, 1:-1] = _turns(line)[0] > corner
    sharp[np.arange(len(line)), count - 1] = False
    return _spaced(line, count, spacing, sharp)


def _spaced(line: np.ndarray, count: np.ndarray, spacing: float, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of padded lines at least ``spacing`` from the one kept before, and those ``kept`` marks; the last
    vertex replaces a kept one closer than that (unless marked). Returns the lines compacted (padded with their last
    point) and their new vertex counts. Lines whose vertices all lie ``spacing`` apart keep them all; the others are
    walked vertex by vertex, together."""
    rows = np.arange(len(line))
    keep = np.arange(line.shape[1])[None, :] < count[:, None]
    loose = np.flatnonzero(np.any(keep[:, 1:] & (np.linalg.norm(np.diff(line, axis=1), axis=2) < spacing), axis=1))
    walk, marked, inside = line[loose], keep[loose] & kept[loose], keep[loose]
    taken, at, walking = np.zeros_like(inside), np.zeros(len(loose), int), np.arange(len(loose))
    taken[:, 0] = True
    for i in range(1, line.shape[1] if len(loose) else 1):
        step = walk[:, i] - walk[walking, at]  # from the last vertex kept; its length as np.linalg.norm takes it
        taken[:, i] = take = marked[:, i] | (inside[:, i] & (np.sqrt(np.square(step).sum(axis=1)) >= spacing))
        at[take] = i
    keep[loose], last = taken, count - 1
    last[loose] = at
    end, short = count - 1, last != count - 1
    replace = short & (keep.sum(axis=1) > 1) & ~kept[rows, last]
    keep[rows[replace], last[replace]] = False
    keep[rows[short], end[short]] = True
    order = np.argsort(~keep, axis=1, kind="stable")
    out = np.take_along_axis(line, order[:, :, None], axis=1)
    new_count = keep.sum(axis=1)
    pad = np.arange(line.shape[1])[None, :] >= new_count[:, None]
    out[pad] = np.repeat(out[rows, new_count - 1], line.shape[1] - new_count, axis=0)
    return out, new_count
