"""Pictures of scenes for people: lane panels coloured by direction, SD raster panels, tile grids.

All panels follow the raster convention (docs/data.md: "Frames and rasters"): forward is up, left is left. Lane colour
is the lane's local heading in the ego frame as a hue (forward red, left green-yellow, backward
cyan, right violet; see :func:`heading_colours`), so opposite directions of one road stand apart.
Images are RGB uint8.
"""

from __future__ import annotations

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
    img = np.full((size, size, 3), BACKGROUND, np.uint8)
    fm = frame_m
    scale = size / fm
    bands = img.copy()
    stops = []
    for lights, colour in ((green, GREEN), (red, RED)):
        for line in lights:
            pix = _pix(line, size, fm)
            cv2.polylines(bands, [pix.reshape(-1, 1, 2)], False, colour, max(3, int(round(2.2 * scale))),
                          cv2.LINE_AA, CV_SHIFT)
            stops.append((tuple(pix[0]), colour))
    img = cv2.addWeighted(bands, 0.55, img, 0.45, 0.0)
    lines = [np.asarray(l, np.float64) for l in lines]
    lw = max(1, int(round(0.5 * scale)))
    for line in lines:
        d = np.diff(line, axis=0)
        colours = heading_colours(np.arctan2(d[:, 1], d[:, 0]))
        pix = _pix(line, size, fm)
        for k in range(len(d)):
            c = tuple(int(v) for v in colours[k])
            cv2.line(img, tuple(pix[k]), tuple(pix[k + 1]), c, lw, cv2.LINE_AA, CV_SHIFT)
        cv2.circle(img, tuple(pix[0]), int(1.2 * scale) << CV_SHIFT, (200, 200, 200), -1, cv2.LINE_AA, CV_SHIFT)
        tip, tail = line[-1], line[-1] - 2.5 * _unit(line[-1] - line[max(-3, -len(line))])
        cv2.arrowedLine(img, tuple(_pix(tail, size, fm)), tuple(_pix(tip, size, fm)), tuple(int(v) for v in colours[-1]),
                        lw, cv2.LINE_AA, CV_SHIFT, tipLength=0.8)
    for i, j in edges:
        a, b = lines[i][max(-3, -len(lines[i]))], lines[j][min(2, len(lines[j]) - 1)]
        cv2.arrowedLine(img, tuple(_pix(a, size, fm)), tuple(_pix(b, size, fm)), (255, 255, 255), 1, cv2.LINE_AA,
                        CV_SHIFT, tipLength=0.35)
    for centre, colour in stops:  # a lamp where each light line starts (at its stop line)
        cv2.circle(img, centre, int(1.3 * scale) << CV_SHIFT, (255, 255, 255), -1, cv2.LINE_AA, CV_SHIFT)
        cv2.circle(img, centre, int(0.9 * scale) << CV_SHIFT, colour, -1, cv2.LINE_AA, CV_SHIFT)
    if ego:
        triangle = np.array([[2.5, 0.0], [-1.5, 1.5], [-1.5, -1.5]])
        cv2.fillPoly(img, [_pix(triangle, size, fm).reshape(-1, 1, 2)], (255, 255, 255), cv2.LINE_AA, CV_SHIFT)
    return img


def sd_panel(sd: np.ndarray, size: int = 256) -> np.ndarray:
    """The SD raster made readable: roads grey (brighter with more lanes, mid grey when the lane
    count is unknown), one-way roads in the hue of their travel direction."""
    dec = decode_sd(sd)
    road, lanes = dec["road"], dec["lanes"]
    grey = np.where(lanes > 0, 70 + 25 * np.clip(lanes, 0, 7), 130).astype(np.uint8)
    img = np.full(road.shape + (3,), BACKGROUND, np.uint8)
    img[road] = grey[road][:, None]
    oneway = ~np.isnan(dec["heading"])
    img[oneway] = heading_colours(dec["heading"][oneway])
    return cv2.resize(img, (size, size), interpolation=cv2.INTER_NEAREST)


def title_strip(text: str, width: int, height: int = 22) -> np.ndarray:
    img = np.full((height, width, 3), (48, 48, 56), np.uint8)
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
