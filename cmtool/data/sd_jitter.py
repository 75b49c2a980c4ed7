"""The imperfections of real OpenStreetMap, applied to a derived SD map so training sees SD maps as
users have them.

Measured against a real extract in ``docs/data-realism.md``. Applied in this order, all drawn from
one seed (deterministic):

1. ``drop_minor``: each minor road (residential, service, unclassified) is missing with this
   probability.
2. ``lanes_known_major`` / ``lanes_known_minor``: the probability that a road keeps its ``lanes``
   tag (tertiary and up / minor roads); mappers leave it out on most streets.
3. ``service_stubs_per_km``: short service ways (driveways, parking aisles) that OSM maps and HD
   maps have no lanes for, branching off roads at a shared node.
4. ``simplify_m``: polylines between nodes simplified to within this many metres (mappers draw
   curves with few nodes).
5. ``wobble_m``: a smooth random displacement field (RMS ``wobble_m``, wavelength
   ``wobble_wavelength_m``) moves every point, so roads are off by a slowly varying amount and
   points shared by roads stay shared; then a rotation of up to ``rotation_deg`` about the map
   centre and a shift of up to ``offset_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import shapely

from cmtool.core.geometry import from_frame, insert_vertex
from cmtool.maps.sdmap import Road, SDMap

MINOR_CLASSES = ("residential", "service", "unclassified")
_STUB_M = (15.0, 40.0)  # length range of a service stub
_STUB_CLEAR_M = 8.0  # a stub keeps this far from every other road


@dataclass
class SDJitter:
    """How far a derived SD map is made to look like real OSM (see the module doc; defaults: off)."""

    offset_m: float = 0.0
    rotation_deg: float = 0.0
    drop_minor: float = 0.0
    wobble_m: float = 0.0
    wobble_wavelength_m: float = 120.0
    simplify_m: float = 0.0
    lanes_known_major: float = 1.0
    lanes_known_minor: float = 1.0
    service_stubs_per_km: float = 0.0

    @property
    def enabled(self) -> bool:
        return (self.offset_m > 0 or self.rotation_deg > 0 or self.drop_minor > 0 or self.wobble_m > 0
                or self.simplify_m > 0 or self.lanes_known_major < 1 or self.lanes_known_minor < 1
                or self.service_stubs_per_km > 0)

    def problems(self) -> list[str]:
        """What is out of range, as ``field: reason`` strings (empty when all is well)."""
        out = [f"{k}: must be a finite number >= 0" for k, v in vars(self).items()
               if not (np.isfinite(v) and v >= 0)]
        out += [f"{k}: must be a probability in [0, 1]" for k in ("drop_minor", "lanes_known_major",
                                                                   "lanes_known_minor")
                if np.isfinite(getattr(self, k)) and getattr(self, k) > 1]
        if self.wobble_wavelength_m <= 0:
            out.append("wobble_wavelength_m: must be positive")
        return out


def apply_jitter(sd: SDMap, jitter: SDJitter, seed: int = 0) -> SDMap:
    """``sd`` with the imperfections of ``jitter`` (module doc), drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    draws = rng.random((len(sd.roads), 2))  # fixed draws per road: a setting changes only its own effect
    roads = []
    for road, (drop, known) in zip(sd.roads, draws):
        minor = road.road_class in MINOR_CLASSES
        if minor and drop < jitter.drop_minor:
            continue
        keep_lanes = known < (jitter.lanes_known_minor if minor else jitter.lanes_known_major)
        roads.append(replace(road, polyline=np.asarray(road.polyline, np.float64),
                             lanes=road.lanes if keep_lanes else None))
    if not roads:
        return SDMap(sd.city, [], sd.source, dict(sd.meta))
    roads = _add_stubs(roads, jitter.service_stubs_per_km, rng)
    if jitter.simplify_m > 0:
        roads = _simplify(roads, jitter.simplify_m)
    pts = np.concatenate([r.polyline for r in roads])
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2.0
    field = _wobble_field(jitter.wobble_m, jitter.wobble_wavelength_m, rng)
    angle = np.radians(rng.uniform(-1.0, 1.0) * jitter.rotation_deg)
    direction, radius = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(0.0, 1.0) * jitter.offset_m
    shift = radius * np.array([np.cos(direction), np.sin(direction)])
    moved = [replace(r, polyline=from_frame(field(r.polyline) - centre, 0.0, 0.0, angle) + centre + shift)
             for r in roads]
    return SDMap(sd.city, moved, sd.source, dict(sd.meta))


