"""Helpers shared by the HD map importers: centerlines from lane bounds, and reference clean-up."""

from __future__ import annotations

import numpy as np

from cmtool.core.geometry import resample
from cmtool.maps.hdmap import HDMap

MIN_WIDTH, MAX_WIDTH = 0.5, 20.0  # the range HDMap.from_json accepts


def centerline_and_width(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, float]:
    """Centerline and mean width of a lane from its left and right bounds (both in driving direction).

    Both bounds are resampled by arc length to the same number of points; the centerline is their
    pointwise mean and the width the mean pointwise distance (clipped to a plausible lane width).
    """
    n = max(len(left), len(right), 2)
    left, right = resample(left, n), resample(right, n)
    width = float(np.linalg.norm(left - right, axis=1).mean())
    return 0.5 * (left + right), float(np.clip(width, MIN_WIDTH, MAX_WIDTH))


def same_direction(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two polylines run the same way (their start-to-end vectors point within 90 degrees)."""
    return float(np.dot(a[-1] - a[0], b[-1] - b[0])) > 0.0


def tidy_references(hd: HDMap) -> HDMap:
    """Drop references to lanes that are not in the map and make every successor relation two-sided.

    An edge a -> b is kept when either side names it and both lanes exist; it is then recorded on both
    (``a.successors`` and ``b.predecessors``), in a deterministic order.
    """
    edges = set()
    for lane in hd.lanes.values():
        edges.update((lane.id, s) for s in lane.successors if s in hd.lanes and s != lane.id)
        edges.update((p, lane.id) for p in lane.predecessors if p in hd.lanes and p != lane.id)
        lane.successors, lane.predecessors = [], []
        if lane.left_neighbor not in hd.lanes:
            lane.left_neighbor = None
        if lane.right_neighbor not in hd.lanes:
            lane.right_neighbor = None
    for a, b in sorted(edges):
        hd.link(a, b)
    for sl in hd.stop_lines:
        sl.lane_ids = [i for i in sl.lane_ids if i in hd.lanes]
    return hd
