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
# a light is drawn as a bar across its lane at its stop line: half its length, half its width (metres)
LIGHT_BAR_HALF_M, LIGHT_BAR_RADIUS_M = 1.6, 0.45


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
    """HD vectors in ego metres: direction-coloured lanes with a dot at each lane start, an arrow head at each end,
    white successor arrows across joints, each light as a short green / red bar across its lane at its stop line
    (where its light line starts: :func:`light_bars`, outlined in white) and (``ego``) the ego as a white
    triangle."""
    img = _blank(size, size, BACKGROUND).copy()
    fm = frame_m
    scale = size / fm
    lines = [np.asarray(l, np.float64) for l in lines]
    if lines:
        _draw_lanes(img, lines, edges, fm, size)
    bars = [(_pix(bar, size, fm), colour) for lights, colour in ((green, GREEN), (red, RED))
            for bar in light_bars(lights)]
    thick = max(2, round(2 * LIGHT_BAR_RADIUS_M * scale))
    for (a, b), _ in bars:  # a white outline first, so that a bar stands out from a lane of its colour
        cv2.line(img, tuple(a.tolist()), tuple(b.tolist()), (255, 255, 255), thick + 2, cv2.LINE_AA, CV_SHIFT)
    for (a, b), colour in bars:
        cv2.line(img, tuple(a.tolist()), tuple(b.tolist()), colour, thick, cv2.LINE_AA, CV_SHIFT)
    if ego:
        triangle = np.array([[2.5, 0.0], [-1.5, 1.5], [-1.5, -1.5]])
        cv2.fillPoly(img, [_pix(triangle, size, fm).reshape(-1, 1, 2)], (255, 255, 255), cv2.LINE_AA, CV_SHIFT)
    return img


def light_bars(lights, half_m: float = LIGHT_BAR_HALF_M) -> np.ndarray:
    """(N, 2, 2): each light line's marker, a bar ``2 half_m`` long across its lane where the line starts (its stop
    line), square to the line's first metre."""
    lights = [np.asarray(l, np.float64).reshape(-1, 2) for l in lights]
    lights = [l for l in lights if len(l)]
    if not lights:
        return np.zeros((0, 2, 2), np.float64)
    starts = np.array([l[0] for l in lights])
    ahead = []
    for l in lights:  # the first point a metre on (or the last), for the line's direction where it starts
        far = np.flatnonzero(np.linalg.norm(l - l[0], axis=1) >= 1.0)
        ahead.append(l[far[0]] if len(far) else l[-1])
    d = np.array(ahead) - starts
    n = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(n > 1e-9, d / np.maximum(n, 1e-9), [1.0, 0.0])
    across = np.stack([-d[:, 1], d[:, 0]], axis=1) * half_m
    return np.stack([starts - across, starts + across], axis=1)


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
            if "light" in text:  # as a light is drawn: a short bar outlined in white
                cv2.line(img, (x + 2, mid), (x + 16, mid), (255, 255, 255), 6, cv2.LINE_AA)
            cv2.line(img, (x + 2, mid), (x + 16, mid), colour, 4, cv2.LINE_AA)
            x += 24
        cv2.putText(img, text, (x, mid + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TEXT, 1, cv2.LINE_AA)
    return img


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.array([1.0, 0.0])
