"""The lane level of a procedural city: road lanes, intersection connectors, lights and crosswalks."""

from __future__ import annotations

import itertools

import numpy as np

from cmtool.core.geometry import offset, wrap_angle
from cmtool.data.synth.curves import cut, end_tangents, hermite, point_and_tangent
from cmtool.data.synth.network import CROSSWALK, MAX_TURN, Network, Road
from cmtool.maps.hdmap import Crosswalk, HDMap, Lane, StopLine

THROUGH = np.radians(45.0)  # an exit within this angle of the approach heading is straight on


def build_lanes(net: Network, hd: HDMap, rng: np.random.Generator) -> None:
    """Fill ``hd`` with the lanes, connectors, stop lines and crosswalks of ``net``."""
    hand = 1.0 if hd.drives_on == "right" else -1.0
    ids = (f"l{k}" for k in itertools.count())
    arriving: dict[int, list[list[Lane]]] = {}
    leaving: dict[int, list[list[Lane]]] = {}
    degree: dict[int, int] = {}
    for k, road in enumerate(net.roads):
        degree[road.u] = degree.get(road.u, 0) + 1
        degree[road.v] = degree.get(road.v, 0) + 1
        axis = cut(road.line, road.setback[0], road.length - road.setback[1])
        for travel, start, end, oneway in ((axis, road.u, road.v, 1), (axis[::-1], road.v, road.u, -1)):
            if road.oneway in (0, oneway):
                group = _road_lanes(hd, road, f"r{k}", travel, hand, ids)
                arriving.setdefault(end, []).append(group)
                leaving.setdefault(start, []).append(group)
    for n in sorted(set(arriving) & set(leaving)):
        if degree[n] < 2:
            continue
        approaches = [(group, _connect(hd, n, group, leaving[n], degree[n], hand, ids)) for group in arriving[n]]
        _feed_unreached(hd, n, approaches, leaving[n], ids)
        if n in net.signals and len(approaches) >= 2:
            _stop_lines(hd, approaches, rng)
    for n in sorted(net.crosswalks):
        for road in net.roads:
            if n in (road.u, road.v):
                _crosswalk(hd, road, n)


def _road_lanes(hd: HDMap, road: Road, road_id: str, travel: np.ndarray, hand: float, ids) -> list[Lane]:
    """The lanes of one travel direction, innermost (nearest the centre line) first, placed to the
    right of the axis for right-hand traffic (``hand`` = 1) and to the left for left-hand traffic."""
    n, w = road.lanes, road.width
    if road.oneway:
        lateral = hand * ((n - 1) / 2 - np.arange(n)) * w
    else:
        lateral = -hand * (road.median / 2 + (np.arange(n) + 0.5) * w)
    lanes = [
        hd.add_lane(Lane(id=next(ids), centerline=offset(travel, float(d)), width=w, road_id=road_id,
                         lane_type="bus" if road.bus and n >= 2 and i == n - 1 else "vehicle"))
        for i, d in enumerate(lateral)
    ]
    outer, inner = ("right_neighbor", "left_neighbor") if hand > 0 else ("left_neighbor", "right_neighbor")
    for a, b in zip(lanes, lanes[1:]):
        setattr(a, outer, b.id)
        setattr(b, inner, a.id)
    return lanes


def _connect(hd: HDMap, node: int, approach: list[Lane], exits: list[list[Lane]], degree: int, hand: float,
             ids) -> list[str]:
    """Connector lanes for every legal movement from ``approach``; returns their ids.

    At a plain bend (degree 2) every lane continues. Elsewhere: straight on lane k -> lane k; the
    near-side turn (right for right-hand traffic) from the outermost to the outermost lane, the
    far-side turn from the innermost to the innermost lane. Without a straight-on exit the inner
    half of the lanes turns to the far side and the outer half to the near side (all of them where
    only one side has exits). No U-turns onto the approach's own road, and no turns sharper than
    ``MAX_TURN`` unless there is no other way on.
    """
    heading_in = _heading(end_tangents(approach[0].centerline)[1])
    exits = [e for e in exits if e[0].road_id != approach[0].road_id]
    turn = np.array([wrap_angle(_heading(end_tangents(e[0].centerline)[0]) - heading_in) for e in exits])
    if degree > 2 and (np.abs(turn) <= MAX_TURN).any():  # else keep them: a sharp turn beats a dead end
        exits, turn = [e for e, a in zip(exits, turn) if abs(a) <= MAX_TURN], turn[np.abs(turn) <= MAX_TURN]
    through = int(np.argmin(np.abs(turn))) if len(turn) and np.abs(turn).min() < THROUGH else -1
    near = turn * hand < 0
    n_in = len(approach)
    if through >= 0:
        near_from, far_to = n_in - 1, 1
    else:
        near_from = n_in // 2 if (~near).any() else 0
        far_to = (n_in + 1) // 2 if near.any() else n_in
    made = []
    for j, exit_ in enumerate(exits):
        n_out = len(exit_)
        if degree == 2:
            pairs = [(min(k, n_in - 1), min(k, n_out - 1)) for k in range(max(n_in, n_out))]
        elif j == through:
            pairs = [(min(k, n_in - 1), min(k, n_out - 1)) for k in range(max(n_in, n_out))]
        elif near[j]:
            pairs = [(k, max(n_out - n_in + k, 0)) for k in range(near_from, n_in)]
        else:
            pairs = [(k, min(k, n_out - 1)) for k in range(far_to)]
        for a, b in pairs:
            made.append(_connector(hd, node, approach[a], exit_[b], next(ids)))
    return made


