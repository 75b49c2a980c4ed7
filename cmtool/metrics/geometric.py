"""Geometric metrics of a generated lane set against its ground truth and its SD control (ours,
beyond the paper). Lanes are ego-frame polylines in metres; SD rasters follow the raster convention
(docs/data.md: "Frames and rasters").

- :func:`chamfer`: symmetric mean distance between the lane sets (metres);
- :func:`sd_adherence`: share of SD road within 3 m of a generated lane, and share of generated lane
  length within 5 m of an SD road. Road length is measured by road pixels (roads are drawn at a
  constant width);
- :func:`driving_side`: share of generated lane length along two-way SD roads that lies on the side
  of the road the city drives on;
- :func:`oncoming_side`: the same judged from the lanes alone, by the side on which oncoming lanes
  run (needs no SD map, so it also judges unguided samples);
- :func:`legal_oneway`: share of lane length along one-way SD roads that runs the legal way.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from cmtool.core.geometry import as_polyline
from cmtool.data.sd_raster import decode_direction
from cmtool.metrics.lanes import near_polylines, pair_distances, resampled

STEP_M = 0.5  # lane resampling step for all point-based scores


def chamfer(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray], step: float = STEP_M) -> float:
    """Mean of the two directed mean nearest distances (metres); NaN when either set is empty."""
    return chamfer_of(pair_distances(pred, gt, step))


def chamfer_of(distances: tuple[np.ndarray, np.ndarray]) -> float:
    """:func:`chamfer` from the distances of :func:`cmtool.metrics.lanes.pair_distances`."""
    a, b = distances
    return math.nan if len(a) == 0 or len(b) == 0 else 0.5 * float(a.mean() + b.mean())


def pixel_centres(mask: np.ndarray, frame_m: float = 64.0) -> np.ndarray:
    """Ego-frame metres (N, 2) of the centres of the True pixels of a raster mask (row 0 in front)."""
    px = frame_m / mask.shape[0]
    rows, cols = np.nonzero(mask)
    half = frame_m / 2.0
    return np.stack([half - (rows + 0.5) * px, half - (cols + 0.5) * px], axis=-1)


def sd_adherence(lanes: Sequence[np.ndarray], sd: np.ndarray, road_tol: float = 3.0, lane_tol: float = 5.0,
                 frame_m: float = 64.0, step: float = STEP_M) -> dict[str, float]:
    """``sd_coverage``: share of SD road within ``road_tol`` of a lane (NaN without roads);
    ``lane_on_sd``: share of lane length within ``lane_tol`` of an SD road (NaN without lanes)."""
    roads = _roads(sd, frame_m)
    coverage = math.nan
    if len(roads.rows):
        coverage = float(np.mean(near_polylines(roads.centres, lanes, road_tol))) if len(lanes) else 0.0
    points = np.concatenate(_resampled(lanes, step)) if len(lanes) else np.zeros((0, 2))
    on_sd = math.nan
    if len(points):
        if len(roads.rows):
            row, col = _pixel_of(points, sd.shape[0], frame_m)
            inside = (row >= 0) & (row < sd.shape[0]) & (col >= 0) & (col < sd.shape[1])
            dist = np.full(len(points), np.inf)
            dist[inside] = roads.far[row[inside], col[inside]]
            on_sd = float(np.mean(dist <= lane_tol))
        else:
            on_sd = 0.0
    return {"sd_coverage": coverage, "lane_on_sd": on_sd}


@dataclass
class _Roads:
    """The road pixels of an SD raster ``sd`` (a copy) of ``frame_m`` metres a side: their rows, columns and centres
    (ego-frame metres), and, made when first asked for, a KD-tree of the centres, the distance (m) from each pixel to
    the nearest road pixel and :func:`_oneway_points`' answers for the last few lane sets."""
    sd: np.ndarray
    frame_m: float
    rows: np.ndarray
    cols: np.ndarray
    centres: np.ndarray
    judged: dict = field(default_factory=dict)

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.centres)

    @cached_property
    def far(self) -> np.ndarray:
        road = (self.sd[..., 0] > 0).astype(np.uint8)
        return cv2.distanceTransform(1 - road, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * (self.frame_m / road.shape[0])


def _roads(sd: np.ndarray, frame_m: float) -> _Roads:
    """The :class:`_Roads` of an SD raster, remembered for the last few rasters (found by comparing them, faster than
    a digest): the scores of a map and of its repair ask about one raster several times."""
    for roads in _ROADS:
        if roads.frame_m == frame_m and roads.sd.shape == sd.shape and np.array_equal(roads.sd, sd):
            return roads
    road = sd[..., 0] > 0
    rows, cols = np.nonzero(road)
    _ROADS.insert(0, _Roads(np.array(sd), frame_m, rows, cols, pixel_centres(road, frame_m)))
    del _ROADS[REMEMBERED:]
    return _ROADS[0]


REMEMBERED = 4  # SD rasters (and lane sets resampled, and judged on each raster) remembered
_ROADS: list[_Roads] = []
_RESAMPLED: dict[tuple, list[np.ndarray]] = {}


def _remembered(store: dict, key, make):
    """``make()``, remembered in ``store`` by ``key`` for the last few keys (shared, not copied: read only)."""
    if key not in store:
        if len(store) >= REMEMBERED:
            store.clear()
        store[key] = make()
    return store[key]


def _digest(lanes) -> bytes:
    """A digest of lanes' shapes, types and coordinates: equal only for equal lanes."""
    digest = hashlib.blake2b(digest_size=32)
    for lane in lanes:
        lane = np.ascontiguousarray(lane)
        digest.update(f"{lane.shape}{lane.dtype.str}".encode())
        digest.update(lane)
    return digest.digest()


def driving_side(lanes: Sequence[np.ndarray], sd: np.ndarray, drives_on: str, reach: float = 6.0,
                 frame_m: float = 64.0, step: float = STEP_M) -> tuple[float, int]:
    """Share of lane points along two-way SD roads on the ``drives_on`` ("right"/"left") side, and
    how many points were judged.

    At each lane point, the two-way road pixels met on a cross-section along the lane's normal (up
    to ``reach`` m to either side, every 0.25 m) locate the road's centre line; the point is on the
    right when that centre lies to its left. Points less than 0.5 m from the centre are not judged.
    """
    if drives_on not in ("right", "left"):
        raise ValueError(f"drives_on must be 'right' or 'left', got {drives_on!r}")
    two_way = (sd[..., 0] > 0) & (sd[..., 2] == 0)
    pieces = _resampled(lanes, step)
    if not two_way.any() or not pieces:
        return math.nan, 0
    points, dirs = _headings(pieces)
    left = np.stack([-dirs[:, 1], dirs[:, 0]], axis=-1)
    offsets = np.arange(-reach, reach + 1e-9, 0.25)
    probes = points[:, None, :] + offsets[None, :, None] * left[:, None, :]  # (N, K, 2)
    row, col = _pixel_of(probes.reshape(-1, 2), two_way.shape[0], frame_m)
    inside = (row >= 0) & (row < two_way.shape[0]) & (col >= 0) & (col < two_way.shape[1])
    hit = np.zeros(len(row), bool)
    hit[inside] = two_way[row[inside], col[inside]]
    hit = hit.reshape(len(points), len(offsets))
    count = hit.sum(axis=1)
    centre = (hit * offsets).sum(axis=1) / np.maximum(count, 1)
    judged = (count >= 2) & (np.abs(centre) >= 0.5)
    if not judged.any():
        return math.nan, 0
    share_right = float(np.mean(centre[judged] > 0))
    return (share_right if drives_on == "right" else 1.0 - share_right), int(judged.sum())


def oncoming_side(lanes: Sequence[np.ndarray], drives_on: str, reach: tuple[float, float] = (1.5, 10.0),
                  step: float = 1.0, neighbours: int = 48) -> tuple[float, int]:
    """Share of lane points whose nearest oncoming lane runs on the side that ``drives_on`` implies
    (on their left for right-hand traffic), and how many points were judged.

    At each point (every ``step`` m), the nearest point of another lane heading the other way
    (within 37 degrees of opposite) between ``reach`` metres away and more beside than ahead of it
    decides; points without one are not judged.
    """
    if drives_on not in ("right", "left"):
        raise ValueError(f"drives_on must be 'right' or 'left', got {drives_on!r}")
    pieces = _resampled(lanes, step)
    if len(pieces) < 2:
        return math.nan, 0
    points, dirs = _headings(pieces)
    owner = np.concatenate([np.full(len(p), i) for i, p in enumerate(pieces)])
    k = min(neighbours, len(points))
    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=reach[1])
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    offset = points[idx] - points[:, None, :]
    along = np.abs(np.einsum("nkd,nd->nk", offset, dirs))
    ok = found & (dist > reach[0]) & (owner[idx] != owner[:, None]) & (along < 0.5 * dist) \
        & (np.einsum("nkd,nd->nk", dirs[idx], dirs) < -0.8)
    judged = ok.any(axis=1)
    if not judged.any():
        return math.nan, 0
    first = np.argmax(ok, axis=1)  # neighbours come sorted by distance: the nearest oncoming point
    near = offset[np.arange(len(points)), first]
    on_left = dirs[:, 0] * near[:, 1] - dirs[:, 1] * near[:, 0] > 0
    share_right = float(np.mean(on_left[judged]))
    return (share_right if drives_on == "right" else 1.0 - share_right), int(judged.sum())


