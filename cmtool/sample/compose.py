"""The map the SD map states, with the model's decisions: every road of the frame's SD map carries its lanes, whole,
and nothing else does; junctions are joined from those lanes.

The layout is the rules' (:func:`cmtool.data.rules.rule_layout` on the frame's roads): lanes offset from each SD
road's own line a lane width of its class apart, stopping short of junctions, divided roads as their two
carriageways; connectors are cubic Bézier curves from an arriving lane's end to a leaving lane's start, tangent to
both, no tighter than ``TURN_RADIUS_M`` where the lanes have another way on. The model decides what the SD map leaves
open:

- **lanes per direction** where the road has no ``lanes`` tag (``counts="model"``): as many as the model drew along
  it (:func:`cmtool.sample.roads.drawn_lane_counts`), the road class's usual count where it drew none; or
  (``counts="class"``) the class's usual count everywhere;
- **movements**: a junction's movement from one arm into another is made where one of the model's lanes (or a chain
  of up to ``CHAIN`` of them joined by successor links) passes the first arm's lane ends, then the second's lane
  starts, heading on (:func:`_gate`). An arm that the model enters or leaves by no movement keeps every legal one,
  and a lane still joined to no movement gets the straightest one that joins it, so that no lane ends in a junction.
  Only legal movements are made: one-way roads one way, no U-turns, the lanes of a movement paired from the near side
  so that they do not cross.

What the model drew where the SD map has no road is not written; ``meta.composed`` counts it (``dropped``: the
model's lanes lying mostly farther than a road's reach from every SD road:
:func:`cmtool.metrics.decisions.unexplained`) beside where each road direction's lane
count came from and which movements the model chose. The traffic lights the model drew stay where one of the map's
lanes runs under their stop line.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace

import numpy as np

from cmtool.core.geometry import unit
from cmtool.data.rules import lane_counts, rule_layout
from cmtool.data.scene import Pose, SceneCropper
from cmtool.diffusion.settings import SamplingError
from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road, SDMap
from cmtool.metrics.decisions import unexplained
from cmtool.metrics.lanes import distance_to_polylines, resampled
from cmtool.sample import COUNTS, DEFAULT_COUNTS
from cmtool.sample.roads import drawn_lane_counts

CHAIN = 3  # lanes joined by successor links that count as one path through a junction
GATE_BACK_M, GATE_ON_M = 10.0, 4.0  # a path passes an arm's lane ends within this far before / after them
GATE_SIDE_M = 2.0  # ... and within this far beyond its outer lanes
GATE_DEG = 40.0  # ... heading within this of the lanes
LIGHT_M = 3.0  # a light stays where a lane runs within this of its start (its stop line)
POINTS = 20  # points per lane, as the model's lanes have
TURN_RADIUS_M = 5.0  # the tightest turn a connector makes where its lanes have another way (the kink check's is 4 m)


def check_counts(counts: str, prefix: str = "--") -> None:
    """Reject a lane count source :func:`compose` does not know; ``prefix`` names the option in the message."""
    if counts not in COUNTS:
        raise SamplingError(f"{prefix}lane-counts: choose {' or '.join(COUNTS)}, got {counts!r}")


def compose(graph: LaneGraph, roads: list[Road], side: str, counts: str = DEFAULT_COUNTS) -> LaneGraph:
    """The map of the frame's SD ``roads`` (:func:`cmtool.sample.roads.frame_roads`) with the decisions of the
    model's ``graph`` (module doc); ``side``: the driving side; ``counts``: an untagged road's lanes per direction from
    its class ("class") or as the model drew them, the class's where it drew none ("model")."""
    check_counts(counts, "")
    drawn = drawn_lane_counts(graph, roads, side) if counts == "model" else {}
    lanes, source = {}, Counter()
    for p, road in enumerate(roads):
        lanes[id(road)], how = _count(road, p, drawn)
        source.update(how)
    tracks = _tracks(graph)
    chose = Counter()

    def movements(arms_in, arms_out, legal):
        chosen, how = _movements(tracks, arms_in, arms_out, legal)
        chose.update(how)
        return chosen

    hd = rule_layout(SDMap(city=graph.city, roads=roads), side, counts=lambda road: lanes[id(road)],
                     movements=movements, turn_radius_m=TURN_RADIUS_M)
    pieces = 4 * len(hd.lanes) + 8  # a lane leaving the frame and coming back is two pieces
    laid = SceneCropper(hd).extract(Pose(0.0, 0.0, 0.0), num_lines=pieces, num_points=POINTS, num_lights=0,
                                    frame_m=graph.frame_m).to_lanegraph()
    meta = dict(graph.meta) | {"composed": {"lanes_from": dict(source), "movements": dict(chose),
                                            "dropped": len(unexplained(graph, roads))}}
    lights = {key: _lit(getattr(graph, key), laid.lanes) for key in ("green_lights", "red_lights")}
    return replace(laid, **lights, city=graph.city, meta=meta)