def _feed_unreached(hd: HDMap, node: int, approaches: list[tuple[list[Lane], list[str]]],
                    exits: list[list[Lane]], ids) -> None:
    """Give every exit lane no movement reaches a connector from the lane feeding its nearest
    reached neighbour (a lane opening up after the junction)."""
    made_by = {lanes[0].id: made for lanes, made in approaches}
    group_of = {lane.id: lanes for lanes, _ in approaches for lane in lanes}
    for exit_ in exits:
        fed = [j for j, lane in enumerate(exit_) if lane.predecessors]
        for k, lane in enumerate(exit_):
            if not lane.predecessors and fed:
                j = min(fed, key=lambda j: abs(j - k))
                source = hd.lanes[hd.lanes[exit_[j].predecessors[0]].predecessors[0]]
                made_by[group_of[source.id][0].id].append(_connector(hd, node, source, lane, next(ids)))


def _connector(hd: HDMap, node: int, a: Lane, b: Lane, lane_id: str) -> str:
    line = hermite(a.centerline[-1], end_tangents(a.centerline)[1], b.centerline[0], end_tangents(b.centerline)[0])
    hd.add_lane(Lane(id=lane_id, centerline=line, width=a.width, is_intersection=True, intersection_id=f"i{node}"))
    hd.link(a.id, lane_id)
    hd.link(lane_id, b.id)
    return lane_id


def _heading(d: np.ndarray) -> float:
    return float(np.arctan2(d[1], d[0]))


def _stop_lines(hd: HDMap, approaches: list[tuple[list[Lane], list[str]]], rng: np.random.Generator) -> None:
    """One stop line across the end of each approach; approaches along one axis (chosen at random)
    are green, the crossing ones (at least one) red. Each light controls the connectors leaving its
    approach."""
    lines, off_axis = [], []
    axis = _heading(end_tangents(approaches[int(rng.integers(len(approaches)))][0][0].centerline)[1])
    for lanes, connectors in approaches:
        d = end_tangents(lanes[0].centerline)[1]
        normal = np.array([-d[1], d[0]])
        ends = np.array([lane.centerline[-1] for lane in lanes])
        lateral = (ends - ends[0]) @ normal
        half = lanes[0].width / 2
        line = np.array([ends[0] + (lateral.max() + half) * normal, ends[0] + (lateral.min() - half) * normal])
        lines.append(StopLine(id=f"s{len(hd.stop_lines) + len(lines)}", line=line, state="green", lane_ids=connectors))
        off_axis.append(abs(wrap_angle(2.0 * (_heading(d) - axis))) / 2.0)
    red = np.array(off_axis) >= np.pi / 4
    red[int(np.argmax(off_axis))] = True
    for sl, r in zip(lines, red):
        sl.state = "red" if r else "green"
    hd.stop_lines += lines


def _crosswalk(hd: HDMap, road: Road, node: int) -> None:
    """A rectangle across the whole road, between its stop line and the junction."""
    line = road.line if node == road.u else road.line[::-1]
    setback = road.setback[0] if node == road.u else road.setback[1]
    centre, t = point_and_tangent(line, setback - 1.0 - CROSSWALK / 2)
    normal = np.array([-t[1], t[0]]) * road.half_width
    along = t * CROSSWALK / 2
    polygon = np.array([centre - along + normal, centre + along + normal, centre + along - normal,
                        centre - along - normal])
    hd.crosswalks.append(Crosswalk(id=f"c{len(hd.crosswalks)}", polygon=polygon))
