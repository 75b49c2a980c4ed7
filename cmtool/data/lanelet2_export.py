"""Lane graphs as Lanelet2 maps (OSM XML, WGS84), loadable by Lanelet2 and by our own importer.

Every lane becomes a lanelet (``type=lanelet``, ``subtype=road``, ``one_way=yes``) whose left and
right bounds are ways half a lane width either side of the centerline. Lane ends and starts joined
by successor edges (forks and merges included) get one shared left and one shared right bound
node, which is how Lanelet2 routing finds successors.
Bounds of neighbouring lanes that coincide (within ``SHARE_M`` on average and ``SHARE_ENDS_M`` at
both ends, in either direction) become one way, so routing sees lane changes. Each traffic-light line becomes a
``regulatory_element`` (``subtype=traffic_light``) with a light way and a stop line across the
lane it starts on, referenced by that lanelet. The scene frame's origin is placed at
``(lat0, lon0)`` with its forward axis pointing to the compass ``heading``.
"""

from __future__ import annotations

import os
from xml.sax.saxutils import quoteattr

import numpy as np

from cmtool.data.geo import scene_to_latlon
from cmtool.data.jsonio import write_text_atomic
from cmtool.geometry import offset, resample, unit
from cmtool.unionfind import UnionFind

LANE_WIDTH_M = 3.5
SHARE_M = 0.3  # mean distance under which two bounds become one way ...
SHARE_ENDS_M = 0.05  # ... when their end points are this close
LIGHT_REACH_M = 3.0  # a light line controls the lane starting this close to its start


class _Ways:
    """Nodes (deduplicated to the millimetre) and ways, numbered from 1."""

    def __init__(self):
        self.node_ids: dict[tuple[int, int], int] = {}
        self.nodes: list[np.ndarray] = []
        self.ways: list[tuple[list[int], dict]] = []
        self.aliases: dict[tuple[int, int], tuple[int, int]] = {}

    @staticmethod
    def _key(p: np.ndarray) -> tuple[int, int]:
        return round(float(p[0]) * 1000), round(float(p[1]) * 1000)

    def alias(self, p: np.ndarray, q: np.ndarray) -> None:
        """Make point ``p`` the same node as ``q`` (a shared bound's end, within ``SHARE_ENDS_M``)."""
        key, target = self._key(p), self._key(q)
        seen = {key}
        while target in self.aliases and target not in seen:
            seen.add(target)
            target = self.aliases[target]
        if target not in seen and key not in self.aliases:
            self.aliases[key] = target

    def node(self, p: np.ndarray) -> int:
        key = self._key(p)
        if key in self.aliases:
            key, p = self.aliases[key], None
        if key not in self.node_ids:
            if p is None:
                p = np.array(key, np.float64) / 1000.0
            self.node_ids[key] = len(self.nodes) + 1
            self.nodes.append(np.asarray(p, np.float64))
        return self.node_ids[key]

    def way(self, points: np.ndarray, **tags) -> int:
        refs = []
        for p in points:
            n = self.node(p)
            if not refs or refs[-1] != n:
                refs.append(n)
        self.ways.append((refs, tags))
        return len(self.ways)


