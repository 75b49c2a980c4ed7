"""An SD map traced from a picture of roads larger than one frame (``cmtool sample --sd PICTURE --area``): a road
drawing, or a picture in the SD raster's colours (:mod:`cmtool.data.sd_raster`), north up, ``px_m`` metres a pixel.

The road pixels are thinned to lines one pixel wide (Zhang and Suen's thinning); pixels where the lines meet or end
are nodes (touching ones one node, at their mean); the lines between nodes become roads, in metres east and north
of the picture's centre. Spurs of the thinning (a line from a node to an end shorter than ``SPUR_WIDTHS`` road
widths) are dropped, and nodes closer than a road width are one. In the SD raster's colours a road takes its lane
count (G) and, where most of its pixels say one-way (B), its direction: the picture's up is north, as a raster's up
is ahead.
"""

from __future__ import annotations

import cv2
import numpy as np
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.data.sd_raster import LANE_STEP, ROAD_VALUE, decode_direction, drawing_roads, picture
from cmtool.maps.sdmap import Road, SDMap

SPUR_WIDTHS = 2.0  # a dead-end line shorter than this many road widths is a spur of the thinning
SIMPLIFY_PX = 0.7  # traced lines are simplified to within this many pixels
_RING = [(-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1)]  # P2 .. P9, clockwise from up


def trace_sd(path, px_m: float = 0.5, city: str | None = None) -> SDMap:
    """The SD map of the roads in the picture at ``path`` (module doc)."""
    if not px_m > 0:
        raise CmtoolError(f"--px-m {px_m}: must be a positive number of metres")
    img, coloured = picture(path)
    return trace_picture(img, coloured, px_m, city, path)


def trace_picture(img: np.ndarray, coloured: bool, px_m: float, city: str | None = None, path="picture") -> SDMap:
    """The SD map of the roads in a picture array (``coloured``: in the SD raster's colours, else a road drawing),
    named ``path`` in messages."""
    mask = (img[..., 0] == ROAD_VALUE).astype(np.uint8) if coloured else drawing_roads(img)
    if mask is None or not mask.any():
        raise CmtoolError(f"{path}: no roads in the picture (draw roads light on dark or dark on light)")
    width = 2.0 * float(cv2.distanceTransform(mask, cv2.DIST_L2, 3).max())  # the widest road, pixels
    lines = _tidy(_lines(_thin(mask)), width)
    roads = []
    h, w = mask.shape
    for k, line in enumerate(lines):
        simple = shapely.get_coordinates(shapely.LineString(line[:, ::-1]).simplify(SIMPLIFY_PX))  # (col, row)
        if len(simple) < 2 or shapely.length(shapely.LineString(simple)) < 1.0:  # a link of two touching nodes
            continue
        metres = np.stack([(simple[:, 0] + 0.5 - w / 2.0) * px_m, (h / 2.0 - simple[:, 1] - 0.5) * px_m], axis=1)
        lanes, oneway = _attributes(img, line) if coloured else (None, 0)
        roads.append(Road(f"d{k}", metres, lanes=lanes, oneway=oneway))
    if not roads:
        raise CmtoolError(f"{path}: no road lines could be traced in the picture")
    return SDMap(city=city, roads=roads, source=f"drawing:{path}", meta={"px_m": px_m})


def _thin(mask: np.ndarray) -> np.ndarray:
    """Zhang and Suen's thinning of a 0/1 mask to lines one pixel wide."""
    img = np.pad(mask.astype(np.uint8), 1)
    while True:
        changed = False
        for first in (True, False):
            p = [np.roll(img, (-dr, -dc), axis=(0, 1)) for dr, dc in _RING]  # p[k][r, c] = img[r + dr, c + dc]
            neighbours = sum(p)
            rises = sum(((p[k] == 0) & (p[(k + 1) % 8] == 1)).astype(np.uint8) for k in range(8))
            a, b = (p[0] * p[2] * p[4], p[2] * p[4] * p[6]) if first else (p[0] * p[2] * p[6], p[0] * p[4] * p[6])
            gone = (img == 1) & (neighbours >= 2) & (neighbours <= 6) & (rises == 1) & (a == 0) & (b == 0)
            if gone.any():
                img[gone] = 0
                changed = True
        if not changed:
            return img[1:-1, 1:-1]


