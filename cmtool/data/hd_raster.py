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


def draw_direction_lines(canvas: np.ndarray, lines: np.ndarray, px_m: float, frame_m: float,
                         thickness: int) -> None:
    """Draw polylines (N, P, 2) into an (H, W, 2) float32 canvas, colour = encoded heading."""
    if len(lines) == 0:
        return
    lines = np.asarray(lines, dtype=np.float64)
    d = np.diff(lines, axis=1)
    h = np.arctan2(d[..., 1], d[..., 0])
    colour = 0.5 * np.stack([np.cos(h), np.sin(h)], axis=-1) + 0.5
    pix = ego_to_pixel(lines, px_m, frame_m)
    n, k = np.nonzero(np.linalg.norm(d, axis=-1) > 1e-9)
    for a, b, c in zip(pix[n, k].tolist(), pix[n, k + 1].tolist(), colour[n, k].tolist()):
        cv2.line(canvas, a, b, c, thickness, cv2.LINE_8, CV_SHIFT)


def rasterize_scene(lines, line_mask, green, green_mask, red, red_mask, px_m: float = 0.5,
                    frame_m: float = 64.0, width_m: float = 1.0) -> np.ndarray:
    """Scene vectors -> float32 (6, H, W) HD raster, H = W = frame_m / px_m.

    ``width_m`` is the drawn line width (at least one pixel).
    """
    size = int(round(frame_m / px_m))
    thickness = max(1, int(round(width_m / px_m)))
    out = np.zeros((3, size, size, 2), np.float32)
    for c, (vecs, mask) in enumerate(((lines, line_mask), (green, green_mask), (red, red_mask))):
        draw_direction_lines(out[c], np.asarray(vecs)[np.asarray(mask, bool)], px_m, frame_m, thickness)
    return out.transpose(0, 3, 1, 2).reshape(6, size, size)
