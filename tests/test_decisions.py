"""The decisions a map makes where the SD map leaves them open (cmtool.metrics.decisions), on hand-made maps: junction
movements against the truth's, and the lane length no SD road explains."""

import numpy as np
import pytest

from cmtool.maps.lanegraph import LaneGraph
from cmtool.maps.sdmap import Road
from cmtool.metrics.decisions import (decision_counts, decisions, frame_junctions, movements, pooled,
                                      unexplained_length)

# A T junction at the origin, driven on the right: a through road west-east with a vertex at the junction and a side
# road from the south ending there; lanes 1.6 m beside the lines, stopping 8 m short of the junction.
ROADS = [Road("main", np.array([[-50.0, 0.0], [0.0, 0.0], [50.0, 0.0]])),
         Road("side", np.array([[0.0, -50.0], [0.0, 0.0]]))]
LANES = {"W_in": [(-40, -1.6), (-8, -1.6)], "E_out": [(8, -1.6), (40, -1.6)], "E_in": [(40, 1.6), (8, 1.6)],
         "W_out": [(-8, 1.6), (-40, 1.6)], "S_in": [(1.6, -40), (1.6, -8)], "S_out": [(-1.6, -8), (-1.6, -40)]}
NAMES = list(LANES)


def turn(start, end, corner) -> np.ndarray:
    """A quadratic curve from ``start`` to ``end`` bent towards ``corner``: a connector."""
    t = np.linspace(0.0, 1.0, 12)[:, None]
    p0, p1, p2 = (np.array(p, float) for p in (start, corner, end))
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t ** 2 * p2


CONNECTORS = {  # movement -> (lane in, lane out, connector line)
    "W>E": ("W_in", "E_out", np.linspace([-8, -1.6], [8, -1.6], 17)),
    "E>W": ("E_in", "W_out", np.linspace([8, 1.6], [-8, 1.6], 17)),
    "S>E": ("S_in", "E_out", turn((1.6, -8), (8, -1.6), (1.6, -1.6))),
    "W>S": ("W_in", "S_out", turn((-8, -1.6), (-1.6, -8), (-1.6, -1.6))),
    "S>W": ("S_in", "W_out", turn((1.6, -8), (-8, 1.6), (1.6, 1.6))),
}


def t_map(made: list[str], extra: list[np.ndarray] = ()) -> LaneGraph:
    """The T junction's six road lanes, the connectors of the movements ``made`` and the lanes ``extra``."""
    lanes = [np.array(LANES[n], float) for n in NAMES]
    successors = []
    for m in made:
        a, b, line = CONNECTORS[m]
        successors += [(NAMES.index(a), len(lanes)), (len(lanes), NAMES.index(b))]
        lanes.append(np.asarray(line, float))
    return LaneGraph(lanes=lanes + [np.asarray(l, float) for l in extra], successors=successors)


def keys(found: set, frame) -> set[str]:
    """Movements as "W>E" names: an edge by where it lies from the junction."""
    def where(e):
        mid = frame.edges[e].polyline.mean(axis=0)
        return "W" if mid[0] < -1 else "E" if mid[0] > 1 else "S"
    return {f"{where(a[0])}>{where(b[0])}" for a, b in found}


def test_the_t_junction_has_three_arms_and_each_movement_is_found():
    frame = frame_junctions(ROADS)
    assert len(frame.edges) == 3  # the through road split at the junction
    assert len(frame.arrives) == len(frame.leaves) == 3 and len(set(frame.arrives.values())) == 1  # the far ends: none
    truth = t_map(["W>E", "E>W", "S>E", "W>S"])
    assert keys(movements(truth, frame), frame) == {"W>E", "E>W", "S>E", "W>S"}
    assert movements(t_map([]), frame) == set()  # lanes joined to nothing make no movement