def to_lanelet2(graph, lat0: float, lon0: float, heading: float = 0.0, lane_width: float = LANE_WIDTH_M) -> str:
    """The OSM XML text of ``graph`` (a LaneGraph) as a Lanelet2 map."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    bounds = [[offset(l, lane_width / 2.0), offset(l, -lane_width / 2.0)] for l in lanes]  # [left, right]
    _join_ends(bounds, graph.successors)
    ways = _Ways()
    owner: dict[tuple[int, int], tuple[int, int]] = {}  # bound -> the first bound it coincides with
    firsts: list[tuple[int, int]] = []  # bounds that coincide with no earlier one: one way each
    for i in range(len(lanes)):
        for side in (0, 1):
            b = bounds[i][side]
            owner[(i, side)] = (i, side)
            for key in firsts:
                other = bounds[key[0]][key[1]]
                flip = _coincide(b, other)
                if flip is not None:
                    owner[(i, side)] = key
                    ways.alias(b[0], other[-1] if flip else other[0])  # joints this bound ends at
                    ways.alias(b[-1], other[0] if flip else other[-1])  # become the shared way's ends
                    break
            else:
                firsts.append((i, side))
    made = {key: ways.way(bounds[key[0]][key[1]], type="line_thin", subtype="dashed") for key in firsts}
    way_of = {bound: made[key] for bound, key in owner.items()}
    relations = []
    for i in range(len(lanes)):
        relations.append(([("way", way_of[(i, 0)], "left"), ("way", way_of[(i, 1)], "right")],
                          {"type": "lanelet", "subtype": "road", "location": "urban", "one_way": "yes",
                           "cmtool:lane": str(i)}))
    starts = np.array([l[0] for l in lanes]).reshape(-1, 2)
    for state, lights in (("green", graph.green_lights), ("red", graph.red_lights)):
        for line in lights if len(starts) else []:
            line = np.asarray(line, np.float64)
            k = int(np.argmin(np.linalg.norm(starts - line[0], axis=1)))
            if np.linalg.norm(starts[k] - line[0]) > LIGHT_REACH_M:
                continue
            across = np.array([-1.0, 1.0]) * unit(lanes[k][1] - lanes[k][0])[::-1]
            stop = np.array([line[0] + across * lane_width / 2.0, line[0] - across * lane_width / 2.0])
            stop_way = ways.way(stop, type="stop_line")
            light_way = ways.way(line[:2], type="traffic_light", subtype="red_yellow_green")
            relations.append(([("way", light_way, "refers"), ("way", stop_way, "ref_line")],
                              {"type": "regulatory_element", "subtype": "traffic_light", "cmtool:state": state}))
            relations[k][0].append(("relation", len(relations), "regulatory_element"))
    return _xml(ways, relations, lat0, lon0, heading)


def write_lanelet2(graph, path: str | os.PathLike, lat0: float, lon0: float, heading: float = 0.0,
                   lane_width: float = LANE_WIDTH_M) -> None:
    write_text_atomic(path, to_lanelet2(graph, lat0, lon0, heading, lane_width))


def _join_ends(bounds: list[list[np.ndarray]], successors) -> None:
    """Give every joint of the successor graph one left and one right bound point: lane ends and
    starts joined by successor edges (transitively, so forks and merges share one joint) move to
    the mean of their bound points."""
    ends = UnionFind(range(2 * len(bounds)))  # 2i: start of lane i, 2i + 1: its end
    for i, j in successors:
        ends.union(2 * int(i) + 1, 2 * int(j))
    for members in ends.groups():
        if len(members) < 2:
            continue
        for side in (0, 1):
            points = [(bounds[k // 2][side], 0 if k % 2 == 0 else -1) for k in members]
            mean = np.mean([b[e] for b, e in points], axis=0)
            for b, e in points:
                b[e] = mean


def _coincide(a: np.ndarray, b: np.ndarray) -> bool | None:
    """Whether two bounds run along each other and end at the same points, so that sharing one way
    moves no joint by more than ``SHARE_ENDS_M``: False when in the same direction, True when in
    opposite directions, None when they do not coincide."""
    ra, rb = resample(a, 10), resample(b, 10)
    for flip, other in ((False, rb), (True, rb[::-1])):
        ends = max(np.linalg.norm(ra[0] - other[0]), np.linalg.norm(ra[-1] - other[-1]))
        if ends < SHARE_ENDS_M and np.linalg.norm(ra - other, axis=1).mean() < SHARE_M:
            return flip
    return None


def _xml(ways: _Ways, relations, lat0: float, lon0: float, heading: float) -> str:
    latlon = scene_to_latlon(np.array(ways.nodes).reshape(-1, 2), lat0, lon0, heading)
    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="cmtool">']
    out += [f'  <node id="{i}" lat="{lat:.10f}" lon="{lon:.10f}" version="1"/>'
            for i, (lat, lon) in enumerate(latlon, start=1)]
    for k, (refs, tags) in enumerate(ways.ways, start=1):
        out.append(f'  <way id="{k}" version="1">')
        out += [f'    <nd ref="{r}"/>' for r in refs]
        out += [f"    <tag k={quoteattr(t)} v={quoteattr(v)}/>" for t, v in tags.items()]
        out.append("  </way>")
    for k, (members, tags) in enumerate(relations, start=1):
        out.append(f'  <relation id="{k}" version="1">')
        out += [f'    <member type="{kind}" ref="{ref}" role="{role}"/>' for kind, ref, role in members]
        out += [f"    <tag k={quoteattr(t)} v={quoteattr(v)}/>" for t, v in tags.items()]
        out.append("  </relation>")
    out.append("</osm>")
    return "\n".join(out) + "\n"