def _wobble_field(rms: float, wavelength: float, rng: np.random.Generator, waves: int = 4):
    """A smooth random displacement ``p -> p + d(p)``: a sum of plane waves with RMS ``rms``."""
    theta = rng.uniform(0.0, 2.0 * np.pi, waves)  # direction the wave varies along
    phi = rng.uniform(0.0, 2.0 * np.pi, waves)  # direction it displaces towards
    phase = rng.uniform(0.0, 2.0 * np.pi, waves)
    length = wavelength * rng.uniform(0.7, 1.4, waves)
    k = np.stack([np.cos(theta), np.sin(theta)], axis=1) * (2.0 * np.pi / length)[:, None]
    u = np.stack([np.cos(phi), np.sin(phi)], axis=1) * rms * np.sqrt(2.0 / waves)

    def field(points: np.ndarray) -> np.ndarray:
        return points + np.sin(points @ k.T + phase) @ u

    return field


def _add_stubs(roads: list[Road], per_km: float, rng: np.random.Generator) -> list[Road]:
    """Service stubs branching off roads at a right angle (give or take 20 degrees), at shared nodes."""
    lengths = np.array([shapely.length(shapely.LineString(r.polyline)) for r in roads])
    count = rng.poisson(per_km * lengths.sum() / 1000.0) if per_km > 0 else 0
    if count == 0:
        return roads
    lines = [shapely.LineString(r.polyline) for r in roads]
    tree = shapely.STRtree(lines)
    roads = list(roads)
    for k in range(count):
        i = int(rng.choice(len(lines), p=lengths / lengths.sum()))
        at = rng.uniform(0.0, lengths[i])
        side, turn, size = rng.choice([-1.0, 1.0]), np.radians(rng.uniform(-20.0, 20.0)), rng.uniform(*_STUB_M)
        if not _STUB_M[0] <= at <= lengths[i] - _STUB_M[0]:
            continue
        p0, p1 = shapely.get_coordinates(shapely.line_interpolate_point(lines[i], [at - 1.0, at + 1.0]))
        root = shapely.get_coordinates(shapely.line_interpolate_point(lines[i], at))[0]
        d = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-9)
        normal = side * np.array([-d[1], d[0]])
        out = np.cos(turn) * normal + np.sin(turn) * d
        stub = np.array([root, root + size * out])
        probe = shapely.LineString([root + (_STUB_CLEAR_M + 1.0) * out, stub[1]])
        if len(tree.query(probe, predicate="dwithin", distance=_STUB_CLEAR_M)) or _hits_stub(probe, roads[len(lines):]):
            continue
        roads[i] = replace(roads[i], polyline=insert_vertex(roads[i].polyline, root)[0])
        roads.append(Road(f"s{k}", stub, "service", None, 0))
    return roads


def _hits_stub(probe, stubs: list[Road]) -> bool:
    return any(shapely.dwithin(probe, shapely.LineString(s.polyline), _STUB_CLEAR_M) for s in stubs)


def _simplify(roads: list[Road], tolerance: float) -> list[Road]:
    """Each road simplified between its nodes (its ends and points shared with other roads)."""
    keys = [np.round(r.polyline * 1000.0).astype(np.int64) for r in roads]
    uniq, inverse = np.unique(np.concatenate(keys), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    owners = np.zeros(len(uniq), dtype=np.int64)
    np.add.at(owners, inverse, 1)
    out, start = [], 0
    for road, key in zip(roads, keys):
        shared = owners[inverse[start:start + len(key)]] > 1
        start += len(key)
        cuts = np.flatnonzero(shared)
        cuts = np.unique(np.concatenate([[0, len(key) - 1], cuts]))
        parts = [shapely.get_coordinates(shapely.simplify(shapely.LineString(road.polyline[a:b + 1]), tolerance))
                 for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
        line = np.concatenate([parts[0]] + [p[1:] for p in parts[1:]]) if parts else road.polyline
        out.append(replace(road, polyline=line))
    return out
