import json

import numpy as np
import pytest

from cmtool.core.errors import CmtoolError
from cmtool.maps.lanegraph import LaneGraph, infer_successors, read_jsonl, write_jsonl


def scene(city="SGP"):
    lanes = [np.array([[-30.0, 0.0], [0.0, 0.0]]), np.array([[0.5, 0.2], [30.0, 0.0]]),
             np.array([[0.0, 0.0], [0.0, -30.0]]), np.array([[30.0, 3.0], [-30.0, 3.0]])]
    return LaneGraph(lanes=lanes, successors=[(0, 1)], green_lights=[lanes[1]], city=city, meta={"seed": 3})


def test_jsonl_roundtrip(tmp_path):
    graphs = [scene(), scene("BOS")]
    write_jsonl(tmp_path / "s.jsonl", graphs)
    back = read_jsonl(tmp_path / "s.jsonl")
    assert [g.city for g in back] == ["SGP", "BOS"]
    assert back[0].successors == [(0, 1)] and back[0].meta == {"seed": 3}
    np.testing.assert_allclose(back[1].lanes[3], graphs[1].lanes[3])
    assert len(back[0].green_lights) == 1 and back[0].red_lights == []


def test_single_pretty_json_is_accepted(tmp_path):
    path = tmp_path / "one.json"
    path.write_text(json.dumps(scene().to_json(), indent=2))
    assert len(read_jsonl(path)) == 1


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda o: o["lanes"][2].__setitem__(0, [float("inf"), 0.0]), r"line 2: lanes\[2\]: polyline has NaN or infinite"),
        (lambda o: o.update(successors=[[0, 9]]), r"line 2: successors\[0\]: lane index out of range"),
        (lambda o: o.update(successors=[[0]]), r"line 2: successors\[0\]: expected \[i, j\]"),
        (lambda o: o.update(version=2), r"line 2: version: unsupported"),
        (lambda o: o["lanes"].__setitem__(1, [[1.0, 2.0]]), r"line 2: lanes\[1\]: expected at least 2 points"),
        (lambda o: o.update(frame_m="64"), r"line 2: frame_m: expected a number"),
    ],
)
def test_validation_names_line_and_field(tmp_path, mutate, message):
    good = json.dumps(scene().to_json())
    bad = scene().to_json()
    mutate(bad)
    path = tmp_path / "s.jsonl"
    path.write_text(good + "\n" + json.dumps(bad) + "\n")
    with pytest.raises(CmtoolError, match=message):
        read_jsonl(path)


def test_malformed_line(tmp_path):
    path = tmp_path / "s.jsonl"
    path.write_text(json.dumps(scene().to_json()) + "\n{oops\n")
    with pytest.raises(CmtoolError, match="line 2: malformed JSON"):
        read_jsonl(path)


def test_infer_successors_uses_gap_and_angle():
    lanes = scene().lanes
    # 0 -> 1: gap 0.54 m, same heading; 0 -> 2: gap 0 but a 90 degree turn (> 60); 3 starts far away.
    assert infer_successors(lanes) == [(0, 1)]
    assert (0, 2) in infer_successors(lanes, max_angle_deg=95.0)
    assert infer_successors(lanes, max_gap_m=0.1) == []


def test_infer_successors_equals_comparing_every_end_with_every_start():
    """The KD-tree search against the slow path (all ends against all starts), on 50 random scenes of up to 300
    short lanes whose ends often land near other lanes' starts."""
    rng = np.random.default_rng(11)
    for _ in range(50):
        n = int(rng.integers(1, 300))
        starts = rng.uniform(-20, 20, (n, 2))
        starts[n // 2:] = np.round(starts[n // 2:])  # many lanes start on a grid of whole metres...
        steps = rng.normal(0, 1, (n, 3, 2))
        lanes = [np.cumsum(np.vstack([s, d]), axis=0) for s, d in zip(starts, steps)]
        for lane in lanes[: n // 3]:
            lane[-1] = np.round(lane[-1])  # ...and some end on it, at gaps of 0 to about 1.5 m of each other
        ends, heads = np.array([l[-1] for l in lanes]), np.array([l[0] for l in lanes])
        end_dir = np.array([(l[-1] - l[-2]) / np.linalg.norm(l[-1] - l[-2]) for l in lanes])
        start_dir = np.array([(l[1] - l[0]) / np.linalg.norm(l[1] - l[0]) for l in lanes])
        ok = (np.linalg.norm(ends[:, None] - heads[None], axis=-1) <= 1.5) & (end_dir @ start_dir.T >= 0.5)
        np.fill_diagonal(ok, False)
        assert infer_successors(lanes) == [(int(a), int(b)) for a, b in zip(*np.nonzero(ok))]