def legal_oneway(lanes: Sequence[np.ndarray], sd: np.ndarray, reach: float = 4.0, frame_m: float = 64.0,
                 step: float = STEP_M) -> tuple[float, float]:
    """Share of lane length along one-way SD roads that runs the legal way, and the length judged (m).

    A lane point is judged when the nearest road pixel within ``reach`` m is one-way and the lane runs
    along that road (within 45 degrees of its axis, so lanes crossing it at a junction are not
    judged); it is legal when it heads within 90 degrees of the road's travel heading.
    """
    judged = _oneway_points(lanes, sd, reach, frame_m, step)
    if judged is None or not len(judged[1]):
        return math.nan, 0.0
    return float(np.mean(judged[1])), float(len(judged[1]) * step)


def legal_oneway_by_lane(lanes: Sequence[np.ndarray], sd: np.ndarray, reach: float = 4.0, frame_m: float = 64.0,
                         step: float = STEP_M) -> tuple[np.ndarray, np.ndarray]:
    """:func:`legal_oneway` of each lane on its own, (shares, judged metres) (L,) each (NaN and 0 where nothing of
    the lane is judged), from one search over the road pixels."""
    shares, metres = np.full(len(lanes), math.nan), np.zeros(len(lanes))
    judged = _oneway_points(lanes, sd, reach, frame_m, step)
    if judged is not None and len(judged[1]):
        lane, legal = judged
        counts = np.bincount(lane, minlength=len(lanes))
        seen = counts > 0
        shares[seen] = np.bincount(lane, weights=legal, minlength=len(lanes))[seen] / counts[seen]
        metres = counts * step
    return shares, metres


