"""The training pipeline end to end on a tiny dataset: rvae -> latent cache -> dit -> controlnet,
checkpoints, exact resume after kill -9, DDP on two CPU processes, and `cmtool info`."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader
from safetensors.torch import load_file

from cmtool import checkpoint as ckpt
from cmtool.errors import CmtoolError
from tests.conftest import REPO

TINY_MODELS = {
    "rvae": '[rvae]\nd_model = 32\ndecoder_layers = 1\nheads = 2\nffn = 64\ndropout = 0.0\n',
    "dit": '[dit]\nsize = "tiny"\ndepth = 2\nhidden = 32\nheads = 2\n',
    "controlnet": '[dit]\nsize = "tiny"\ndepth = 2\nhidden = 32\nheads = 2\n[control]\nnum_blocks = 2\nwidths = [8, 8, 16, 16]\ngroups = 4\n',
}


def write_recipe(path, stage, steps, **train):
    keys = {"stage": stage, "steps": steps, "batch_size": 4, "warmup_steps": 2, "ckpt_every": 2, "log_every": 1,
            "preview_every": steps, "preview_steps": 3, **train}
    lines = ["[train]"] + [f"{k} = {json.dumps(v)}" for k, v in keys.items()]
    path.write_text("\n".join(lines) + "\n" + TINY_MODELS[stage])
    return path


def cli(*args, cwd=None, env=None):
    return subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd or REPO, timeout=600, env=env)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, tiny_data):
    """One finished run of each stage on the tiny dataset."""
    root = tmp_path_factory.mktemp("train")
    data = tiny_data
    out = {"root": root, "data": data}
    for stage, extra in (("rvae", {"data": str(data)}),
                         ("dit", {"rvae": str(root / "rvae")}),
                         ("controlnet", {"data": str(data), "rvae": str(root / "rvae"), "dit": str(root / "dit")})):
        recipe = write_recipe(root / f"{stage}.toml", stage, 4, **extra)
        result = cli("train", stage, "--recipe", recipe, "--out", root / stage, "--quiet")
        assert result.returncode == 0, result.stderr
        out[stage] = root / stage
        out[f"{stage}_recipe"] = recipe
    return out


def test_rvae_run_writes_checkpoint_latents_and_recording(runs):
    run = runs["rvae"]
    final = ckpt.resolve(run)
    config = ckpt.load_config(run)
    assert final.name == "step_00000004" and config["complete"] and config["step"] == 4
    assert config["latent_scale"] > 0 and 0.0 <= config["reconstruction"]["f1"] <= 1.0
    with np.load(run / "latents" / "train.npz") as z:
        assert z["mean"].shape == (24, 64, 8, 8) and z["mean"].dtype == np.float16
        assert set(z["city"].tolist()) == {"LAV", "PIT", "SGP"}
    assert (run / "latents" / "test.npz").is_file()
    assert (run / "train.rrd").stat().st_size > 0
    # older checkpoints are pruned to train.keep (2) and no temporary folders are left behind
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step_00000002", "step_00000004"]


def recording_steps(rrd) -> dict[str, set]:
    """Entity path -> the train_step values it was logged at."""
    steps = {}
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        if "train_step" in batch.schema.names:
            steps.setdefault(chunk.entity_path, set()).update(batch.column("train_step").to_pylist())
    return steps


def test_training_recordings_hold_scalars_and_previews(runs):
    steps = recording_steps(runs["rvae"] / "train.rrd")
    for path in ("/train/loss", "/train/lr", "/train/grad_norm", "/train/kl", "/train/l1/lines"):
        assert steps[path] == {1, 2, 3, 4}, path
    assert steps["/train/preview/sample_0/decoded/hd/lanes"] == {4}
    assert steps["/train/preview/sample_0/truth/hd/lanes"] == {4}
    steps = recording_steps(runs["controlnet"] / "train.rrd")
    assert steps["/train/loss"] == {1, 2, 3, 4}
    assert steps["/train/preview/sample_0/control/sd"] == {4}
    assert steps["/train/preview/sample_0/generated/hd/lanes"] == {4}


def test_controlnet_keeps_the_dit_frozen(runs):
    dit = load_file(str(ckpt.resolve(runs["dit"]) / ckpt.WEIGHTS))
    control = load_file(str(ckpt.resolve(runs["controlnet"]) / ckpt.WEIGHTS))
    base = {k[len("base."):]: v for k, v in control.items() if k.startswith("base.")}
    assert base.keys() == dit.keys()
    assert all(torch.equal(base[k], dit[k]) for k in dit)
    # ... while the branch did train: its zero-initialised injections are no longer zero
    config = ckpt.load_config(runs["controlnet"])
    assert config["kind"] == "controlmap" and config["cities"] == ["LAV", "PIT", "SGP"]
    model, _ = ckpt.load_model(runs["controlnet"])
    assert any(p.abs().sum() > 0 for n, p in model.named_parameters() if "zero" in n or "inject" in n)


def test_resume_after_kill_matches_an_uninterrupted_run(runs, tmp_path):
    root = runs["root"]
    recipe = write_recipe(tmp_path / "dit.toml", "dit", 12, rvae=str(root / "rvae"), ckpt_every=1, preview_every=0)
    straight = tmp_path / "straight"
    assert cli("train", "dit", "--recipe", recipe, "--out", straight, "--quiet").returncode == 0

    crashed = tmp_path / "crashed"
    proc = subprocess.Popen([sys.executable, "-m", "cmtool", "train", "dit", "--recipe", str(recipe), "--out",
                             str(crashed), "--quiet"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and len(ckpt.run_checkpoints(crashed)) < 1:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = ckpt.run_checkpoints(crashed)
    assert done and ckpt.load_config(done[-1])["step"] < 12  # killed mid-run, checkpoints intact
    again = cli("train", "dit", "--recipe", recipe, "--out", crashed, "--quiet")
    assert again.returncode != 0 and "--resume" in again.stderr
    assert cli("train", "dit", "--recipe", recipe, "--out", crashed, "--resume", "--quiet").returncode == 0

    a = load_file(str(ckpt.resolve(straight) / ckpt.WEIGHTS))
    b = load_file(str(ckpt.resolve(crashed) / ckpt.WEIGHTS))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    sa = load_file(str(ckpt.resolve(straight) / ckpt.STATE))
    sb = load_file(str(ckpt.resolve(crashed) / ckpt.STATE))
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_finished_controlnet_run_extends_with_resume_and_more_steps(runs, tmp_path):
    run = tmp_path / "controlnet"
    shutil.copytree(runs["controlnet"], run)
    recipe = runs["controlnet_recipe"]
    same = cli("train", "controlnet", "--recipe", recipe, "--out", run, "--resume", "--quiet")
    assert same.returncode == 0 and "already complete at step 4" in same.stderr
    longer = cli("train", "controlnet", "--recipe", recipe, "--out", run, "--resume", "--steps", "6", "--quiet")
    assert longer.returncode == 0, longer.stderr
    config = ckpt.load_config(run)
    assert config["step"] == 6 and config["complete"] and config["training"]["samples"] == 6 * 4


def test_ddp_two_cpu_processes_keep_replicas_identical(runs, tmp_path):
    root = runs["root"]
    recipe = write_recipe(tmp_path / "dit.toml", "dit", 4, rvae=str(root / "rvae"), preview_every=0)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                             "-m", "cmtool", "train", "dit", "--recipe", str(recipe), "--out", str(tmp_path / "ddp"),
                             "--quiet"], capture_output=True, text=True, cwd=REPO, timeout=600, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    training = ckpt.load_config(tmp_path / "ddp")["training"]
    assert training["world_size"] == 2 and training["samples"] == 16
    fps = training["replica_fingerprints"]
    assert len(fps) == 2 and fps[0] == fps[1]


def test_info_on_checkpoints_and_paper_recipes(runs):
    out = cli("info", runs["controlnet"])
    assert out.returncode == 0, out.stderr
    assert "controlmap (complete, step 4/4)" in out.stdout and "LAV, PIT, SGP" in out.stdout
    assert "frozen DiT" in out.stdout
    rvae = cli("info", runs["rvae"]).stdout
    assert "reconstruction" in rvae and "latent scale" in rvae

    def params(recipe):
        result = cli("info", REPO / "recipes" / "paper" / recipe)
        assert result.returncode == 0, result.stderr
        line = next(l for l in result.stdout.splitlines() if l.startswith("parameters"))
        return int(line.split()[1].replace(",", ""))

    assert abs(params("dit-b.toml") - 138e6) / 138e6 < 0.10
    assert abs(params("controlmap-dit-b.toml") - 230e6) / 230e6 < 0.10
    assert params("dit-xl.toml") > 400e6


def test_user_errors_are_one_line(runs, tmp_path):
    root = runs["root"]
    bad = [
        (["train", "dit", "--recipe", runs["rvae_recipe"], "--out", tmp_path / "x"], "rvae stage"),
        (["train", "controlnet", "--recipe", write_recipe(tmp_path / "c.toml", "controlnet", 2, data=str(runs["data"]),
                                                           rvae=str(root / "rvae"), dit=str(root / "rvae")),
          "--out", tmp_path / "y"], "needs a DiT"),
        (["train", "dit", "--recipe", write_recipe(tmp_path / "d.toml", "dit", 2, rvae=str(tmp_path / "none")),
          "--out", tmp_path / "z"], "no such checkpoint"),
        (["info", tmp_path], "not a checkpoint"),
    ]
    for args, fragment in bad:
        result = cli(*args)
        lines = result.stderr.strip().splitlines()
        assert result.returncode != 0 and len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
        assert fragment in lines[0]


def test_checkpoint_writes_are_atomic_and_validated(tmp_path):
    target = ckpt.step_dir(tmp_path, 3)
    ckpt.save_checkpoint(target, {"kind": "dit"}, {"w": torch.ones(2)})
    ckpt.save_checkpoint(target, {"kind": "dit"}, {"w": torch.zeros(2)})  # replaces in place
    assert ckpt.resolve(tmp_path) == target
    assert torch.equal(ckpt.load_tensors(target / ckpt.WEIGHTS)["w"], torch.zeros(2))
    assert sorted(p.name for p in target.parent.iterdir()) == ["step_00000003"]
    # a half-written checkpoint (no weights) is ignored by resolve
    (ckpt.step_dir(tmp_path, 9)).mkdir()
    assert ckpt.resolve(tmp_path) == target
    module = torch.nn.Linear(2, 3)
    with pytest.raises(CmtoolError, match="do not match"):
        ckpt.load_weights(module, target / ckpt.WEIGHTS)
    (target / ckpt.WEIGHTS).write_bytes(b"garbage")
    with pytest.raises(CmtoolError, match="unreadable"):
        ckpt.load_tensors(target / ckpt.WEIGHTS)
