"""The road level of a procedural city: a planar graph of road axes between nodes.

A (rotated, jittered, smoothly warped) street grid with optional diagonal streets is clipped to the
map square; acute arms and a style-dependent share of crossings are dropped, straight-through
degree-2 nodes are merged away, some roads are bent, and every road end gets a setback that leaves
room for the intersection. Roads whose lane corridors would overlap are dropped until none do.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cmtool.core.geometry import arc_length, resample_step, unit
from cmtool.data.synth.curves import bend, cut, point_and_tangent, round_corner
from cmtool.data.synth.styles import Style

MIN_ANGLE = np.radians(30.0)  # arms meeting at a node closer than this are not allowed
HAIRPIN = np.radians(60.0)  # degree-2 nodes whose arms meet closer than this are removed
MERGE_DEFLECTION = np.radians(40.0)  # degree-2 nodes bending less than this are merged away
MARGIN = 3.0  # gap between a road's lanes and the crossing road's edge (m)
TURN_RADIUS = 6.0  # smallest radius of a turn between two arms of a junction (m)
MAX_TURN = np.radians(135.0)  # sharper turns between two arms of a junction get no connector
CROSSWALK = 3.0  # crosswalk depth (m)
MIN_LANE = 8.0  # shortest road lane kept (m)


@dataclass(eq=False)
class Road:
    line: np.ndarray  # axis polyline from node u to node v
    u: int
    v: int
    lanes: int  # lanes per travelled direction
    oneway: int  # 0 two-way, +1 only u -> v, -1 only v -> u
    width: float  # lane width (m)
    median: float  # gap between the two directions (m)
    arterial: bool
    bus: bool  # outermost lanes are bus lanes
    setback: tuple[float, float] = (0.0, 0.0)  # where lanes stop short of u and of v (m)

    @property
    def length(self) -> float:
        return float(arc_length(self.line)[-1])

    @property
    def half_width(self) -> float:
        if self.oneway:
            return self.lanes * self.width / 2
        return self.median / 2 + self.lanes * self.width

    def reversed(self) -> Road:
        return replace(self, line=self.line[::-1].copy(), u=self.v, v=self.u, oneway=-self.oneway,
                       setback=self.setback[::-1])

    def other(self, node: int) -> int:
        return self.v if node == self.u else self.u

    def direction_at(self, node: int, reach: float = 8.0) -> np.ndarray:
        """Unit direction of the arm leaving ``node`` (over its first ``reach`` metres)."""
        line = self.line if node == self.u else self.line[::-1]
        p, _ = point_and_tangent(line, min(reach, arc_length(line)[-1]))
        return unit(p - line[0])

    def flows_in(self, node: int) -> bool:
        return self.oneway == 0 or self.oneway == (1 if node == self.v else -1)

    def flows_out(self, node: int) -> bool:
        return self.oneway == 0 or self.oneway == (1 if node == self.u else -1)

    def set_setback(self, node: int, s: float) -> None:
        self.setback = (s, self.setback[1]) if node == self.u else (self.setback[0], s)


@dataclass
class Network:
    nodes: np.ndarray  # (N, 2) node positions; some may be unused
    roads: list[Road]
    signals: set[int]  # nodes with traffic lights
    crosswalks: set[int]  # nodes with crosswalks on every arm


def build_network(style: Style, rng: np.random.Generator, extent: float) -> Network:
    nodes, roads = _grid(style, rng, extent)
    roads = _clip(nodes, roads, extent)
    roads = _drop_acute(roads)
    roads = _drop_crossings(style, rng, roads)
    roads = _merge_straight(_prune_dead_ends(_largest_component(roads), extent))
    _bend(style, rng, roads)
    draws = rng.random((len(nodes), 2))
    while True:
        _fix_one_way(roads)
        degree = {n: len(rs) for n, rs in _incidence(roads).items()}
        signals = {n for n, d in degree.items() if d >= 3 and draws[n, 0] < style.signal}
        crosswalks = signals | {n for n, d in degree.items() if d >= 3 and draws[n, 1] < style.crosswalk}
        _set_setbacks(roads, crosswalks)
        bad = _conflicts(roads)
        if not bad:
            return Network(np.array(nodes), roads, signals, crosswalks)
        roads = _prune_dead_ends(_largest_component([r for i, r in enumerate(roads) if i not in bad]), extent)


# ---------------------------------------------------------------- grid


def _grid(style: Style, rng: np.random.Generator, extent: float) -> tuple[list, list[Road]]:
    """Jittered, rotated and warped grid of streets around the map centre (not yet clipped)."""
    reach = 0.75 * extent + style.block[1] + style.warp
    xs, ys = _positions(rng, style.block, reach), _positions(rng, style.block, reach)
    nx, ny = len(xs), len(ys)
    local = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    lim = style.block[0] / 4
    local += np.clip(rng.normal(0.0, style.jitter, local.shape), -lim, lim)
    theta = np.radians(rng.uniform(-style.rotation, style.rotation))
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    flat = local @ rot.T + extent / 2
    warp = _warp(style, rng)
    nodes = list(warp(flat))

    roads: list[Road] = []

    def add(a: int, b: int, attrs: dict) -> None:
        line = warp(resample_step(np.stack([flat[a], flat[b]]), 5.0))
        line[0], line[-1] = nodes[a], nodes[b]
        roads.append(Road(line=line, u=a, v=b, **attrs))

    art_x, art_y = _arterials(rng, style, nx), _arterials(rng, style, ny)
    for j in range(ny):
        attrs = _street(style, rng, j in art_y)
        for i in range(nx - 1):
            add(i * ny + j, (i + 1) * ny + j, attrs)
    for i in range(nx):
        attrs = _street(style, rng, i in art_x)
        for j in range(ny - 1):
            add(i * ny + j, i * ny + j + 1, attrs)
    used_blocks = set()
    ic, jc = int(np.argmin(np.abs(xs))), int(np.argmin(np.abs(ys)))
    for _ in range(style.diagonals):
        sign, shift = rng.choice([-1, 1]), int(rng.integers(-2, 3))
        attrs = _street(style, rng, False)
        for i in range(nx - 1):
            j0 = jc + shift + sign * (i - ic)
            j1 = j0 + sign
            block = (i, min(j0, j1))
            if 0 <= min(j0, j1) and max(j0, j1) < ny and block not in used_blocks:
                used_blocks.add(block)
                add(i * ny + j0, (i + 1) * ny + j1, attrs)
    return nodes, roads


def _positions(rng: np.random.Generator, block: tuple[float, float], reach: float) -> np.ndarray:
    """Street positions along one axis: a street near 0, then random block lengths both ways."""
    pos = [rng.uniform(-block[0] / 3, block[0] / 3)]
    while pos[-1] < reach:
        pos.append(pos[-1] + rng.uniform(*block))
    while pos[0] > -reach:
        pos.insert(0, pos[0] - rng.uniform(*block))
    return np.array(pos)


def _arterials(rng: np.random.Generator, style: Style, n: int) -> set[int]:
    lo, hi = style.arterial_every
    if lo == 0:
        return set()
    out, k = set(), int(rng.integers(0, hi))
    while k < n:
        out.add(k)
        k += int(rng.integers(lo, hi + 1))
    return out


def _street(style: Style, rng: np.random.Generator, arterial: bool) -> dict:
    """Attributes shared by all edges of one street."""
    oneway = 0
    if not arterial and rng.random() < style.one_way:
        oneway = int(rng.choice([-1, 1]))
        lanes = rng.integers(style.one_way_lanes[0], style.one_way_lanes[1] + 1)
    else:
        lo, hi = style.arterial_lanes if arterial else style.local_lanes
        lanes = rng.integers(lo, hi + 1)
    median = rng.uniform(*style.median) if arterial and not oneway else 0.0
    bus = bool(arterial and lanes >= 2 and rng.random() < style.bus)
    return dict(lanes=int(lanes), oneway=oneway, width=float(rng.uniform(*style.width)),
                median=float(median), arterial=arterial, bus=bus)


def _warp(style: Style, rng: np.random.Generator):
    """A smooth map of the plane (two sine waves) that bends whole streets."""
    k = 2 * np.pi / style.warp_wavelength
    dirs = unit(rng.normal(size=(2, 2)))
    phase = rng.uniform(0.0, 2 * np.pi, 2)
    return lambda p: p + style.warp * np.sin(k * (p @ dirs.T) + phase)


# ---------------------------------------------------------------- topology clean-up


def _clip(nodes: list, roads: list[Road], extent: float) -> list[Road]:
    """Keep roads with an end inside the square, cutting those that leave it at the border
    (their border end becomes a new dead-end node)."""
    pts = np.array(nodes)
    inside = ((pts > 0) & (pts < extent)).all(axis=1)
    out = []
    for r in roads:
        if inside[r.u] and inside[r.v]:
            out.append(r)
        elif inside[r.u] or inside[r.v]:
            r = r if inside[r.u] else r.reversed()
            r.line = _clip_line(r.line, extent)
            nodes.append(r.line[-1])
            r.v = len(nodes) - 1
            out.append(r)
    return out


def _clip_line(line: np.ndarray, extent: float) -> np.ndarray:
    """``line`` (starting inside the square) up to where it first leaves it."""
    k = int(np.argmax(((line <= 0) | (line >= extent)).any(axis=1)))
    a, d = line[k - 1], line[k] - line[k - 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.concatenate([np.where(d < 0, -a / d, np.inf), np.where(d > 0, (extent - a) / d, np.inf)])
    return np.vstack([line[:k], a + t.min() * d])


def _incidence(roads: list[Road]) -> dict[int, list[Road]]:
    inc: dict[int, list[Road]] = {}
    for r in roads:
        inc.setdefault(r.u, []).append(r)
        inc.setdefault(r.v, []).append(r)
    return inc


def _drop_acute(roads: list[Road]) -> list[Road]:
    """Drop the lesser of two arms that meet at a node at less than MIN_ANGLE."""
    while True:
        victim = None
        for n, rs in _incidence(roads).items():
            if len(rs) < 2:
                continue
            ang = np.array([np.arctan2(*r.direction_at(n)[::-1]) for r in rs])
            order = np.argsort(ang)
            gaps = np.diff(np.concatenate([ang[order], ang[order[:1]] + 2 * np.pi]))
            k = int(np.argmin(gaps))
            if gaps[k] < MIN_ANGLE:
                pair = rs[order[k]], rs[order[(k + 1) % len(rs)]]
                victim = min(pair, key=lambda r: (r.arterial, r.length))
                break
        if victim is None:
            return roads
        roads = [r for r in roads if r is not victim]


def _drop_crossings(style: Style, rng: np.random.Generator, roads: list[Road]) -> list[Road]:
    """Turn a share of crossings into T-junctions by dropping non-arterial edges between junctions;
    dropped edges that would split the network are put back."""
    degree: dict[int, int] = {}
    for r in roads:
        degree[r.u] = degree.get(r.u, 0) + 1
        degree[r.v] = degree.get(r.v, 0) + 1
    dropped = []
    for i in rng.permutation(len(roads)):
        r = roads[i]
        if not r.arterial and degree[r.u] >= 3 and degree[r.v] >= 3 and rng.random() < style.drop:
            dropped.append(i)
            degree[r.u] -= 1
            degree[r.v] -= 1
    parent = {n: n for n in degree}

    def root(n: int) -> int:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    keep = np.ones(len(roads), dtype=bool)
    keep[dropped] = False
    for r in (r for r, k in zip(roads, keep) if k):
        parent[root(r.u)] = root(r.v)
    for i in dropped:
        a, b = root(roads[i].u), root(roads[i].v)
        if a != b:
            keep[i] = True
            parent[a] = b
    return [r for r, k in zip(roads, keep) if k]


def _largest_component(roads: list[Road]) -> list[Road]:
    if not roads:
        return roads
    u = np.array([r.u for r in roads])
    v = np.array([r.v for r in roads])
    n = int(max(u.max(), v.max())) + 1
    _, label = connected_components(coo_matrix((np.ones(len(roads)), (u, v)), shape=(n, n)), directed=False)
    best = np.bincount(label[u]).argmax()
    return [r for r, lab in zip(roads, label[u]) if lab == best]


def _prune_dead_ends(roads: list[Road], extent: float) -> list[Road]:
    """Remove stubs left behind by dropped roads: roads ending at a dead end away from the border."""
    while True:
        inc = _incidence(roads)
        stubs = {id(rs[0]) for n, rs in inc.items() if len(rs) == 1 and _off_border(rs[0], n, extent)}
        if not stubs:
            return roads
        roads = [r for r in roads if id(r) not in stubs]


def _off_border(road: Road, node: int, extent: float) -> bool:
    p = road.line[0] if node == road.u else road.line[-1]
    return bool(np.all((p > 1.0) & (p < extent - 1.0)))


def _merge_straight(roads: list[Road]) -> list[Road]:
    """Merge the two roads at every degree-2 node that bends by less than MERGE_DEFLECTION."""
    inc = _incidence(roads)
    for n in list(inc):
        if len(inc[n]) != 2:
            continue
        a, b = inc[n]
        if a.other(n) == b.other(n) or np.dot(a.direction_at(n), b.direction_at(n)) > -np.cos(MERGE_DEFLECTION):
            continue
        ra = a if a.v == n else a.reversed()
        rb = b if b.u == n else b.reversed()
        base = ra if a.length >= b.length else rb
        merged = replace(base, line=round_corner(ra.line, rb.line, 12.0), u=ra.u, v=rb.v)
        inc[n] = []
        inc[ra.u] = [merged if x is a else x for x in inc[ra.u]]
        inc[rb.v] = [merged if x is b else x for x in inc[rb.v]]
    out, seen = [], set()
    for rs in inc.values():
        for r in rs:
            if id(r) not in seen:
                seen.add(id(r))
                out.append(r)
    return out


def _bend(style: Style, rng: np.random.Generator, roads: list[Road]) -> None:
    """Resample every axis at 3 m and bend a share of them sideways."""
    for r in roads:
        r.line = resample_step(r.line, 3.0)
        if rng.random() < style.curve_share and r.length > 40.0:
            amp = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * style.curve_amp * r.length
            r.line = bend(r.line, float(np.clip(amp, -0.2 * style.block[0], 0.2 * style.block[0])))


def _fix_one_way(roads: list[Road]) -> None:
    """Make one-way roads two-way until, at every junction, traffic arriving on a road can leave on
    another one and traffic leaving on a road can come from another one."""
    inc = _incidence(roads)
    while stuck := [rs for n, rs in inc.items() if len(rs) >= 2 and not _passable(n, rs)]:
        next(r for r in stuck[0] if r.oneway).oneway = 0


def _passable(node: int, rs: list[Road]) -> bool:
    ins = [r for r in rs if r.flows_in(node)]
    outs = [r for r in rs if r.flows_out(node)]
    return all(any(o is not r for o in outs) for r in ins) and all(any(i is not r for i in ins) for r in outs)


def _set_setbacks(roads: list[Road], crosswalks: set[int]) -> None:
    """Stop each road's lanes far enough from a junction that they clear every other arm there
    by a margin, and that a turn into any other arm (up to ``MAX_TURN``) has room for a radius of
    ``TURN_RADIUS`` (plus room for a crosswalk); dead ends get no setback."""
    for n, rs in _incidence(roads).items():
        if len(rs) < 2:
            rs[0].set_setback(n, 0.0)
            continue
        d = np.array([r.direction_at(n) for r in rs])
        h = np.array([r.half_width for r in rs])
        cos = np.clip(d @ d.T, -1.0, 1.0)
        sin = np.maximum(np.sqrt(1.0 - cos**2), 0.1)
        clear = np.where(cos > 0, (h[None, :] + h[:, None] * cos) / sin, h[None, :])
        # the outermost lanes of two arms at angle a meet at a corner; a turn of radius R between
        # them needs R / tan(a / 2) of lane before that corner, which lies half a lane inside `clear`
        half_lane = np.array([r.width / 2 for r in rs])
        turn = (TURN_RADIUS * (1.0 + cos) - half_lane[None, :] - half_lane[:, None] * cos) / sin
        turn[cos > np.cos(np.pi - MAX_TURN)] = 0.0
        need = clear + np.maximum(MARGIN, turn)
        np.fill_diagonal(need, 0.0)
        extra = CROSSWALK + 1.0 if n in crosswalks else 0.0
        for r, s in zip(rs, need.max(axis=1) + extra):
            r.set_setback(n, float(s))


def _conflicts(roads: list[Road]) -> set[int]:
    """Indices of roads to drop: too short for their setbacks, the shorter arm of a hairpin bend, or
    the shorter of two roads whose lane corridors overlap."""
    bad = {i for i, r in enumerate(roads) if r.length - sum(r.setback) < MIN_LANE}
    index = {id(r): i for i, r in enumerate(roads)}
    for n, rs in _incidence(roads).items():
        if len(rs) == 2 and np.dot(rs[0].direction_at(n), rs[1].direction_at(n)) > np.cos(HAIRPIN):
            bad.add(index[id(min(rs, key=lambda r: r.length))])
    ok = [i for i in range(len(roads)) if i not in bad]
    corridors = [
        shapely.buffer(shapely.LineString(cut(r.line, r.setback[0], r.length - r.setback[1])), r.half_width,
                       cap_style="flat")
        for r in (roads[i] for i in ok)
    ]
    a, b = shapely.STRtree(corridors).query(corridors, predicate="intersects")
    for i, j in zip(a, b):
        i, j = ok[i], ok[j]
        if i < j and i not in bad and j not in bad:
            bad.add(min(i, j, key=lambda k: roads[k].length))
    return bad
