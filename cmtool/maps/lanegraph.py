"""The lane graph JSON format: one 64 m scene in the ego frame per JSON object (or a whole HD map in its own
metres, :meth:`LaneGraph.from_hd`, its ``frame_m`` the square about the origin that holds it).

This is the interchange format: what the model emits as a map and what the metrics read. A set of
scenes is JSON Lines (``.jsonl``), one object per line::

    {"version": 1, "city": "SGP", "frame_m": 64.0,
     "lanes": [[[x, y], ...], ...], "successors": [[i, j], ...],
     "green_lights": [[[x, y], ...], ...], "red_lights": [[[x, y], ...], ...],
     "left_neighbors": [[i, j], ...], "oncoming": [[i, j], ...], "widths": [3.5, ...],
     "meta": {"source": "...", "seed": 0, "cfg": 0.7, "geo": {"lat": 60.53, "lon": 26.95, "heading": 90.0}}}

Lanes are centerlines in driving direction (any number of points >= 2); ``successors`` are index
pairs (lane i flows into lane j). ``left_neighbors`` (optional) are index pairs: lane j is lane i's
left neighbour, the same way (a lane change); ``oncoming`` (optional) pairs i < j are lanes that run
the other way across a shared centre line (see :mod:`cmtool.maps.neighbours`); files without them
(older ones) get them from the geometry where they are needed. ``widths`` (optional) are lane
widths in metres.
``meta.geo`` (optional) places the frame on the globe: the latitude and longitude of its origin and
the compass heading of its forward axis. Reading validates everything and names the line and field
of the first problem; NaN and infinite coordinates are rejected.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import unit
from cmtool.core.jsonio import Fields, MalformedLine, json_lines, read_json, write_text_atomic
from cmtool.core.unionfind import UnionFind
from cmtool.maps.hdmap import HDMap, Lane, StopLine, drives_on

HD_MARGIN_M = 2.0  # a whole map's frame (LaneGraph.from_hd) reaches this far beyond its farthest point


@dataclass
class LaneGraph:
    lanes: list[np.ndarray]  # each (N, 2), N >= 2
    successors: list[tuple[int, int]] = field(default_factory=list)
    green_lights: list[np.ndarray] = field(default_factory=list)
    red_lights: list[np.ndarray] = field(default_factory=list)
    left_neighbors: list[tuple[int, int]] | None = None  # None: not recorded (inferred where needed)
    oncoming: list[tuple[int, int]] | None = None  # the same
    widths: list[float] | None = None
    city: str | None = None
    frame_m: float = 64.0
    meta: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        def lines(ls):
            return [np.round(np.asarray(l, dtype=np.float64), 3).tolist() for l in ls]

        return {
            "version": 1,
            "city": self.city,
            "frame_m": float(self.frame_m),
            "lanes": lines(self.lanes),
            "successors": [[int(i), int(j)] for i, j in self.successors],
            "green_lights": lines(self.green_lights),
            "red_lights": lines(self.red_lights),
            **{k: [[int(i), int(j)] for i, j in v] for k, v in (("left_neighbors", self.left_neighbors),
                                                                ("oncoming", self.oncoming)) if v is not None},
            **({} if self.widths is None else {"widths": [round(float(w), 3) for w in self.widths]}),
            "meta": self.meta,
        }

    def as_written(self) -> "LaneGraph":
        """The lane graph as its file holds it: coordinates and widths to the millimetre (:meth:`to_json`), so that
        what is judged in memory is judged alike when the file is read back."""
        def mm(lines):
            return [np.round(np.asarray(l, dtype=np.float64), 3) for l in lines]

        return replace(self, lanes=mm(self.lanes), green_lights=mm(self.green_lights), red_lights=mm(self.red_lights),
                       widths=None if self.widths is None else [round(float(w), 3) for w in self.widths])

    @classmethod
    def from_json(cls, obj, where: str = "scene") -> "LaneGraph":
        f = Fields(obj, where)
        f.header(None, "a lane graph")
        frame_m = f.number("frame_m", 64.0)
        if frame_m <= 0:
            f.fail("frame_m", f"must be positive, got {frame_m}")
        graph = cls(
            lanes=f.lines("lanes"),
            green_lights=f.lines("green_lights", []),
            red_lights=f.lines("red_lights", []),
            city=f.get("city", str, None, allow_none=True),
            frame_m=frame_m,
            meta=f.get("meta", dict, {}),
        )
        graph.successors = _pairs(f, "successors", len(graph.lanes))
        for key in ("left_neighbors", "oncoming"):
            if f.get(key, list, None, allow_none=True) is not None:
                setattr(graph, key, _pairs(f, key, len(graph.lanes)))
        widths = f.get("widths", list, None, allow_none=True)
        if widths is not None:
            if len(widths) != len(graph.lanes):
                f.fail("widths", f"expected one width per lane ({len(graph.lanes)}), got {len(widths)}")
            for k, w in enumerate(widths):
                if type(w) not in (int, float) or not 0.5 <= w <= 20.0:
                    f.fail(f"widths[{k}]", f"expected a lane width in metres (0.5 to 20), got {w!r}")
            graph.widths = [float(w) for w in widths]
        geo = graph.meta.get("geo")
        if geo is not None:
            geo_origin(geo, f"{where}: meta.geo")
        return graph

    @classmethod
    def from_hd(cls, hd: HDMap) -> "LaneGraph":
        """A whole HD map as one lane graph, in the map's own metres: its lanes with their successors, left
        neighbours and widths, its green and red lights as light lines (as scenes draw them: the centre line of
        each lane a stop line controls, or the stop line itself where it names none); ``frame_m`` the square about the
        origin that holds it all (so that only lanes ending at the map's outer edge touch the border); ``meta.geo``
        where the map records its place (an imported map's projection origin, x east and y north)."""
        ids = list(hd.lanes)
        index = {k: i for i, k in enumerate(ids)}
        lanes = [np.asarray(hd.lanes[k].centerline, np.float64) for k in ids]
        lights = {state: [np.asarray(line, np.float64) for s in hd.stop_lines if s.state == state
                          for line in ([hd.lanes[i].centerline for i in s.lane_ids if i in hd.lanes] or [s.line])]
                  for state in ("green", "red")}
        points = [p for p in (*lanes, *lights["green"], *lights["red"]) if len(p)]
        reach = float(max((np.abs(p).max() for p in points), default=32.0))
        return cls(
            lanes=lanes,
            successors=[(index[k], index[s]) for k in ids for s in hd.lanes[k].successors if s in index],
            left_neighbors=[(index[k], index[hd.lanes[k].left_neighbor]) for k in ids
                            if hd.lanes[k].left_neighbor in index],
            widths=[float(hd.lanes[k].width) for k in ids],
            green_lights=lights["green"], red_lights=lights["red"], city=hd.city or None,
            frame_m=2.0 * (math.ceil(reach) + HD_MARGIN_M),
            meta={"source": hd.source, **({"geo": geo} if (geo := _hd_geo(hd.meta)) else {})})

    def to_hd(self) -> HDMap:
        """The lane graph as an HD map (lanes ``l0, l1, ...``; each light line a stop line of its colour across the
        start of the lane it controls, :func:`controlled_lanes`, or along the light line where it controls none). It
        records no intersection lanes: a lane graph does not say which lanes are junction connectors."""
        hd = HDMap(city=self.city or "", drives_on=drives_on(self.city), source=str(self.meta.get("source", "")),
                   meta={"geo": self.meta["geo"]} if "geo" in self.meta else {})
        for k, lane in enumerate(self.lanes):
            width = 3.5 if self.widths is None else float(self.widths[k])
            hd.add_lane(Lane(f"l{k}", np.asarray(lane, np.float64), width=width))
        for i, j in self.successors:
            hd.link(f"l{i}", f"l{j}")
        for i, j in self.left_neighbors or []:
            hd.lanes[f"l{i}"].left_neighbor, hd.lanes[f"l{j}"].right_neighbor = f"l{j}", f"l{i}"
        for n, (state, line, k) in enumerate(controlled_lanes(self, every=True)):
            if k is None:
                hd.stop_lines.append(StopLine(f"s{n}", line, state))
                continue
            lane = hd.lanes[f"l{k}"]
            hd.stop_lines.append(StopLine(f"s{n}", stop_line(lane.centerline, lane.width), state, [lane.id]))
        return hd

    @property
    def geo(self) -> tuple[float, float, float] | None:
        """(lat, lon, compass heading) of the frame's origin and forward axis, when recorded."""
        geo = self.meta.get("geo")
        return None if geo is None else geo_origin(geo, "meta.geo")


def _hd_geo(meta: dict) -> dict | None:
    """Where an HD map lies: its recorded ``geo``, or the projection origin of an imported map (x east)."""
    if "geo" in meta:
        return meta["geo"]
    if "lat0" in meta and "lon0" in meta:
        return {"lat": meta["lat0"], "lon": meta["lon0"], "heading": 90.0}
    return None


def geo_origin(geo, where: str) -> tuple[float, float, float]:
    """``{"lat":, "lon":, "heading":}`` checked: a latitude, a longitude and a finite heading."""
    try:
        lat, lon, heading = (float(geo[k]) for k in ("lat", "lon", "heading"))
    except (KeyError, TypeError, ValueError, OverflowError):
        raise CmtoolError(f"{where}: expected {{\"lat\": ..., \"lon\": ..., \"heading\": ...}}, got {geo!r}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(heading)):
        raise CmtoolError(f"{where}: latitude must be in [-90, 90], longitude in [-180, 180] and the heading "
                          f"finite, got {lat}, {lon}, {heading}")
    return lat, lon, heading


def _pairs(f: Fields, key: str, n: int) -> list[tuple[int, int]]:
    out = []
    for k, pair in enumerate(f.get(key, list, [])):
        ok = isinstance(pair, list) and len(pair) == 2 and all(type(v) is int for v in pair)
        if not ok:
            f.fail(f"{key}[{k}]", f"expected [i, j] lane indices, got {pair!r}")
        if not all(0 <= v < n for v in pair):
            f.fail(f"{key}[{k}]", f"lane index out of range in {pair} ({n} lanes)")
        out.append((pair[0], pair[1]))
    return out


def read_jsonl(path: str | os.PathLike) -> list[LaneGraph]:
    """Read lane graphs from a ``.jsonl`` file (a ``.json`` file holding one object also works)."""
    path = Path(path)
    try:
        rows = json_lines(path)
    except MalformedLine as e:
        if e.lineno == 1 and path.suffix == ".json":  # a pretty-printed single scene
            return [LaneGraph.from_json(read_json(path), f"{path}")]
        raise
    graphs = [LaneGraph.from_json(obj, f"{path}: line {lineno}") for lineno, obj in rows]
    if not graphs:
        raise CmtoolError(f"{path}: no lane graphs in the file")
    return graphs


def write_jsonl(path: str | os.PathLike, graphs) -> None:
    """Write lane graphs as JSON Lines (atomically)."""
    write_text_atomic(path, "".join(json.dumps(g.to_json(), separators=(",", ":")) + "\n" for g in graphs))


LIGHT_REACH_M = 3.0  # a light line controls the lane starting this close to its start


def controlled_lanes(graph, every: bool = False) -> list[tuple[str, np.ndarray, int | None]]:
    """(state, light line, index of the lane it controls) for each green and red light line that starts
    within ``LIGHT_REACH_M`` of a lane's start (the lane starting nearest, and of lanes starting alike, the one
    that runs nearest its end: the branches of a fork start at one point); the others control nothing, and come
    with the index None when ``every`` is set (else not at all)."""
    lanes = [np.asarray(l, np.float64) for l in graph.lanes]
    starts = np.array([l[0] for l in lanes]).reshape(-1, 2)
    out = []
    for state, lights in (("green", graph.green_lights), ("red", graph.red_lights)):
        for line in lights:
            line = np.asarray(line, np.float64)
            distance = np.linalg.norm(starts - line[0], axis=1)
            k = None
            if len(lanes):
                near = np.flatnonzero(distance <= distance.min() + 0.01)
                k = int(near[np.argmin([np.linalg.norm(lanes[i] - line[-1], axis=1).min() for i in near])])
                k = k if distance[k] <= LIGHT_REACH_M else None
            if k is not None or every:
                out.append((state, line, k))
    return out


def stop_line(line: np.ndarray, width: float, at: np.ndarray | None = None) -> np.ndarray:
    """A stop line ``width`` long across the start of ``line`` (a lane centre line, or a light line), left end
    first, centred on ``at`` [default: the line's start]."""
    across = np.array([-1.0, 1.0]) * unit(line[1] - line[0])[::-1] * width / 2.0
    at = line[0] if at is None else at
    return np.array([at + across, at - across])


def infer_successors(lanes, max_gap_m: float = 1.5, max_angle_deg: float = 60.0) -> list[tuple[int, int]]:
    """Successor edges by endpoint proximity: the end of lane i lies within
    ``max_gap_m`` of the start of lane j and their headings there differ by at most
    ``max_angle_deg``. Sorted; the candidates come from a KD-tree of the starts, so a scene of many
    lanes costs what its near pairs cost."""
    if len(lanes) == 0:
        return []
    ends = np.array([l[-1] for l in lanes], np.float64)
    starts = np.array([l[0] for l in lanes], np.float64)
    end_dir = unit(np.array([l[-1] - l[-2] for l in lanes]))
    start_dir = unit(np.array([l[1] - l[0] for l in lanes]))
    pairs = cKDTree(starts).query_ball_point(ends, max_gap_m * (1 + 1e-9) + 1e-12)  # a hair wide: checked below
    i = np.repeat(np.arange(len(lanes)), [len(p) for p in pairs])
    j = np.fromiter((k for p in pairs for k in p), np.int64, len(i))
    ok = ((np.linalg.norm(ends[i] - starts[j], axis=-1) <= max_gap_m) & (i != j)
          & (np.sum(end_dir[i] * start_dir[j], axis=-1) >= np.cos(np.radians(max_angle_deg))))
    return sorted((int(a), int(b)) for a, b in zip(i[ok], j[ok]))


def join_successors(lanes, successors) -> list[np.ndarray]:
    """Lanes moved so that every successor pair shares its joint point: the end of i and the start of j
    (and every other end or start linked to them) meet at their mean. Each lane takes its end's move
    in full at that end, fading linearly to none at its other end, so it bends without a kink."""
    lanes = [np.asarray(l, np.float64) for l in lanes]
    ports = UnionFind([(k, end) for k in range(len(lanes)) for end in (0, 1)])
    for i, j in successors:
        ports.union((int(i), 1), (int(j), 0))
    moves = {}
    for group in ports.groups():
        if len(group) > 1:
            points = np.array([lanes[k][-1 if end else 0] for k, end in group])
            for (k, end), p in zip(group, points):
                moves[(k, end)] = points.mean(axis=0) - p
    out = []
    for k, lane in enumerate(lanes):
        t = np.linspace(0.0, 1.0, len(lane))[:, None]
        out.append(lane + t * moves.get((k, 1), 0.0) + (1.0 - t) * moves.get((k, 0), 0.0))
    return out
