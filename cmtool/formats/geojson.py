"""Lane graphs as GeoJSON (RFC 7946): WGS84 longitude/latitude, one FeatureCollection per scene.

The scene frame (metres, x forward, y left) is placed with its origin at ``(lat0, lon0)`` and its x
axis pointing to the compass ``heading`` (0 = north). Features, each with a ``kind`` property:

- ``lane``: the centerline (``id``, ``successors``, ``predecessors``, ``length_m``);
- ``boundary``: the left and right lane edges, half a lane width from the centerline (``lane``,
  ``side``);
- ``light``: traffic-light lines (``state`` green or red).
"""

from __future__ import annotations

import numpy as np

from cmtool.core.geo import scene_to_latlon
from cmtool.core.geometry import equal_count_batches, offset

LANE_WIDTH_M = 3.5


def to_geojson(graph, lat0: float, lon0: float, heading: float = 0.0, lane_width: float = LANE_WIDTH_M) -> dict:
    """A FeatureCollection of ``graph`` (a LaneGraph) placed at ``(lat0, lon0)``."""
    succ: dict[int, list[int]] = {}
    pred: dict[int, list[int]] = {}
    for i, j in graph.successors:
        succ.setdefault(int(i), []).append(int(j))
        pred.setdefault(int(j), []).append(int(i))
    lanes = [np.asarray(lane, np.float64) for lane in graph.lanes]
    edges, length = [None] * len(lanes), np.zeros(len(lanes))
    for which, batch in equal_count_batches(lanes):  # lanes of one vertex count at once, the same numbers
        length[which] = np.linalg.norm(np.diff(batch, axis=1), axis=2).sum(axis=1)
        sides = [offset(batch, np.full(len(which), sign * lane_width / 2.0)) for sign in (1.0, -1.0)]
        for n, k in enumerate(which):
            edges[k] = (sides[0][n], sides[1][n])
    lines, props = [], []  # every feature's line in scene metres, and its properties
    for i, lane in enumerate(lanes):
        lines += [lane, *edges[i]]
        props += [{"kind": "lane", "id": i, "successors": succ.get(i, []), "predecessors": pred.get(i, []),
                   "length_m": round(float(length[i]), 3)},
                  *({"kind": "boundary", "lane": i, "side": side} for side in ("left", "right"))]
    for state, lights in (("green", graph.green_lights), ("red", graph.red_lights)):
        lines += [np.asarray(line, np.float64) for line in lights]
        props += [{"kind": "light", "state": state} for _ in lights]
    if lines:  # one projection of all points: a scene of 10,000 lanes takes about a second
        lonlat = np.round(scene_to_latlon(np.concatenate(lines), lat0, lon0, heading)[:, ::-1], 9).tolist()
        ends = np.cumsum([len(line) for line in lines]).tolist()  # one tolist, sliced: not one call per feature
        coords = [lonlat[a:b] for a, b in zip([0] + ends[:-1], ends)]
    features = [{"type": "Feature", "geometry": {"type": "LineString", "coordinates": c},
                 "properties": p} for c, p in zip(coords, props)] if lines else []
    return {"type": "FeatureCollection", "features": features,
            "properties": {"city": graph.city, "frame_m": graph.frame_m, "origin": [lat0, lon0], "heading": heading,
                           "lane_width_m": lane_width}}