def _count(road: Road, p: int, drawn: dict) -> tuple[tuple[int, int], list[str]]:
    """A road's lanes (along, against its travel direction) and where each direction's count came from: its tag, the
    model's lanes (``drawn``: :func:`drawn_lane_counts`), or its class."""
    prior = lane_counts(road)
    if road.lanes is not None:
        return prior, ["tag"] * (1 if road.oneway else 2)
    travel = -1 if road.oneway == -1 else 1
    along, against = drawn.get((p, travel)), None if road.oneway else drawn.get((p, -travel))
    how = ["model" if along else "class"] + ([] if road.oneway else ["model" if against else "class"])
    return (along or prior[0], 0 if road.oneway else against or prior[1]), how


def _tracks(graph: LaneGraph) -> list[tuple[np.ndarray, np.ndarray]]:
    """The model's paths, each a lane or a chain of up to ``CHAIN`` lanes along successor links, as points every metre
    and their unit headings."""
    lanes = resampled([np.asarray(l, np.float64) for l in graph.lanes], 1.0)
    after: dict[int, list[int]] = {}
    for i, j in graph.successors:
        if i != j:
            after.setdefault(i, []).append(j)
    paths, grow = [], [[k] for k in range(len(lanes))]
    for _ in range(CHAIN):
        paths += grow
        grow = [path + [j] for path in grow for j in after.get(path[-1], []) if j not in path]
    out = []
    for path in paths:
        points = np.concatenate([lanes[k] for k in path])
        if len(points) >= 2:
            out.append((points, unit(np.gradient(points, axis=0))))
    return out


def _movements(tracks, arms_in, arms_out, legal: dict) -> tuple[set, list[str]]:
    """The junction's movements (:func:`cmtool.data.rules.rule_layout`'s ``movements``): those the model's ``tracks``
    make, every legal one of an arm the model enters or leaves by none, the straightest legal one of each lane still
    joined to none; and where each chosen movement came from."""
    enter = [_gate(tracks, arm, True) for arm in arms_in]
    leave = [_gate(tracks, arm, False) for arm in arms_out]
    made = {(a, b) for a, b in legal if any(t in leave[b] and i < leave[b][t] for t, i in enter[a].items())}
    chosen = made | {(a, b) for a, b in legal
                     if not any(m[0] == a for m in made) or not any(m[1] == b for m in made)}
    turn = {(a, b): abs(_turn(arms_in[a][0][-2:], arms_out[b][0][:2])) for a, b in legal}
    for m in sorted(legal, key=turn.get):
        for end in (0, 1):  # 0: the lanes arriving, 1: the lanes leaving
            joined = {(c[end], pair[end]) for c in chosen for pair in legal[c]}
            if any((m[end], pair[end]) not in joined for pair in legal[m]):
                chosen.add(m)
    return chosen, ["model" if m in made else "rules" for m in chosen]


def _turn(before: np.ndarray, after: np.ndarray) -> float:
    """The angle (radians) from the direction of the segment ``before`` to that of ``after``."""
    a, b = unit(before[1] - before[0]), unit(after[1] - after[0])
    return math.atan2(a[0] * b[1] - a[1] * b[0], float(a @ b))


def _gate(tracks, arm: list[np.ndarray], at_end: bool) -> dict[int, int]:
    """The tracks that pass an arm's lane ends (``at_end``; else its lane starts), heading on: track -> the index of its
    first point there (``at_end``) or its last."""
    ends = np.array([l[-1] if at_end else l[0] for l in arm])
    heading = unit(np.sum([unit(l[-1] - l[-2]) if at_end else unit(l[1] - l[0]) for l in arm], axis=0))
    centre = ends.mean(axis=0)
    across = np.abs((ends - centre) @ np.array([-heading[1], heading[0]])).max() + GATE_SIDE_M
    back, on = (GATE_BACK_M, GATE_ON_M) if at_end else (GATE_ON_M, GATE_BACK_M)
    cos = math.cos(math.radians(GATE_DEG))
    out = {}
    for t, (points, tangents) in enumerate(tracks):
        rel = points - centre
        along, lateral = rel @ heading, rel @ np.array([-heading[1], heading[0]])
        inside = np.flatnonzero((along >= -back) & (along <= on) & (np.abs(lateral) <= across)
                                & (tangents @ heading >= cos))
        if len(inside):
            out[t] = int(inside[0] if at_end else inside[-1])
    return out


def _lit(lights: list[np.ndarray], lanes: list[np.ndarray]) -> list[np.ndarray]:
    """The light lines whose start (the stop line, where the light is drawn) lies within ``LIGHT_M`` of a lane."""
    if not lights or not lanes:
        return []
    starts = np.array([np.asarray(l, np.float64)[0] for l in lights])
    return [l for l, d in zip(lights, distance_to_polylines(starts, lanes)) if d <= LIGHT_M]