def _lines(skeleton: np.ndarray) -> list[np.ndarray]:
    """The lines of a skeleton between its nodes, as (row, col) pixel arrays whose ends are the nodes' means.
    Neighbouring pixels are joined, but not corner to corner where both touch a third pixel edge to edge (the step
    of a staircase): a line's pixels then have two neighbours each; a pixel with one (an end) or three or more (a
    junction) is a node, and touching node pixels are one node."""
    rows, cols = np.nonzero(skeleton)
    index = -np.ones((skeleton.shape[0] + 2, skeleton.shape[1] + 2), np.int64)
    index[rows + 1, cols + 1] = np.arange(len(rows))
    near = [[] for _ in rows]
    at = lambda dr, dc: index[rows + 1 + dr, cols + 1 + dc]  # noqa: E731
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        other = at(dr, dc)
        keep = other >= 0
        if dr and dc:  # a corner step beside an edge step is a staircase: not joined
            keep &= (at(dr, 0) < 0) & (at(0, dc) < 0)
        for i, j in zip(np.flatnonzero(keep), other[keep]):
            near[i].append(int(j))
            near[int(j)].append(int(i))
    node = np.array([len(n) != 2 for n in near], bool)
    mask = np.zeros(skeleton.shape, np.uint8)
    mask[rows[node], cols[node]] = 1
    labels = cv2.connectedComponents(mask, connectivity=8)[1][rows, cols]  # 0: not a node
    centres = {lab: np.array([rows[labels == lab].mean(), cols[labels == lab].mean()]) for lab in np.unique(labels)
               if lab}
    point = lambda i: centres[labels[i]] if labels[i] else np.array([rows[i], cols[i]], np.float64)  # noqa: E731
    done, visited, lines = set(), node.copy(), []
    for start in np.flatnonzero(node):
        for first in near[start]:
            if (start, first) in done or (labels[first] and labels[first] == labels[start]):
                continue
            path, prev, cur = [start, first], start, first
            while not node[cur]:
                visited[cur] = True
                prev, cur = cur, next(j for j in near[cur] if j != prev)
                path.append(cur)
            done |= {(start, first), (cur, prev)}
            lines.append(np.array([point(i) for i in path]))
    for start in np.flatnonzero(~visited):  # loops without a node
        if visited[start]:
            continue
        path, prev, cur = [start], None, start
        while not visited[cur]:
            visited[cur] = True
            prev, cur = cur, next(j for j in near[cur] if j != prev and (j != start or len(path) > 2))
            path.append(cur)
        if len(path) > 3:
            lines.append(np.array([point(i) for i in path]))
    return lines


def _tidy(lines: list[np.ndarray], width: float) -> list[np.ndarray]:
    """Lines without the thinning's artefacts: spurs (lines shorter than ``SPUR_WIDTHS`` road widths from a node that
    joins two or more other lines to an end that joins none) dropped, then links shorter than a road width between
    two such nodes contracted (both nodes become one, at the link's middle)."""

    def degrees(lines):
        count = {}
        for line in lines:
            for p in (line[0], line[-1]):
                count[tuple(p)] = count.get(tuple(p), 0) + 1
        return count

    def length(line):
        return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())

    count = degrees(lines)
    def spur(line):
        ends = sorted((count[tuple(line[0])], count[tuple(line[-1])]))
        return length(line) < SPUR_WIDTHS * width and ends[0] == 1 and ends[1] >= 3

    lines = [line for line in lines if not spur(line)]
    count = degrees(lines)
    moved = {}
    for line in lines:
        a, b = tuple(line[0]), tuple(line[-1])
        if a != b and length(line) < width and count[a] >= 3 and count[b] >= 3 and a not in moved and b not in moved:
            moved[a] = moved[b] = 0.5 * (line[0] + line[-1])
    out = []
    for line in lines:
        a, b = tuple(line[0]), tuple(line[-1])
        if a in moved and b in moved and np.array_equal(moved[a], moved[b]):
            continue  # the contracted link itself
        line = line.copy()
        line[0], line[-1] = moved.get(a, line[0]), moved.get(b, line[-1])
        out.append(line)
    return out


def _attributes(img: np.ndarray, line: np.ndarray) -> tuple[int | None, int]:
    """A traced road's lane count (None: unknown) and one-way direction along the line (1, -1 or 0) from the SD
    raster colours of its pixels."""
    rows, cols = np.round(line).astype(int).T
    rows, cols = rows.clip(0, img.shape[0] - 1), cols.clip(0, img.shape[1] - 1)
    g, b = img[rows, cols, 1].astype(int), img[rows, cols, 2].astype(int)
    lanes = int(np.round(np.median(g[g > 0]) / LANE_STEP)) if (g > 0).mean() > 0.5 else None
    if (b > 0).mean() <= 0.5:
        return lanes, 0
    theta = decode_direction(b[b > 0])  # 0: up (north), pi / 2: left (west)
    travel = np.array([-np.sin(theta).mean(), np.cos(theta).mean()])  # east, north
    along = np.array([line[-1, 1] - line[0, 1], line[0, 0] - line[-1, 0]])  # the line's direction, east and north
    return lanes, 1 if travel @ along >= 0 else -1
