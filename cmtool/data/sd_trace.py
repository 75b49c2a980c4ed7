"""An SD map traced from a picture of roads larger than one frame (``cmtool sample --sd PICTURE --area``): a road
drawing, or a picture in the SD raster's colours (:mod:`cmtool.data.sd_raster`), north up, ``px_m`` metres a pixel.

The road pixels are thinned to lines one pixel wide (Zhang and Suen's thinning); pixels where the lines meet or end
are nodes (touching ones one node, at their mean); the lines between nodes become roads, in metres east and north of
the picture's centre. Spurs of the thinning (a line from a node to an end shorter than ``SPUR_WIDTHS`` road widths)
are dropped, and nodes closer than a road width are one; a road end that the thinning left short of the picture's
edge (within a road width of it, heading out) goes on to the edge. In the SD raster's colours a road takes its lane
count (G), its class where most of its pixels give one (R) and, where most of its pixels say one-way (B), its
direction: the picture's up is north, as a raster's up is ahead.
"""

from __future__ import annotations

import cv2
import numpy as np
import shapely

from cmtool.core.errors import CmtoolError
from cmtool.data.sd_raster import CLASS_VALUES, LANE_STEP, decode_direction, drawing_roads, picture
from cmtool.maps.sdmap import Road, SDMap

SPUR_WIDTHS = 2.0  # a dead-end line shorter than this many road widths is a spur of the thinning
UNKNOWN_CLASS = ("residential", False)  # (class, link) of a road whose picture does not give one
SIMPLIFY_PX = 0.7  # traced lines are simplified to within this many pixels
MAX_TRACE_PIXELS = 5_000 * 5_000  # larger pictures are refused (a noisy one this size takes about a minute)
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
    if img.shape[0] * img.shape[1] > MAX_TRACE_PIXELS:
        raise CmtoolError(f"{path}: a picture of {img.shape[1]} x {img.shape[0]} pixels; roads are traced in pictures "
                          f"of up to {MAX_TRACE_PIXELS:,} pixels (5000 x 5000)")
    mask = (img[..., 0] > 0).astype(np.uint8) if coloured else drawing_roads(img)
    if mask is None or not mask.any():
        raise CmtoolError(f"{path}: no roads in the picture (draw roads light on dark or dark on light)")
    width = 2.0 * float(cv2.distanceTransform(mask, cv2.DIST_L2, 3).max())  # the widest road, pixels
    lines = _tidy(_lines(_thin(mask)), width)
    h, w = mask.shape
    shapes = shapely.simplify(shapely.linestrings(np.concatenate(lines)[:, ::-1], indices=np.repeat(
        np.arange(len(lines)), [len(line) for line in lines])), SIMPLIFY_PX) if lines else np.zeros(0, object)
    simple, which = shapely.get_coordinates(shapes, return_index=True)  # (col, row)
    metres = np.stack([(simple[:, 0] + 0.5 - w / 2.0) * px_m, (h / 2.0 - simple[:, 1] - 0.5) * px_m], axis=1)
    metres = _to_edge(np.split(metres, np.flatnonzero(np.diff(which)) + 1), (w / 2.0 * px_m, h / 2.0 * px_m),
                      width * px_m)
    roads = []
    for k in np.flatnonzero(shapely.length(shapes) >= 1.0):  # shorter: a link of two touching nodes
        lanes, oneway, (road_class, link) = _attributes(img, lines[k]) if coloured else (None, 0, UNKNOWN_CLASS)
        roads.append(Road(f"d{k}", metres[k], road_class, lanes, oneway, link))
    if not roads:
        raise CmtoolError(f"{path}: no road lines could be traced in the picture")
    return SDMap(city=city, roads=roads, source=f"drawing:{path}", meta={"px_m": px_m})


def _to_edge(lines: list[np.ndarray], half: tuple[float, float], reach: float) -> list[np.ndarray]:
    """Each line end that no other line shares and that lies within ``reach`` of the picture's edge (``half``: its
    half width and height, metres about its centre) along its heading (from the point ``reach`` back along the line:
    the thinning bends the last pixels), taken on to the edge."""
    ends = np.array([(line[0], line[-1]) for line in lines]).reshape(-1, 2)
    shared = np.unique(np.round(ends, 6), axis=0, return_counts=True)
    alone = {tuple(p) for p, n in zip(*shared) if n == 1}
    out = []
    for line in lines:
        line = line.copy()
        for end in (0, -1):
            if len(line) < 2 or tuple(np.round(line[end], 6)) not in alone:
                continue
            back = line if end == 0 else line[::-1]
            far = np.flatnonzero(np.linalg.norm(back - back[0], axis=1) >= reach)
            d = back[0] - back[far[0] if len(far) else -1]
            d = d / max(float(np.linalg.norm(d)), 1e-9)
            with np.errstate(divide="ignore", invalid="ignore"):
                steps = np.where(np.abs(d) > 1e-9, (np.sign(d) * np.array(half) - line[end]) / d, np.inf)
            step = float(np.min(steps))
            if 0.0 < step <= reach:
                tip = line[end] + step * d
                line = np.vstack([tip[None], line]) if end == 0 else np.vstack([line, tip[None]])
        out.append(line)
    return out


