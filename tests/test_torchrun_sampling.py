"""`cmtool sample` and `cmtool eval` split over two CPU processes by torchrun make the same maps as one process."""

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO, in_process

pytestmark = pytest.mark.usefixtures("one_thread")
SD_PNG = REPO / "sample_data" / "sd_bos.png"


def torchrun(*args, processes: int = 2) -> subprocess.CompletedProcess:
    """``torchrun ... -m cmtool -- ARGS``: the ``--`` keeps torchrun from reading ``--n`` and ``--num`` as
    abbreviations of its own options."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node",
                           str(processes), "-m", "cmtool", "--", *map(str, args)], capture_output=True, text=True, cwd=REPO,
                          timeout=600, env=env)


def test_sample_in_two_processes_makes_the_same_maps(sampling_ckpt, tmp_path, capsys):
    args = ("sample", "--ckpt", sampling_ckpt["controlmap"], "--sd", SD_PNG, "--num", 5, "--batch", 2, "--steps", 3,
            "--sampler", "ddpm", "--quiet")
    code, one_out, err = in_process(capsys, *args, "--no-log", "--out", tmp_path / "one", "--grid", tmp_path / "one.png")
    assert code == 0, err
    two = torchrun(*args, "--no-log", "--out", tmp_path / "two", "--grid", tmp_path / "two.png")
    assert two.returncode == 0, two.stderr[-2000:]
    # three batches (2 + 2 + 1 maps): the second came from the other process
    names = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert len([n for n in names if n.endswith(".json")]) == 5
    assert names == sorted(p.name for p in (tmp_path / "two").iterdir())
    for name in names:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
    assert (tmp_path / "one.png").read_bytes() == (tmp_path / "two.png").read_bytes()
    assert two.stdout.count("mean validity") == 1  # the summary is printed once, by the main process
    # the model's maps differ from batch to batch (each batch its own noise), not only from process to process (the
    # maps composed from one SD map may not)
    code, _, err = in_process(capsys, *args, "--raw", "--no-log", "--out", tmp_path / "raw")
    assert code == 0, err
    maps = [json.loads((tmp_path / "raw" / f"sd_bos_s{k}.json").read_text())["lanes"] for k in range(5)]
    assert maps[0] != maps[2] != maps[4]
    refused = torchrun(*args, "--out", tmp_path / "logged")
    assert refused.returncode != 0 and "record no denoising steps: add --no-log" in refused.stderr
    assert not (tmp_path / "logged").exists()


def test_eval_in_two_processes_makes_the_same_maps_and_scores(sampling_ckpt, tiny_data, tmp_path, capsys):
    args = ("eval", "--ckpt", sampling_ckpt["controlmap"], "--data", tiny_data, "--steps", 2, "--batch", 2,
            "--no-features", "--rrd-samples", 2, "--quiet")
    code, _, err = in_process(capsys, *args, "--n", 6, "--out", tmp_path / "one")
    assert code == 0, err
    two = torchrun(*args, "--n", 6, "--out", tmp_path / "two")  # three batches: processes 0, 1, 0
    assert two.returncode == 0, two.stderr[-2000:]
    for method in ("unguided", "controlmap"):
        lines = [(tmp_path / d / "cache" / f"{method}.jsonl").read_text().splitlines() for d in ("one", "two")]
        assert len(lines[0]) == 6 and lines[0] == lines[1]
    scores = [{m: {k: v for k, v in r.items() if k != "seconds"} for m, r in
               json.loads((tmp_path / d / "metrics.json").read_text())["methods"].items()} for d in ("one", "two")]
    assert scores[0] == scores[1]
    assert two.stdout.count("wrote ") == 1  # the reports are printed once, by the main process
    # more scenes later: two processes continue the cache one process began, as one process would
    more = torchrun(*args, "--n", 8, "--out", tmp_path / "one")
    assert more.returncode == 0, more.stderr[-2000:]
    code, _, err = in_process(capsys, *args, "--n", 8, "--out", tmp_path / "whole")
    assert code == 0, err
    lines = [(tmp_path / d / "cache" / "controlmap.jsonl").read_text().splitlines() for d in ("one", "whole")]
    assert len(lines[0]) == 8 and lines[0] == lines[1]
    # a cache of other settings is refused by every process, which all stop
    clash = torchrun(*args, "--n", 8, "--cfg", 0.5, "--out", tmp_path / "one")
    assert clash.returncode != 0 and "made with other settings (cfg)" in clash.stderr


def test_an_area_in_two_processes_is_the_same_map(tmp_path, capsys):
    """`sample --area` under torchrun: the processes share the batches of tiles, the main process stitches and
    writes the map an unbroken single process makes (the shipped weights)."""
    town, box = REPO / "sample_data" / "town_bos.osm", "42.3560,-71.0640,42.3575,-71.0620"
    args = ("sample", "--osm", town, "--area", box, "--steps", 3, "--sampler", "dpm++2m-sde", "--batch", 4, "--raw",
            "--quiet")
    code, _, err = in_process(capsys, *args, "--out", tmp_path / "one")
    assert code == 0, err
    two = torchrun(*args, "--out", tmp_path / "two")
    assert two.returncode == 0, two.stderr[-2000:]
    one, other = (json.loads((tmp_path / d / "town_bos_area.json").read_text()) for d in ("one", "two"))
    assert one["lanes"] == other["lanes"] and one["successors"] == other["successors"]
    assert two.stdout.count("successor joins from") == 1