def _oneway_points(lanes, sd: np.ndarray, reach: float, frame_m: float,
                   step: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The judged points of :func:`legal_oneway`: each one's lane index and whether it runs the legal way (None
    without one-way road pixels or lanes)."""
    roads, pieces = _roads(sd, frame_m), _resampled(lanes, step)
    if not pieces or not (sd[roads.rows, roads.cols, 2] > 0).any():
        return None

    def make() -> tuple[np.ndarray, np.ndarray]:
        points, dirs = _headings(pieces)
        lane = np.repeat(np.arange(len(pieces)), [len(p) for p in pieces])
        _, nearest = roads.tree.query(points, distance_upper_bound=reach)
        found = nearest < len(roads.rows)
        value = np.zeros(len(points), np.uint8)
        value[found] = sd[roads.rows[nearest[found]], roads.cols[nearest[found]], 2]
        theta = decode_direction(value)
        cos = dirs[:, 0] * np.cos(theta) + dirs[:, 1] * np.sin(theta)
        judged = (value > 0) & (np.abs(cos) >= math.cos(math.radians(45.0)))
        return lane[judged], cos[judged] > 0

    return _remembered(roads.judged, (_digest(lanes), float(reach), float(step)), make)


def _resampled(lanes: Sequence[np.ndarray], step: float) -> list[np.ndarray]:
    """The lanes resampled every ``step`` metres (:func:`cmtool.metrics.lanes.resampled`, at least 2 points each),
    remembered for the last few lane sets."""
    return _remembered(_RESAMPLED, (_digest(lanes), float(step)),
                       lambda: resampled([as_polyline(l) for l in lanes], step))


def _headings(pieces: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """All points of the resampled lanes (N, 2) and their unit travel directions (N, 2): ``np.gradient`` along each
    piece, computed on all at once."""
    points = np.concatenate(pieces)
    end = np.cumsum([len(p) for p in pieces])
    start = end - [len(p) for p in pieces]
    dirs = np.empty_like(points)
    dirs[1:-1] = (points[2:] - points[:-2]) / 2.0
    dirs[start] = points[start + 1] - points[start]
    dirs[end - 1] = points[end - 1] - points[end - 2]
    return points, dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-9)


def _pixel_of(points: np.ndarray, size: int, frame_m: float) -> tuple[np.ndarray, np.ndarray]:
    px = frame_m / size
    half = frame_m / 2.0
    return (np.floor((half - points[:, 0]) / px).astype(int), np.floor((half - points[:, 1]) / px).astype(int))
