"""`cmtool metrics` on JSON Lines files, as a user runs it, and its one-line errors."""

import json

import numpy as np
import pytest

from cmtool.data.sd_raster import rasterize_sd
from cmtool.maps.lanegraph import LaneGraph, infer_successors, write_jsonl
from cmtool.maps.sdmap import Road, SDMap
from tests.conftest import in_process

pytestmark = pytest.mark.usefixtures("one_thread")


def scenes(n: int, seed: int):
    """Straight two-way roads at random angles, with a right-hand lane pair each, and their SD rasters."""
    rng = np.random.default_rng(seed)
    graphs, sds = [], []
    for _ in range(n):
        a = rng.uniform(0, np.pi)
        d, left = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        t = np.linspace(-30, 30, 20)[:, None]
        lanes = [t * d - 1.75 * left, (t * d + 1.75 * left)[::-1]]
        halves = [lanes[0][:10], lanes[0][9:], lanes[1]]
        graphs.append(LaneGraph(lanes=halves, successors=infer_successors(halves), city="LAV"))
        sds.append(rasterize_sd(SDMap(roads=[Road("r", np.array([-40 * d, 40 * d]))]), 0.0, 0.0, 0.0))
    return graphs, np.stack(sds)




def test_metrics_end_to_end(tmp_path, capsys):
    ref, sd = scenes(64, 0)
    write_jsonl(tmp_path / "ref.jsonl", ref)
    write_jsonl(tmp_path / "same.jsonl", ref)
    np.save(tmp_path / "sd.npy", sd)
    code, out, err = in_process(capsys, "metrics", "--generated", tmp_path / "same.jsonl", "--reference",
                            tmp_path / "ref.jsonl", "--control", tmp_path / "sd.npy", "--json", tmp_path / "m.json")
    assert code == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["scenes"] == 64 and m["backbone"]["name"] == "resnet50-seeded"
    assert all(v == 0.0 for v in m["topology_fd"].values())
    assert m["gt_recall"]["recall"] == 1.0 and m["gt_recall"]["n"] == 64
    assert m["precision_recall"]["precision"] == 1.0 and m["geometry"]["lane_f1"]["mean"] == 1.0
    assert m["geometry"]["driving_side"]["mean"] == 1.0 and m["geometry"]["sd_coverage"]["mean"] > 0.9  # corners
    assert "| GT Recall ↑ (p) | 1.000 (" in out and "64 scene pairs in" in out
    assert set(m["seconds"]) == {"topology", "lane distances", "validity", "SD adherence", "driving side",
                                 "legal one-way", "features", "recall"} and all(v >= 0 for v in m["seconds"].values())


def test_processes_share_the_scenes_with_the_same_numbers(tmp_path, capsys):
    """--workers 2 scores a set above POOL_MIN_SCENES in two processes, value for value as one process does (and
    the topology distances as computed set by set)."""
    from cmtool.metrics.scenes import POOL_MIN_SCENES
    from cmtool.metrics.topology import topology_fd

    ref, sd = scenes(POOL_MIN_SCENES + 44, 0)
    other, _ = scenes(POOL_MIN_SCENES + 44, 1)
    write_jsonl(tmp_path / "ref.jsonl", ref)
    write_jsonl(tmp_path / "other.jsonl", other)
    np.save(tmp_path / "sd.npy", sd)
    results = []
    for workers in (1, 2):
        code, _, err = in_process(capsys, "metrics", "--generated", tmp_path / "other.jsonl", "--reference",
                                  tmp_path / "ref.jsonl", "--control", tmp_path / "sd.npy", "--no-features", "--quiet",
                                  "--workers", workers, "--json", tmp_path / f"m{workers}.json")
        assert code == 0, err
        results.append(json.loads((tmp_path / f"m{workers}.json").read_text()))
        results[-1].pop("seconds")
    assert results[0] == results[1]
    assert results[0]["topology_fd"] == pytest.approx(topology_fd(other, ref), abs=0, rel=0)
    per_scene = results[0]["geometry"]["lane_f1"]["per_scene"]
    assert len(per_scene) == POOL_MIN_SCENES + 44 and len(set(per_scene)) > 10  # varied scenes


def test_metrics_without_features_on_a_different_set(tmp_path, capsys):
    ref, sd = scenes(20, 0)
    other, _ = scenes(20, 1)
    write_jsonl(tmp_path / "ref.jsonl", ref)
    write_jsonl(tmp_path / "other.jsonl", other)
    code, out, err = in_process(capsys, "metrics", "--generated", tmp_path / "other.jsonl", "--reference",
                            tmp_path / "ref.jsonl", "--no-features", "--json", tmp_path / "m.json")
    assert code == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["geometry"]["lane_f1"]["mean"] < 0.5 and m["geometry"]["chamfer_m"]["mean"] > 1.0
    assert "gt_recall" not in m and "driving_side" not in m["geometry"]


@pytest.mark.parametrize("case", ["count", "bad line", "imagenet", "controls"])
def test_metrics_errors_are_one_line(case, tmp_path, capsys, monkeypatch):
    ref, sd = scenes(4, 0)
    write_jsonl(tmp_path / "ref.jsonl", ref)
    gen = tmp_path / "gen.jsonl"
    extra = []
    if case == "count":
        write_jsonl(gen, ref[:3])
        fragment = "3 generated scenes but 4 reference scenes"
    elif case == "bad line":
        gen.write_text((tmp_path / "ref.jsonl").read_text() + '{"version": 1, "lanes": [[[0, "x"], [1, 1]]]}\n')
        fragment = "line 5"
    elif case == "imagenet":
        write_jsonl(gen, ref)
        monkeypatch.setenv("TORCH_HOME", str(tmp_path))
        extra = ["--backbone", "resnet50-imagenet"]
        fragment = "no ImageNet weights found"
    else:
        write_jsonl(gen, ref)
        np.save(tmp_path / "sd.npy", sd[:2])
        extra = ["--control", tmp_path / "sd.npy", "--no-features"]
        fragment = "2 SD controls for 4 scenes"
    code, _, err = in_process(capsys, "metrics", "--generated", gen, "--reference", tmp_path / "ref.jsonl", *extra)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("Error: ") and fragment in lines[0], err
