"""The HD raster (RVAE input, docs/data.md: "Frames and rasters"): scene vectors drawn as direction-coded lines.

Six channels, in pairs: lanes, green-light lines, red-light lines. Every pixel a line covers
carries its local heading h (ego frame) as ``0.5 * (cos h, sin h) + 0.5``; the background is 0.
Row 0 is the front edge (x = +frame/2), column 0 the left edge (y = +frame/2). Drawing is per
segment with OpenCV (sub-pixel end points), so a scene takes well under a millisecond at 128 px.
"""

from __future__ import annotations

import cv2
import numpy as np

from cmtool.core.geometry import CV_SHIFT, ego_to_pixel


def _segments(lines: np.ndarray, px_m: float, frame_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The drawn segments of polylines (N, P, 2) in drawing order (those of no length left out): their start and end
    pixels (S, 2) in OpenCV fixed point and their colours (S, 2) float64, the encoded heading."""
    lines = np.asarray(lines, dtype=np.float64)
    d = np.diff(lines, axis=1)
    h = np.arctan2(d[..., 1], d[..., 0])
    colour = 0.5 * np.stack([np.cos(h), np.sin(h)], axis=-1) + 0.5
    pix = ego_to_pixel(lines, px_m, frame_m)
    n, k = np.nonzero(np.linalg.norm(d, axis=-1) > 1e-9)
    return pix[n, k], pix[n, k + 1], colour[n, k]


def draw_direction_lines(canvas: np.ndarray, lines: np.ndarray, px_m: float, frame_m: float,
                         thickness: int) -> None:
    """Draw polylines (N, P, 2) into an (H, W, 2) float32 canvas, colour = encoded heading."""
    if len(lines) == 0:
        return
    for a, b, c in zip(*(part.tolist() for part in _segments(lines, px_m, frame_m))):
        cv2.line(canvas, a, b, c, thickness, cv2.LINE_8, CV_SHIFT)


def _channels(lines, line_mask, green, green_mask, red, red_mask) -> list[np.ndarray]:
    return [np.asarray(v)[np.asarray(m, bool)] for v, m in ((lines, line_mask), (green, green_mask), (red, red_mask))]


def _geometry(px_m: float, frame_m: float, width_m: float) -> tuple[int, int]:
    return int(round(frame_m / px_m)), max(1, int(round(width_m / px_m)))


def rasterize_scene(lines, line_mask, green, green_mask, red, red_mask, px_m: float = 0.5,
                    frame_m: float = 64.0, width_m: float = 1.0) -> np.ndarray:
    """Scene vectors -> float32 (6, H, W) HD raster, H = W = frame_m / px_m.

    ``width_m`` is the drawn line width (at least one pixel).
    """
    size, thickness = _geometry(px_m, frame_m, width_m)
    out = np.zeros((3, size, size, 2), np.float32)
    for c, vecs in enumerate(_channels(lines, line_mask, green, green_mask, red, red_mask)):
        draw_direction_lines(out[c], vecs, px_m, frame_m, thickness)
    return out.transpose(0, 3, 1, 2).reshape(6, size, size)


def drawn_pixels(lines, line_mask, green, green_mask, red, red_mask, px_m: float = 0.5, frame_m: float = 64.0,
                 width_m: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`rasterize_scene` draws, as its covered pixels: their flat indices (N,) int32 into the raster's
    first channel of their pair, and their two values (N, 2) float32 (those of the segment drawn over them last)."""
    size, thickness = _geometry(px_m, frame_m, width_m)
    ids = np.zeros((3, size, size), np.float32)  # segment + 1, exact in float32 below 2**24 segments
    colours = [np.zeros((1, 2))]
    for c, vecs in enumerate(_channels(lines, line_mask, green, green_mask, red, red_mask)):
        if len(vecs):
            starts, ends, colour = _segments(vecs, px_m, frame_m)
            for k, (a, b) in enumerate(zip(starts.tolist(), ends.tolist()), start=sum(map(len, colours))):
                cv2.line(ids[c], a, b, k, thickness, cv2.LINE_8, CV_SHIFT)
            colours.append(colour)
    covered = np.flatnonzero(ids)
    channel, place = np.divmod(covered, size * size)
    values = np.concatenate(colours)[ids.reshape(-1)[covered].astype(np.int64)].astype(np.float32)
    return (2 * channel * size * size + place).astype(np.int32), values


def raster_from_pixels(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """The (6, size, size) float32 raster of :func:`drawn_pixels`' record: equal to :func:`rasterize_scene`'s."""
    out = np.zeros(6 * size * size, np.float32)
    out[index] = values[:, 0]
    out[index + size * size] = values[:, 1]
    return out.reshape(6, size, size)