def _thin(mask: np.ndarray) -> np.ndarray:
    """Zhang and Suen's thinning of a 0/1 mask to lines one pixel wide. Each pass tests only the pixels beside those
    the last two passes removed (the others' tests come out as before), so the work grows with the road pixels."""
    img = np.pad(mask.astype(np.uint8), 1)
    flat, seen = img.reshape(-1), np.zeros(img.size, np.int32)
    ring = [dr * img.shape[1] + dc for dr, dc in _RING]

    def roads(idx):  # the road pixels of idx, each once
        seen[idx] = np.arange(len(idx))
        return idx[(seen[idx] == np.arange(len(idx))) & (flat[idx] == 1)]

    check, step = [np.flatnonzero(img > cv2.erode(img, np.ones((3, 3), np.uint8)))] * 2, 0  # pixels on an edge
    while len(check[0]) or len(check[1]):
        look, first = check[step % 2], step % 2 == 0
        p = np.stack([flat[look + o] for o in ring], axis=1)  # p[:, k] = img at look + _RING[k]
        neighbours, rises = p.sum(axis=1), ((p == 0) & (np.roll(p, -1, axis=1) == 1)).sum(axis=1)
        a, b = (p[:, [0, 2, 4]], p[:, [2, 4, 6]]) if first else (p[:, [0, 2, 6]], p[:, [0, 4, 6]])
        gone = look[(neighbours >= 2) & (neighbours <= 6) & (rises == 1) & (a.min(axis=1) == 0) & (b.min(axis=1) == 0)]
        flat[gone] = 0
        near = roads(np.concatenate([gone + o for o in ring]))
        check[step % 2], check[1 - step % 2] = near, roads(np.concatenate([check[1 - step % 2], near]))
        step += 1
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
    centres = np.stack([np.bincount(labels, rows), np.bincount(labels, cols)], axis=1) / np.maximum(
        np.bincount(labels), 1)[:, None]  # each node's mean
    points = np.stack([rows, cols], axis=1).astype(np.float64)  # a pixel's place, a node pixel's that of its node
    points[labels > 0] = centres[labels[labels > 0]]
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
            lines.append(points[path])
    for start in np.flatnonzero(~visited):  # loops without a node
        if visited[start]:
            continue
        path, prev, cur = [start], None, start
        while not visited[cur]:
            visited[cur] = True
            prev, cur = cur, next(j for j in near[cur] if j != prev and (j != start or len(path) > 2))
            path.append(cur)
        if len(path) > 3:
            lines.append(points[path])
    return lines


def _tidy(lines: list[np.ndarray], width: float) -> list[np.ndarray]:
    """Lines without the thinning's artefacts: spurs (lines shorter than ``SPUR_WIDTHS`` road widths from a node that
    joins two or more other lines to an end that joins none) dropped, then links shorter than a road width between
    two such nodes contracted (both nodes become one, at the link's middle)."""

    def ends(lines):  # each line's two end nodes (numbered) and the number of line ends at each node
        points = np.array([(line[0], line[-1]) for line in lines]).reshape(-1, 2)
        _, node, count = np.unique(points, axis=0, return_inverse=True, return_counts=True)
        return node.reshape(-1, 2), count

    node, count = ends(lines)
    degree, length = np.sort(count[node], axis=1), _lengths(lines)
    keep = np.flatnonzero(~((length < SPUR_WIDTHS * width) & (degree[:, 0] == 1) & (degree[:, 1] >= 3)))
    lines, length = [lines[i] for i in keep], length[keep]
    node, count = ends(lines)
    moved = {}
    for i in np.flatnonzero((node[:, 0] != node[:, 1]) & (length < width) & (count[node].min(axis=1) >= 3)):
        a, b = node[i]
        if a not in moved and b not in moved:
            moved[a] = moved[b] = 0.5 * (lines[i][0] + lines[i][-1])
    out = []
    for line, (a, b) in zip(lines, node):
        if a in moved and b in moved and np.array_equal(moved[a], moved[b]):
            continue  # the contracted link itself
        line = line.copy()
        line[0], line[-1] = moved.get(a, line[0]), moved.get(b, line[-1])
        out.append(line)
    return out


def _lengths(lines: list[np.ndarray]) -> np.ndarray:
    """The length of each line (at least two points each)."""
    if not lines:
        return np.zeros(0)
    points, starts = np.concatenate(lines), np.cumsum([0] + [len(line) for line in lines[:-1]])
    step = np.linalg.norm(np.diff(points, axis=0, append=points[-1:]), axis=1)
    step[starts[1:] - 1] = 0.0  # from one line's end to the next line's start
    return np.add.reduceat(step, starts)


def _attributes(img: np.ndarray, line: np.ndarray) -> tuple[int | None, int, tuple[str, bool]]:
    """A traced road's lane count (None: unknown), one-way direction along the line (1, -1 or 0) and (class, link)
    (residential where the raster does not say) from the SD raster colours of its pixels."""
    rows, cols = np.round(line).astype(int).T
    rows, cols = rows.clip(0, img.shape[0] - 1), cols.clip(0, img.shape[1] - 1)
    r, g, b = img[rows, cols].astype(int).T
    lanes = int(np.round(np.median(g[g > 0]) / LANE_STEP)) if (g > 0).mean() > 0.5 else None
    known = [v for v in r if v in CLASS_VALUES]
    road_class = CLASS_VALUES[max(set(known), key=known.count)] if len(known) > 0.5 * len(r) else UNKNOWN_CLASS
    if (b > 0).mean() <= 0.5:
        return lanes, 0, road_class
    theta = decode_direction(b[b > 0])  # 0: up (north), pi / 2: left (west)
    travel = np.array([-np.sin(theta).mean(), np.cos(theta).mean()])  # east, north
    along = np.array([line[-1, 1] - line[0, 1], line[0, 0] - line[-1, 0]])  # the line's direction, east and north
    return lanes, 1 if travel @ along >= 0 else -1, road_class
