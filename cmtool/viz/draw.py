"""Pictures of scenes for people: lane panels coloured by direction, SD raster panels, tile grids.

All panels follow the raster convention (docs/data.md: "Frames and rasters"): forward is up, left is left. Lane colour
is the lane's local heading in the ego frame as a hue (forward red, left green-yellow, backward
cyan, right violet; see :func:`heading_colours`), so opposite directions of one road stand apart.
Images are RGB uint8.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from cmtool.core.geometry import CV_SHIFT, ego_to_pixel
from cmtool.data.sd_raster import decode_sd

BACKGROUND = (24, 24, 28)
GREEN = (40, 200, 80)
RED = (230, 50, 50)
TEXT = (235, 235, 235)


def heading_colours(h) -> np.ndarray:
    """Headings (radians, ego frame) -> RGB uint8 (..., 3): hue = heading, full saturation."""
    h = np.asarray(h, dtype=np.float64)
    if h.size == 0:
        return np.zeros(h.shape + (3,), np.uint8)
    hue = np.round((np.mod(h, 2 * np.pi) / (2 * np.pi)) * 180.0).astype(np.uint8) % 180
    hsv = np.stack([hue, np.full_like(hue, 230), np.full_like(hue, 255)], axis=-1).reshape(-1, 1, 3)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).reshape(*h.shape, 3)


def _pix(points: np.ndarray, size: int, frame_m: float) -> np.ndarray:
    """Ego metres -> fixed-point pixel (col, row) for a ``size`` px panel."""
    return ego_to_pixel(points, frame_m / size, frame_m)


@lru_cache(maxsize=16)
def _blank(height: int, width: int, colour: tuple[int, int, int]) -> np.ndarray:
    """A picture of one colour, to copy (filling one anew takes up to a hundred times longer)."""
    return np.full((height, width, 3), colour, np.uint8)


def lanes_panel(scene, size: int = 256) -> np.ndarray:
    """The HD vectors of a :class:`~cmtool.data.scene.Scene` (see :func:`lanes_image`)."""
    return lanes_image(scene.lines[scene.line_mask], scene.green[scene.green_mask], scene.red[scene.red_mask],
                       scene.edges, scene.frame_m, size)


def graph_panel(graph, size: int = 256) -> np.ndarray:
    """The lanes of a :class:`~cmtool.maps.lanegraph.LaneGraph` (see :func:`lanes_image`)."""
    return lanes_image(graph.lanes, graph.green_lights, graph.red_lights, graph.successors, graph.frame_m, size)


def lanes_image(lines, green, red, edges, frame_m: float = 64.0, size: int = 256, ego: bool = True) -> np.ndarray:
    """HD vectors in ego metres: light lines (wide green / red bands, a lamp where each starts)
    under direction-coloured lanes with a dot at each lane start, an arrow head at each end, white
    successor arrows across joints and (``ego``) the ego as a white triangle."""
    img = _blank(size, size, BACKGROUND).copy()
    fm = frame_m
    scale = size / fm
    bands = img.copy()
    stops = []
    for lights, colour in ((green, GREEN), (red, RED)):
        pix = [_pix(line, size, fm) for line in lights]
        if pix:  # one call draws them all, one after the other
            cv2.polylines(bands, [p.reshape(-1, 1, 2) for p in pix], False, colour, max(3, int(round(2.2 * scale))),
                          cv2.LINE_AA, CV_SHIFT)
        stops += [(tuple(p[0].tolist()), colour) for p in pix]
    if stops:  # (the background blended with itself stays as it is)
        img = cv2.addWeighted(bands, 0.55, img, 0.45, 0.0)
    lines = [np.asarray(l, np.float64) for l in lines]
    if lines:
        _draw_lanes(img, lines, edges, fm, size)
    for centre, colour in stops:  # a lamp where each light line starts (at its stop line)
        cv2.circle(img, centre, int(1.3 * scale) << CV_SHIFT, (255, 255, 255), -1, cv2.LINE_AA, CV_SHIFT)
        cv2.circle(img, centre, int(0.9 * scale) << CV_SHIFT, colour, -1, cv2.LINE_AA, CV_SHIFT)
    if ego:
        triangle = np.array([[2.5, 0.0], [-1.5, 1.5], [-1.5, -1.5]])
        cv2.fillPoly(img, [_pix(triangle, size, fm).reshape(-1, 1, 2)], (255, 255, 255), cv2.LINE_AA, CV_SHIFT)
    return img


def _draw_lanes(img: np.ndarray, lines: list[np.ndarray], edges, fm: float, size: int) -> None:
    """The lanes of :func:`lanes_image` (float64 polylines) and their successor arrows, all converted to pixels and
    colours in one go."""
    scale = size / fm
    lw = max(1, int(round(0.5 * scale)))
    ends = np.cumsum([len(l) for l in lines])
    starts = ends - [len(l) for l in lines]
    points = np.concatenate(lines)
    d = np.diff(points, axis=0)  # segment k runs from point k to k + 1 (those across two lanes go unused)
    colours = heading_colours(np.arctan2(d[:, 1], d[:, 0]))
    pix = _pix(points, size, fm)
    tails = [l[-1] - 2.5 * _unit(l[-1] - l[max(-3, -len(l))]) for l in lines]
    tails = list(map(tuple, _pix(np.array(tails), size, fm).tolist()))
    points, colours = list(map(tuple, pix.tolist())), list(map(tuple, colours.tolist()))
    for a, b, tail in zip(starts.tolist(), (ends - 1).tolist(), tails):
        for k in range(a, b):
            cv2.line(img, points[k], points[k + 1], colours[k], lw, cv2.LINE_AA, CV_SHIFT)
        cv2.circle(img, points[a], int(1.2 * scale) << CV_SHIFT, (200, 200, 200), -1, cv2.LINE_AA, CV_SHIFT)
        cv2.arrowedLine(img, tail, points[b], colours[b - 1], lw, cv2.LINE_AA, CV_SHIFT, tipLength=0.8)
    for i, j in edges:
        tail, tip = points[ends[i] + max(-3, -len(lines[i]))], points[starts[j] + min(2, len(lines[j]) - 1)]
        cv2.arrowedLine(img, tail, tip, (255, 255, 255), 1, cv2.LINE_AA, CV_SHIFT, tipLength=0.35)


def sd_panel(sd: np.ndarray, size: int = 256) -> np.ndarray:
    """The SD raster made readable: roads grey (brighter with more lanes, mid grey when the lane
    count is unknown), one-way roads in the hue of their travel direction."""
    colour = np.where(sd[..., 2] > 0, sd[..., 2].astype(np.uint16) + 256, sd[..., 1])  # a row of _sd_colours
    colour[sd[..., 0] == 0] = 512
    return cv2.resize(np.take(_sd_colours(), colour, axis=0), (size, size), interpolation=cv2.INTER_NEAREST)


@lru_cache(maxsize=1)
def _sd_colours() -> np.ndarray:
    """(513, 3) uint8 colours of :func:`sd_panel`: a road pixel's by its G value (rows 0-255, grey by
    :func:`decode_sd`'s lane count), a one-way road pixel's by its B value (rows 256-511, the hue of its heading),
    the background (row 512)."""
    values = np.arange(256, dtype=np.uint8)
    dec = decode_sd(np.stack([np.full(256, 255, np.uint8), values, values], axis=-1))
    grey = np.where(dec["lanes"] > 0, 70 + 25 * np.clip(dec["lanes"], 0, 7), 130).astype(np.uint8)
    hue = heading_colours(np.nan_to_num(dec["heading"]))
    return np.concatenate([np.repeat(grey[:, None], 3, axis=1), hue, [BACKGROUND]]).astype(np.uint8)


def title_strip(text: str, width: int, height: int = 22) -> np.ndarray:
    img = _blank(height, width, (48, 48, 56)).copy()
    scale = 0.45
    while cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > width - 8 and len(text) > 4:
        text = text[:-4] + "..."
    cv2.putText(img, text, (5, height - 7), cv2.FONT_HERSHEY_SIMPLEX, scale, TEXT, 1, cv2.LINE_AA)
    return img


def grid(tiles: list[np.ndarray], columns: int, gap: int = 6) -> np.ndarray:
    """Lay equally sized tiles out in rows of ``columns`` with a gap between them."""
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    out = np.full((rows * (h + gap) + gap, columns * (w + gap) + gap, 3), 12, np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, columns)
        out[gap + r * (h + gap): gap + r * (h + gap) + h, gap + c * (w + gap): gap + c * (w + gap) + w] = tile
    return out


def legend(width: int, row: int = 40) -> np.ndarray:
    """A strip explaining the colours: a hue wheel for lane heading (forward = up) and swatches,
    wrapped onto more rows of ``row`` px when ``width`` is too narrow for one."""
    return _legend(width, row).copy()


@lru_cache(maxsize=8)
def _legend(width: int, row: int) -> np.ndarray:
    """:func:`legend`, drawn once per size."""
    r = row // 2 - 3
    items = [("lane colour = heading (up: forward)", None), ("green light", GREEN), ("red light", RED),
             ("successor", (255, 255, 255)), ("SD: grey road (brighter = more lanes), colour = one-way", None)]
    placed, x, y = [], 2 * r + 14, 0
    for text, colour in items:
        w = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)[0][0] + (24 if colour is not None else 0)
        if x + w > width and x > 2 * r + 14:
            x, y = 2 * r + 14, y + 1
        placed.append((text, colour, x, y))
        x += w + 22
    img = np.full(((y + 1) * row, width, 3), (12, 12, 12), np.uint8)
    cx = cy = row // 2
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    inside = (xx ** 2 + yy ** 2 <= r * r) & (xx ** 2 + yy ** 2 >= (r // 3) ** 2)
    wheel = heading_colours(np.arctan2(-xx, -yy))  # up = forward (+x), left = +y
    img[cy - r: cy + r + 1, cx - r: cx + r + 1][inside] = wheel[inside]
    for text, colour, x, line in placed:
        mid = line * row + cy
        if colour is not None:
            cv2.line(img, (x, mid), (x + 18, mid), colour, 4, cv2.LINE_AA)
            x += 24
        cv2.putText(img, text, (x, mid + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TEXT, 1, cv2.LINE_AA)
    return img


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.array([1.0, 0.0])
