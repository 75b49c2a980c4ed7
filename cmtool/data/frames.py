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

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.spatial import cKDTree

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

    def classify(self, road: int, at: float, flip: bool = False) -> Frame:
        """The frame of the pose ``at`` metres along ``road``, facing its travel direction (two-way
        roads: against the polyline when ``flip``)."""
        return self._frames(self._classify(np.array([road]), np.array([at], np.float64), np.array([flip])), [0])[0]

    def _candidates(self, n: int, rng: np.random.Generator, roads: set[int] | None) -> list[np.ndarray] | None:
        """``n`` poses drawn uniformly over the length of the roads (only of ``roads``, road indices, when given),
        classified (:meth:`_classify`); None when there is no road to draw from."""
        lengths = self.lengths.copy()
        if roads is not None:
            lengths[np.setdiff1d(np.arange(len(lengths)), list(roads))] = 0.0
        total = float(lengths.sum())
        if n <= 0 or total <= 0:
            return None
        cum = np.cumsum(lengths)
        s = rng.uniform(0.0, total, size=n)
        road = np.minimum(np.searchsorted(cum, s, side="right"), len(cum) - 1)
        at = np.clip(s - (cum[road] - lengths[road]), 0.0, lengths[road])
        return self._classify(road, at, rng.random(n) < 0.5)

    def _classify(self, road: np.ndarray, at: np.ndarray, flip: np.ndarray) -> list[np.ndarray]:
        """:meth:`classify` of many poses (arrays of roads, metres along them and flips) as columns: places, yaws,
        roads, kinds, junction kinds and distances to the nearest junction."""
        lines, length = np.asarray(self.graph.lines, object)[road], self.lengths[road]
        oneway = np.array([r.oneway for r in self.sd.roads])[road]
        ahead = shapely.get_coordinates(shapely.line_interpolate_point(lines[:, None], at[:, None] + [-1.0, 1.0]))
        d = np.where((length > 0)[:, None], ahead[1::2] - ahead[0::2], [1.0, 0.0])
        d[(oneway == -1) | ((oneway == 0) & flip)] *= -1.0
        xy, yaw = shapely.get_coordinates(shapely.line_interpolate_point(lines, at)), np.arctan2(d[:, 1], d[:, 0])
        return [xy, yaw, road, *self._kinds(xy, yaw, lines, at, length)]

    def _frames(self, columns: list[np.ndarray], rows) -> list[Frame]:
        """The frames of some ``rows`` of :meth:`_classify`'s columns."""
        tags = [tuple(t for t, on in (("oneway", r.oneway), ("divided", self.graph.divided[k]),
                                      ("multilane", r.lanes is not None and r.lanes >= (2 if r.oneway else 4))) if on)
                for k, r in enumerate(self.sd.roads)]
        xy, yaw, road, kind, junction, junction_m = (c[rows] for c in columns)
        return [Frame(Pose(float(p[0]), float(p[1]), float(a)), k, j, tags[r], int(r), float(m))
                for p, a, r, k, j, m in zip(xy, yaw, road, kind, junction, junction_m)]

    def _kinds(self, xy: np.ndarray, yaw: np.ndarray, lines: np.ndarray, at: np.ndarray,
               length: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Kinds, junction kinds and distances to the nearest junction of the frames at ``xy`` facing ``yaw``."""
        half, n, centres = self.frame_m / 2.0, len(xy), self.graph.centres
        kind, junction, nearest_m = np.full(n, "", object), np.full(n, None, object), np.full(n, np.inf)
        if len(centres):  # the nearest centre, taken (of the two nearest) as the ego frame measures it
            near = np.sort(cKDTree(centres).query(xy, k=min(2, len(centres)))[1].reshape(n, -1), axis=1)
            dist = np.linalg.norm(to_frame(centres[near], xy[:, :1], xy[:, 1:], yaw[:, None]), axis=-1)
            k, nearest_m = near[np.arange(n), dist.argmin(axis=1)], dist.min(axis=1)
            hub = nearest_m <= JUNCTION_M
            kind[hub] = "junction"
            junction[hub] = [self.graph.junctions[j].kind for j in k[hub]]
            i, j, ego = _in_frame(centres, xy, yaw, half, ~hub)
            first = np.lexsort((j, np.linalg.norm(ego, axis=1), i))  # by pose, then the nearest centre
            first = first[np.r_[True, i[first][1:] != i[first][:-1]]] if len(i) else first
            kind[i[first]] = np.where(ego[first, 0] > 0, "approach", "exit")
        kind[_in_frame(self.graph.dead_ends, xy, yaw, half, kind == "")[0]] = "end"
        rest = np.flatnonzero(kind == "")
        ahead = np.clip(at[rest, None] + [-half, -half + 2.0, half - 2.0, half], 0.0, length[rest, None])
        p = shapely.get_coordinates(shapely.line_interpolate_point(lines[rest, None], ahead)).reshape(-1, 4, 2)
        d0, d1 = p[:, 1] - p[:, 0], p[:, 3] - p[:, 2]
        turn = np.abs(np.degrees(np.arctan2(d0[:, 0] * d1[:, 1] - d0[:, 1] * d1[:, 0], (d0 * d1).sum(axis=1))))
        kind[rest] = np.where(turn >= CURVE_DEG, "curve", "straight")
        return kind, junction, nearest_m

    def sample(self, n: int, rng: np.random.Generator, mix: dict[str, float] | None = None,
               min_spacing_m: float = 16.0, near_junction_m: float | None = None, roads: set[int] | None = None,
               oversample: int = 8) -> list[Frame]:
        """``n`` frames in the proportions of ``mix`` (default :data:`DEFAULT_MIX`; kinds it leaves out
        are not drawn), kept ``min_spacing_m`` apart while enough candidates are, optionally only within
        ``near_junction_m`` of a junction, or on ``roads``. Fewer than ``n`` only when the map has too
        few such places."""
        mix = DEFAULT_MIX if mix is None else mix
        pool = self._candidates(max(n * oversample, 64), rng, roads) if n > 0 else None
        if pool is None:
            return []
        xy, _, _, kind, _, junction_m = pool
        ok = np.array([mix.get(k, 0) > 0 for k in kind], bool)
        if near_junction_m is not None:
            ok &= junction_m <= near_junction_m
        ok = np.flatnonzero(ok)
        return self._frames(pool, ok[pick(kind[ok], xy[ok], n, mix, min_spacing_m)])


def _in_frame(points: np.ndarray, xy: np.ndarray, yaw: np.ndarray, half: float, which: np.ndarray):
    """The pairs (pose ``i``, point ``j``) of the poses ``which`` selects and the points in their frames (squares of
    side ``2 * half`` about ``xy`` facing ``yaw``), and the points in those frames' coordinates."""
    if not len(points) or not which.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    poses = np.flatnonzero(which)
    reach = half * np.sqrt(2.0) + 1e-6  # a frame's corner, and some
    pairs = cKDTree(xy[poses]).sparse_distance_matrix(cKDTree(points), reach, output_type="ndarray")
    i, j = poses[pairs["i"]], pairs["j"].astype(np.int64)
    ego = to_frame(points[j], xy[i, 0], xy[i, 1], yaw[i])
    inside = np.all(np.abs(ego) <= half, axis=1)
    return i[inside], j[inside], ego[inside]


def hd_poses(hd: HDMap, n: int, rng: np.random.Generator, min_spacing_m: float = 16.0) -> list[Pose]:
    """``n`` ego poses on an HD map as the dataset frames its scenes (on its derived SD map)."""
    return [f.pose for f in FrameSampler(derive_sd(hd)).sample(n, rng, min_spacing_m=min_spacing_m)]


def pick(kinds: np.ndarray, xy: np.ndarray, n: int, mix: dict[str, float], min_spacing_m: float) -> list[int]:
    """Up to ``n`` of the frames of ``kinds`` at ``xy`` (their indices, in order) filling the quota of each kind, then
    any kind."""
    if not len(kinds):
        return []
    have = Counter(kinds)
    weights = {k: w for k, w in mix.items() if have[k] and w > 0}
    total = sum(weights.values()) or 1.0
    quota = {k: int(np.ceil(n * w / total)) for k, w in weights.items()}
    taken, count, chosen, crowded = [], Counter(), [False] * len(kinds), [False] * len(kinds)
    cell = 1.01 * min_spacing_m  # a taken frame in a cell that does not touch the frame's own lies farther away
    cells = list(zip(*np.floor(xy / cell).astype(np.int64).T.tolist())) if min_spacing_m > 0 else None
    points, grid, around = xy.tolist(), {}, [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]

    def spaced(i: int) -> bool:
        if cells is None or crowded[i]:  # once too near a taken frame, always so
            return cells is None
        (x, y), (cx, cy) = points[i], cells[i]
        for dx, dy in around:
            for tx, ty in grid.get((cx + dx, cy + dy), ()):
                ex, ey = tx - x, ty - y
                if math.sqrt(ex * ex + ey * ey) < min_spacing_m:
                    crowded[i] = True
                    return False
        return True

    for rule in ("quota", "spacing", "any"):
        for i, kind in enumerate(kinds):
            if len(taken) == n:
                break
            if chosen[i] or (rule == "quota" and count[kind] >= quota.get(kind, 0)) or (rule != "any" and
                                                                                        not spaced(i)):
                continue
            taken.append(i)
            chosen[i] = True
            count[kind] += 1
            if cells is not None:
                grid.setdefault(cells[i], []).append(points[i])
    return taken


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
