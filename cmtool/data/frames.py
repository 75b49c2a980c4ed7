"""Scene frames on an SD map: ego poses spread over the road network in a chosen mix of kinds, what
each frame shows, and per-frame statistics to compare SD maps of different sources.

**Poses** stand on a road's line (as an OpenStreetMap way runs), facing its travel direction (either
way, at random, on two-way roads). Candidates are drawn uniformly over road length, classified, and
taken in the shares of a :class:`FrameMix` of kinds while they keep ``min_spacing_m`` from each other;
kinds a map lacks leave their share to the others. The same sampler frames the training scenes of
an HD map (on its derived SD map) and a user's OpenStreetMap extract (``cmtool data poses``), so
both see the same kinds of frames.

**Kinds** (the first that applies, with the road graph of :mod:`cmtool.maps.roadgraph`):
``junction`` (a junction within ``JUNCTION_M`` of the ego; its sub-kind T/Y/X/multi/fork),
``approach`` / ``exit`` (a junction ahead of / behind the ego, in the frame), ``end`` (a dead end in
the frame), ``curve`` (the ego's road turns by ``CURVE_DEG`` or more within the frame), ``straight``.
Tags that may come on top: ``oneway``, ``divided`` (the ego's road is one carriageway of a divided
road), ``multilane`` (4 lanes or more on a two-way road, 2 or more on a one-way road or carriageway).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import shapely

from cmtool.core.geometry import from_frame, to_frame
from cmtool.data.scene import Pose
from cmtool.data.sd_derive import derive_sd
from cmtool.formats.mapfile import hd_map_of, map_kind
from cmtool.formats.osm import read_osm
from cmtool.maps.hdmap import HDMap
from cmtool.maps.roadgraph import RoadGraph, road_graph
from cmtool.maps.sdmap import SDMap

KINDS = ("junction", "approach", "exit", "end", "curve", "straight")
TAGS = ("oneway", "divided", "multilane")
JUNCTION_M = 16.0
CURVE_DEG = 20.0
FRAME_M = 64.0
_MIN_PIECE_M = 2.0  # clipped road pieces shorter than this are not counted as roads of a frame


@dataclass
class FrameMix:
    """Shares of the frame kinds in a dataset (recipe table ``[data.frame_mix]``); they need not sum
    to 1, and 0 leaves a kind out."""

    junction: float = 0.35
    approach: float = 0.15
    exit: float = 0.15
    end: float = 0.05
    curve: float = 0.1
    straight: float = 0.2

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in KINDS}


DEFAULT_MIX = FrameMix().as_dict()


@dataclass
class Frame:
    """An ego pose on an SD map and what its frame shows."""

    pose: Pose
    kind: str
    junction: str | None = None  # T, Y, X, multi, fork when kind == "junction"
    tags: tuple[str, ...] = ()
    road: int = -1  # index of the road the ego stands on
    junction_m: float = float("inf")  # distance to the nearest junction centre

    @property
    def label(self) -> str:
        return f"{self.kind} {self.junction}" if self.junction else self.kind


class FrameSampler:
    """Draws classified frames from one SD map (its road graph is built once)."""

    def __init__(self, sd: SDMap, frame_m: float = FRAME_M):
        self.sd, self.frame_m = sd, frame_m
        self.graph = road_graph(sd)
        self.lengths = shapely.length(self.graph.lines) if len(sd.roads) else np.zeros(0)

    def candidates(self, n: int, rng: np.random.Generator, roads: set[int] | None = None) -> list[Frame]:
        """``n`` classified poses drawn uniformly over the length of the roads (only of ``roads``, road
        indices, when given)."""
        lengths = self.lengths.copy()
        if roads is not None:
            lengths[np.setdiff1d(np.arange(len(lengths)), list(roads))] = 0.0
        total = float(lengths.sum())
        if n <= 0 or total <= 0:
            return []
        cum = np.cumsum(lengths)
        s = rng.uniform(0.0, total, size=n)
        road = np.minimum(np.searchsorted(cum, s, side="right"), len(cum) - 1)
        at = np.clip(s - (cum[road] - lengths[road]), 0.0, lengths[road])
        flip = rng.random(n) < 0.5
        return [self.classify(int(r), float(a), bool(f)) for r, a, f in zip(road, at, flip)]

    def classify(self, road: int, at: float, flip: bool = False) -> Frame:
        """The frame of the pose ``at`` metres along ``road``, facing its travel direction (two-way
        roads: against the polyline when ``flip``)."""
        line, info = self.graph.lines[road], self.sd.roads[road]
        backward = info.oneway == -1 or (info.oneway == 0 and flip)
        p0, p1 = (shapely.get_coordinates(shapely.line_interpolate_point(line, [at - 1.0, at + 1.0]))
                  if self.lengths[road] > 0 else (np.zeros(2), np.array([1.0, 0.0])))
        d = p0 - p1 if backward else p1 - p0
        here = shapely.get_coordinates(shapely.line_interpolate_point(line, at))[0]
        pose = Pose(float(here[0]), float(here[1]), float(np.arctan2(d[1], d[0])))
        kind, junction, junction_m = self._kind(pose, line, at)
        tags = []
        if info.oneway:
            tags.append("oneway")
        if self.graph.divided[road]:
            tags.append("divided")
        if info.lanes is not None and info.lanes >= (2 if info.oneway else 4):
            tags.append("multilane")
        return Frame(pose, kind, junction, tuple(tags), road, junction_m)

    def _kind(self, pose: Pose, line, at: float) -> tuple[str, str | None, float]:
        """Kind, junction kind and distance to the nearest junction of the frame at ``pose``."""
        half = self.frame_m / 2.0
        centres, nearest_m = self.graph.centres, float("inf")
        if len(centres):
            ego = to_frame(centres, pose.x, pose.y, pose.yaw)
            dist = np.linalg.norm(ego, axis=1)
            k = int(np.argmin(dist))
            nearest_m = float(dist[k])
            if dist[k] <= JUNCTION_M:
                return "junction", self.graph.junctions[k].kind, nearest_m
            inside = np.flatnonzero(np.all(np.abs(ego) <= half, axis=1))
            if len(inside):
                nearest = inside[np.argmin(dist[inside])]
                return ("approach" if ego[nearest, 0] > 0 else "exit"), None, nearest_m
        ends = self.graph.dead_ends
        if len(ends) and np.any(np.all(np.abs(to_frame(ends, pose.x, pose.y, pose.yaw)) <= half, axis=1)):
            return "end", None, nearest_m
        length = shapely.length(line)
        ahead = np.clip([at - half, at - half + 2.0, at + half - 2.0, at + half], 0.0, length)
        pts = shapely.get_coordinates(shapely.line_interpolate_point(line, ahead))
        d0, d1 = pts[1] - pts[0], pts[3] - pts[2]
        turn = abs(np.degrees(np.arctan2(d0[0] * d1[1] - d0[1] * d1[0], d0 @ d1)))
        return ("curve" if turn >= CURVE_DEG else "straight"), None, nearest_m

    def sample(self, n: int, rng: np.random.Generator, mix: dict[str, float] | None = None,
               min_spacing_m: float = 16.0, near_junction_m: float | None = None, roads: set[int] | None = None,
               oversample: int = 8) -> list[Frame]:
        """``n`` frames in the proportions of ``mix`` (default :data:`DEFAULT_MIX`; kinds it leaves out
        are not drawn), kept ``min_spacing_m`` apart while enough candidates are, optionally only within
        ``near_junction_m`` of a junction, or on ``roads``. Fewer than ``n`` only when the map has too
        few such places."""
        mix = DEFAULT_MIX if mix is None else mix
        pool = self.candidates(max(n * oversample, 64), rng, roads) if n > 0 else []
        pool = [f for f in pool if mix.get(f.kind, 0) > 0
                and (near_junction_m is None or f.junction_m <= near_junction_m)]
        return pick(pool, n, mix, min_spacing_m)


def hd_poses(hd: HDMap, n: int, rng: np.random.Generator, min_spacing_m: float = 16.0) -> list[Pose]:
    """``n`` ego poses on an HD map as the dataset frames its scenes (on its derived SD map)."""
    return [f.pose for f in FrameSampler(derive_sd(hd)).sample(n, rng, min_spacing_m=min_spacing_m)]


def pick(pool: list[Frame], n: int, mix: dict[str, float], min_spacing_m: float) -> list[Frame]:
    """Up to ``n`` frames from ``pool`` (in order) filling the quota of each kind, then any kind."""
    if not pool:
        return []
    have = Counter(f.kind for f in pool)
    weights = {k: w for k, w in mix.items() if have[k] and w > 0}
    total = sum(weights.values()) or 1.0
    quota = {k: int(np.ceil(n * w / total)) for k, w in weights.items()}
    taken, count = [], Counter()
    xy = np.array([[f.pose.x, f.pose.y] for f in pool])

    def spaced(i: int) -> bool:
        return not taken or np.min(np.linalg.norm(xy[taken] - xy[i], axis=1)) >= min_spacing_m

    for rule in ("quota", "spacing", "any"):
        for i, f in enumerate(pool):
            if len(taken) == n:
                break
            if i in taken or (rule != "any" and not spaced(i)):
                continue
            if rule == "quota" and count[f.kind] >= quota.get(f.kind, 0):
                continue
            taken.append(i)
            count[f.kind] += 1
    return [pool[i] for i in taken]


def label_order(label: str) -> tuple:
    """Sort key of frame labels and tags: kinds in :data:`KINDS` order (junctions by sub-kind), then tags."""
    kind, _, sub = label.partition(" ")
    known = KINDS + TAGS
    return (known.index(kind) if kind in known else len(known), sub, label)


def mix_table(frames: list[Frame]) -> dict[str, int]:
    """Counts per kind (junctions by sub-kind) and per tag, in :func:`label_order`."""
    counts = Counter(f.label for f in frames) + Counter(t for f in frames for t in f.tags)
    return {k: counts[k] for k in sorted(counts, key=label_order)}


def read_sd_source(path) -> SDMap:
    """The SD map of any map file cmtool reads (:mod:`cmtool.formats.mapfile`): OpenStreetMap ``.osm``/``.osm.pbf``
    and SD map JSON as they are, the others (HD maps, lane graphs) as the SD map derived from them."""
    kind, obj = map_kind(path)
    if kind == "osm":
        return read_osm(path)
    if kind == "sdmap":
        return SDMap.from_json(obj, where=str(path))
    return derive_sd(hd_map_of(path, kind, obj))


# ----------------------------------------------------------------------------- statistics

STAT_ROWS = {
    "roads": "roads per frame (road pieces between junctions)",
    "road_m": "road length per frame (m)",
    "oneway": "one-way share of road length",
    "divided": "divided-road share of road length",
    "lanes_known": "share of road length with a lane count",
    "major": "share of road length on tertiary or larger roads",
    "junctions": "junctions per frame",
}
SHARE_ROWS = ("oneway", "divided", "lanes_known", "major")
MAJOR_CLASSES = ("motorway", "trunk", "primary", "secondary", "tertiary")


def frame_stats(sd: SDMap, poses: list[Pose], graph: RoadGraph | None = None, frame_m: float = FRAME_M) -> dict:
    """Per-frame statistics of ``sd`` around ``poses`` (rows of :data:`STAT_ROWS`): counts and lengths
    are means per frame, shares are of the total road length in all frames."""
    graph = road_graph(sd) if graph is None else graph
    half = frame_m / 2.0
    corners = np.array([[half, half], [-half, half], [-half, -half], [half, -half]])
    flags = {"oneway": np.array([r.oneway != 0 for r in sd.roads], dtype=bool), "divided": graph.divided,
             "lanes_known": np.array([r.lanes is not None for r in sd.roads], dtype=bool),
             "major": np.array([r.road_class in MAJOR_CLASSES for r in sd.roads], dtype=bool)}
    tree = shapely.STRtree(graph.lines)
    sums = Counter()
    for pose in poses:
        square = shapely.Polygon(from_frame(corners, pose.x, pose.y, pose.yaw))
        near = tree.query(square, predicate="intersects")
        parts, src = shapely.get_parts(shapely.intersection(graph.lines[near], square), return_index=True)
        lengths = shapely.length(parts)
        keep = lengths >= _MIN_PIECE_M
        road = near[src]
        inside = _count_inside(square, graph.passes) - _count_inside(square, graph.joins)
        sums["roads"] += max(0, int(keep.sum()) + inside)
        sums["road_m"] += lengths.sum()
        for key, flag in flags.items():
            sums[key] += lengths[flag[road]].sum()
        sums["junctions"] += _count_inside(square, graph.centres)
    n, metres = max(len(poses), 1), max(sums["road_m"], 1e-9)
    return {"frames": len(poses)} | {k: sums[k] / (metres if k in SHARE_ROWS else n) for k in STAT_ROWS}


def _count_inside(square, points: np.ndarray) -> int:
    if len(points) == 0:
        return 0
    return int(np.sum(shapely.contains_xy(square, points[:, 0], points[:, 1])))
