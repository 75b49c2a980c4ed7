"""Scenes: 64 m crops of an HD map around an ego pose, as fixed-size SLEDGE-style vectors.

A scene holds the drivable lane centerlines (vehicle and bus lanes, intersection connectors
included) in the ego frame (x forward, y left), clipped to the square frame and split where a
lane leaves and re-enters it. Pieces shorter than ``min_piece_m`` are dropped; the ``num_lines``
pieces nearest the ego are kept, nearest first, each resampled to ``num_points`` points, and the
scene counts the pieces this cap drops (``cut``).
Successor edges survive clipping: piece p -> piece q when p ends where its lane ends, q starts
where its lane starts and the lanes are successors. Traffic-light lines are the pieces of the
lanes that green / red stop lines control, nearest first, up to ``num_lights`` per state.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import shapely

from cmtool.core.geometry import from_frame, resample, to_frame
from cmtool.maps.hdmap import HDMap
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.neighbours import find_neighbours

DRIVABLE = ("vehicle", "bus")
_END_TOL_M = 1e-3  # a clipped piece within this of its lane's end keeps that end


@dataclass
class Pose:
    x: float
    y: float
    yaw: float  # radians, world frame

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.yaw], dtype=np.float64)


@dataclass
class Scene:
    """Fixed-size scene vectors (padded; valid entries first) plus where they came from."""

    lines: np.ndarray  # (L, P, 2) float32, ego frame metres
    line_mask: np.ndarray  # (L,) bool
    edges: np.ndarray  # (E, 2) int64, indices into lines
    green: np.ndarray  # (K, P, 2) float32
    green_mask: np.ndarray  # (K,) bool
    red: np.ndarray  # (K, P, 2) float32
    red_mask: np.ndarray  # (K,) bool
    city: str
    source: str
    pose: Pose
    frame_m: float = 64.0
    sd: np.ndarray | None = None  # (128, 128, 3) uint8 SD raster of the same frame, when paired
    cut: int = 0  # lane pieces beyond num_lines, dropped by the cap
    kind: str = ""  # what the frame shows (cmtool.data.frames: "junction T", "straight", ...), when known
    tags: str = ""  # comma-separated frame tags (oneway, divided, multilane)
    widths: np.ndarray | None = None  # (L,) lane widths of the source, when cropped from an HD map
    neighbors: np.ndarray | None = None  # (E, 2) line pairs the source records as neighbours (either order)

    def to_lanegraph(self, neighbours: bool = True) -> LaneGraph:
        """The scene in the lane graph interchange format (cmtool.maps.lanegraph), with the source's
        lane neighbours and widths when it was cropped from an HD map, else neighbours from geometry;
        ``neighbours`` False: none recorded (for a caller that needs the lanes alone, as finding them takes long)."""
        lanes = [l.astype(np.float64) for l in self.lines[self.line_mask]]
        widths = None if self.widths is None else self.widths[self.line_mask]
        recorded = None if self.neighbors is None else self.neighbors.tolist()
        left, oncoming = find_neighbours(lanes, widths, recorded) if neighbours else (None, None)
        return LaneGraph(
            lanes=lanes,
            successors=[(int(i), int(j)) for i, j in self.edges],
            left_neighbors=left,
            oncoming=oncoming,
            widths=None if widths is None else [float(w) for w in widths],
            green_lights=[l.astype(np.float64) for l in self.green[self.green_mask]],
            red_lights=[l.astype(np.float64) for l in self.red[self.red_mask]],
            city=self.city,
            frame_m=self.frame_m,
            meta={"source": self.source, "pose": [round(float(v), 4) for v in self.pose.as_array()]},
        )


def drivable_lanes(hd: HDMap) -> list:
    return [lane for lane in hd.lanes.values() if lane.lane_type in DRIVABLE]


class SceneCropper:
    """Crops scenes out of one HD map (the map's lane geometry is indexed once)."""

    def __init__(self, hd: HDMap):
        self.hd = hd
        self.lanes = drivable_lanes(hd)
        self.index = {lane.id: i for i, lane in enumerate(self.lanes)}
        self.geoms = np.array([shapely.LineString(lane.centerline) for lane in self.lanes], dtype=object)
        self.lengths = shapely.length(self.geoms)
        self.bounds = np.array([(*l.centerline.min(0), *l.centerline.max(0)) for l in self.lanes]).reshape(-1, 4)
        self.successors = [[self.index[s] for s in lane.successors if s in self.index] for lane in self.lanes]
        self.neighbors = [{self.index[n] for n in (lane.left_neighbor, lane.right_neighbor) if n in self.index}
                          for lane in self.lanes]
        self.widths = np.array([lane.width for lane in self.lanes], np.float32)
        self.lights = {
            state: {self.index[i] for sl in hd.stop_lines if sl.state == state for i in sl.lane_ids if i in self.index}
            for state in ("green", "red")
        }

    def extract(self, pose: Pose, num_lines: int = 50, num_points: int = 20, num_lights: int = 10,
                frame_m: float = 64.0, min_piece_m: float = 2.0) -> Scene:
        lane_of, lines, at_start, at_end = self._pieces(pose, frame_m / 2.0, min_piece_m)
        kept = range(min(len(lines), num_lines))
        out = np.zeros((num_lines, num_points, 2), np.float32)
        for k in kept:
            out[k] = resample(lines[k], num_points)
        mask = np.arange(num_lines) < len(kept)

        starting = {lane_of[k]: k for k in kept if at_start[k]}
        edges = [
            (k, starting[s])
            for k in kept if at_end[k]
            for s in self.successors[lane_of[k]] if s in starting and s != lane_of[k]
        ]

        lights = {}
        for state in ("green", "red"):
            arr = np.zeros((num_lights, num_points, 2), np.float32)
            m = np.zeros(num_lights, bool)
            chosen = [k for k in range(len(lines)) if lane_of[k] in self.lights[state]][:num_lights]
            for row, k in enumerate(chosen):
                arr[row] = resample(lines[k], num_points)
                m[row] = True
            lights[state] = (arr, m)

        widths = np.full(num_lines, 3.5, np.float32)
        widths[list(kept)] = self.widths[[lane_of[k] for k in kept]]
        pieces = defaultdict(list)  # lane -> its kept pieces
        for k in kept:
            pieces[lane_of[k]].append(k)
        beside = sorted({(min(k, l), max(k, l)) for k in kept for n in self.neighbors[lane_of[k]] for l in pieces[n]})
        return Scene(
            lines=out, line_mask=mask, edges=np.array(edges, np.int64).reshape(-1, 2),
            widths=widths, neighbors=np.array(beside, np.int64).reshape(-1, 2) if any(self.neighbors) else None,
            green=lights["green"][0], green_mask=lights["green"][1],
            red=lights["red"][0], red_mask=lights["red"][1],
            city=self.hd.city, source=self.hd.source, pose=pose, frame_m=frame_m, cut=len(lines) - len(kept),
        )

    def _pieces(self, pose: Pose, half: float, min_piece_m: float):
        """Clipped lane pieces in the ego frame, nearest the ego first.

        Returns (lane index per piece, (N_k, 2) ego-frame polylines, starts-at-lane-start flags,
        ends-at-lane-end flags).
        """
        reach = half * np.sqrt(2.0)
        near = np.flatnonzero(
            (self.bounds[:, 0] <= pose.x + reach) & (self.bounds[:, 2] >= pose.x - reach)
            & (self.bounds[:, 1] <= pose.y + reach) & (self.bounds[:, 3] >= pose.y - reach)
        )
        if len(near) == 0:
            return [], [], [], []
        corners = np.array([[half, half], [-half, half], [-half, -half], [half, -half]])
        square = shapely.Polygon(from_frame(corners, pose.x, pose.y, pose.yaw))
        parts, src = shapely.get_parts(shapely.intersection(self.geoms[near], square), return_index=True)
        keep = (shapely.get_type_id(parts) == 1) & (shapely.length(parts) >= max(min_piece_m, 1e-9))
        parts, lane_idx = parts[keep], near[src[keep]]
        if len(parts) == 0:
            return [], [], [], []

        coords, owner = shapely.get_coordinates(parts, return_index=True)
        first = np.searchsorted(owner, np.arange(len(parts)))
        last = np.append(first[1:], len(owner)) - 1
        s0 = shapely.line_locate_point(self.geoms[lane_idx], shapely.points(coords[first]))
        s1 = shapely.line_locate_point(self.geoms[lane_idx], shapely.points(coords[last]))
        flipped = s1 < s0
        lo, hi = np.minimum(s0, s1), np.maximum(s0, s1)
        at_start = lo <= _END_TOL_M
        at_end = hi >= self.lengths[lane_idx] - _END_TOL_M

        dist = shapely.distance(parts, shapely.Point(pose.x, pose.y))
        order = np.lexsort((lo, lane_idx, dist))
        local = np.clip(to_frame(coords, pose.x, pose.y, pose.yaw), -half, half)
        lines = []
        for k in order:
            line = local[first[k]: last[k] + 1]
            lines.append(line[::-1] if flipped[k] else line)
        return lane_idx[order].tolist(), lines, at_start[order], at_end[order]


def extract_scene(hd: HDMap, pose: Pose, num_lines: int = 50, num_points: int = 20, num_lights: int = 10,
                  frame_m: float = 64.0, min_piece_m: float = 2.0) -> Scene:
    """Crop one scene around ``pose`` (see :class:`SceneCropper` to crop many from one map)."""
    return SceneCropper(hd).extract(pose, num_lines, num_points, num_lights, frame_m, min_piece_m)