def test_movement_precision_and_recall_pool_the_frames():
    frame = frame_junctions(ROADS)
    truth = movements(t_map(["W>E", "E>W", "S>E", "W>S"]), frame)
    generated = t_map(["W>E", "E>W", "S>E", "S>W"])  # three of the truth's and a wrong one
    one = decision_counts(generated, truth, frame, ROADS)
    assert (one["true"], one["false"], one["missed"]) == (3, 1, 1)
    scores = pooled([one])
    assert scores["movement_precision"] == scores["movement_recall"] == scores["movement_f1"] == 0.75
    # a second frame: the truth goes straight on west to east, the map makes nothing
    other = decision_counts(t_map([]), movements(t_map(["W>E"]), frame), frame, ROADS)
    assert (other["true"], other["false"], other["missed"]) == (0, 0, 1)
    both = pooled([one, other])
    assert both["movement_precision"] == 0.75 and both["movement_recall"] == pytest.approx(3 / 5)
    assert both["movement_f1"] == pytest.approx(2 * 0.75 * 0.6 / 1.35)
    assert (both["movements"], both["true_movements"], both["truth_movements"]) == (4, 3, 5)


def test_a_lane_drawn_through_the_junction_makes_its_movement():
    frame = frame_junctions(ROADS)
    through = LaneGraph(lanes=[np.linspace([-40, -1.6], [40, -1.6], 81)])  # one lane, no connector
    assert keys(movements(through, frame), frame) == {"W>E"}
    wrong_way = LaneGraph(lanes=[np.linspace([40, -1.6], [-40, -1.6], 81)])  # on the wrong side: still E>W
    assert keys(movements(wrong_way, frame), frame) == {"E>W"}


def test_one_way_roads_have_no_movement_against_them():
    roads = [ROADS[0], Road("side", ROADS[1].polyline, oneway=1)]  # the side road only into the junction
    frame = frame_junctions(roads)
    assert len(frame.arrives) == 3 and len(frame.leaves) == 2
    assert keys(movements(t_map(["S>E", "W>S"]), frame), frame) == {"S>E"}


def test_the_unexplained_share_is_the_length_of_lanes_off_every_road():
    stray = np.array([[0.0, 30.0], [20.0, 30.0]])  # 30 m from both roads (their reach: 6.2 m)
    graph = t_map(["W>E"], [stray])
    off, total = unexplained_length(graph, ROADS)
    road_lanes = 6 * 32.0 + 16.0
    assert off == pytest.approx(20.0) and total == pytest.approx(road_lanes + 20.0)
    scores = decisions({"map": [graph, t_map(["W>E"])]}, [t_map(["W>E"])] * 2, [ROADS, ROADS])
    assert scores["map"]["unexplained_share"] == pytest.approx(20.0 / (2 * road_lanes + 20.0))
    assert scores["truth"]["unexplained_share"] == 0.0
    assert scores["truth"]["movement_f1"] == 1.0 and scores["truth"]["truth_movements"] == 2
    assert scores["map"]["movement_precision"] == scores["map"]["movement_recall"] == 1.0
    # no roads at all: every lane is unexplained
    assert unexplained_length(graph, [])[0] == pytest.approx(total)


def test_bench_sample_data_reports_the_decisions(sampling_ckpt, tiny_data, capsys):
    """`bench sample --data`: the decisions of every row's maps, and of the baselines in a line each."""
    from cmtool.formats.sumo import netconvert_path
    from tests.conftest import in_process

    code, out, err = in_process(capsys, "bench", "sample", "--ckpt", sampling_ckpt["controlmap"], "--data", tiny_data,
                                "--n", 4, "--table-steps", "1", "--samplers", "ddpm", "--batch", 4)
    assert code == 0, err
    head = next(line for line in out.splitlines() if line.startswith("| sampler"))
    names = [c.strip() for c in head.split("|")[1:-1]]
    assert names[-5:] == ["lanes per road direction as the truth's", "movement precision", "movement recall",
                          "movement F1", "lane length no SD road explains"]
    row = next(line for line in out.splitlines() if line.startswith("| ddpm |")).split("|")[1:-1]
    p, r, f1 = (float(row[names.index(f"movement {k}")]) for k in ("precision", "recall", "F1"))
    assert 0 <= p <= 1 and 0 <= r <= 1 and f1 == pytest.approx(2 * p * r / (p + r) if p + r else 0.0, abs=2e-3)
    assert float(row[-1]) < 0.05  # the maps as cmtool sample writes them: every lane on an SD road
    lines = [line for line in out.splitlines() if "(the SD map's layout)" in line]
    assert [line.split(" ")[0] for line in lines] == ["rules"] + (["netconvert"] if netconvert_path() else [])
    assert all("movement F1" in line and "lane length no SD road explains 0.000" in line for line in lines)
