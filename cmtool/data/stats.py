"""Map statistics that characterise a city's style, computed the same way for every HD source.

Everything goes through the derived road network (:func:`cmtool.data.sd_derive.road_network`):
roads as OpenStreetMap would draw them, road pieces between intersections, and intersections from
the connector lanes (``intersection_id`` / ``is_intersection``).
"""

from __future__ import annotations

import numpy as np

from cmtool.core.geometry import polyline_length, resample_step, wrap_angle
from cmtool.data.sd_derive import ROAD_LANE_TYPES, road_network, sd_from_network
from cmtool.maps.hdmap import HDMap

CURVATURE_STEP_M = 5.0  # polylines are resampled at this spacing before summing heading changes


def map_stats(hd: HDMap) -> dict[str, float]:
    """Style statistics of ``hd`` (means are 0 when there is nothing to average):

    - ``lanes_per_road``: mean total lane count of the derived SD roads, weighted by length;
    - ``block_length_m``: mean length of road pieces between two intersections, centre to centre;
    - ``intersection_degree``: mean number of road arms (piece ends) at an intersection;
    - ``curvature_deg_per_100m``: absolute heading change along road pieces per 100 m;
    - ``oneway_share``: length share of one-way roads;
    - ``lane_width_m``: mean width of road lanes (outside intersections), weighted by length;
    - ``lanes``, ``intersections``: counts; ``road_km``: total SD road length.
    """
    net = road_network(hd, split_divided=False)
    sd = sd_from_network(net, hd)
    road_len = np.array([polyline_length(r.polyline) for r in sd.roads])
    total = float(road_len.sum())
    blocks, arms = [], {k: 0 for k in net.intersections}
    turn, piece_len = 0.0, 0.0
    for piece in net.pieces:
        for end in piece.ends:
            if end is not None:
                arms[end] += 1
        length = polyline_length(piece.line)
        if None not in piece.ends and piece.ends[0] != piece.ends[1]:
            c0, c1 = (net.intersections[e] for e in piece.ends)
            blocks.append(length + np.linalg.norm(piece.line[0] - c0) + np.linalg.norm(piece.line[-1] - c1))
        if length > 0:
            d = np.diff(resample_step(piece.line, CURVATURE_STEP_M), axis=0)
            turn += float(np.abs(wrap_angle(np.diff(np.arctan2(d[:, 1], d[:, 0])))).sum())
            piece_len += length
    lanes = [l for l in hd.lanes.values()
             if l.lane_type in ROAD_LANE_TYPES and not (l.is_intersection or l.intersection_id is not None)]
    lane_len = np.array([polyline_length(l.centerline) for l in lanes])
    degrees = [a for a in arms.values() if a > 0]
    return {
        "lanes_per_road": _mean([r.lanes for r in sd.roads], road_len),
        "block_length_m": _mean(blocks),
        "intersection_degree": _mean(degrees),
        "curvature_deg_per_100m": float(np.degrees(turn) / piece_len * 100.0) if piece_len > 0 else 0.0,
        "oneway_share": _mean([float(r.oneway != 0) for r in sd.roads], road_len),
        "lane_width_m": _mean([l.width for l in lanes], lane_len),
        "lanes": float(len(hd.lanes)),
        "intersections": float(len(net.intersections)),
        "road_km": total / 1000.0,
    }


def _mean(values, weights=None) -> float:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0 or (weights is not None and float(np.sum(weights)) <= 0.0):
        return 0.0
    return float(np.average(values, weights=weights))
