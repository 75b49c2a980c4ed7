"""`cmtool train pipeline`: the whole chain from one toy recipe, skipped when done, resumed after kill -9,
refused when a stage's recipe changed."""

import json
import shutil
import subprocess
import sys
import time

import pytest

from cmtool.core.jsonio import read_json
from cmtool.model import checkpoint as ckpt
from tests.conftest import REPO
from tests.test_train import cli, write_recipe

STAGES = ["data", "rvae", "decoder", "dit", "controlnet", "pack", "eval"]


def write_pipeline(folder, dit_steps=12):
    """A toy pipeline recipe in ``folder``: the tiny data set, tiny models, a few steps each."""
    folder.mkdir(parents=True, exist_ok=True)
    write_recipe(folder / "rvae.toml", "rvae", 4, data="ignored", out="ignored")
    write_recipe(folder / "decoder.toml", "decoder", 4)
    write_recipe(folder / "dit.toml", "dit", dit_steps, ckpt_every=1, preview_every=0)
    write_recipe(folder / "controlnet.toml", "controlnet", 4)
    (folder / "pipeline.toml").write_text(
        f'[pipeline]\ndata = {json.dumps(str(REPO / "recipes" / "data_tiny.toml"))}\nrvae = "rvae.toml"\n'
        'decoder = "decoder.toml"\ndit = "dit.toml"\ncontrolnet = "controlnet.toml"\n'
        '[pipeline.eval]\nn = 4\nsteps = 2\nbatch = 4\nrrd_samples = 1\n')
    return folder / "pipeline.toml"


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """One uninterrupted pipeline run."""
    root = tmp_path_factory.mktemp("pipeline")
    recipe = write_pipeline(root / "recipes")
    result = cli("train", "pipeline", "--recipe", recipe, "--out", root / "run", "--quiet")
    assert result.returncode == 0, result.stderr
    return {"root": root, "recipe": recipe, "run": root / "run", "stdout": result.stdout, "stderr": result.stderr}


def test_pipeline_runs_every_stage_and_reports(straight):
    run = straight["run"]
    state = read_json(run / "pipeline.json")
    assert list(state["stages"]) == STAGES and all(s["done"] for s in state["stages"].values())
    for k, name in enumerate(STAGES, start=1):
        assert f"pipeline: stage {k}/7 {name}" in straight["stderr"]
        assert any(line.startswith(name) and " ran " in line for line in straight["stdout"].splitlines())
    # each stage read the one before: the DiT trained on this RVAE's latents, the weights ship the decoder
    assert ckpt.load_config(run / "dit")["rvae"].startswith(str(run / "rvae"))
    assert ckpt.load_config(run / "decoder")["step"] == 4
    assert (run / "weights" / "controlmap" / ckpt.WEIGHTS).is_file()
    assert read_json(run / "weights" / "MANIFEST.json")["files"]
    assert (run / "eval" / "summary.md").is_file() and "lane_f1" in state["stages"]["eval"]["result"]
    assert state["stages"]["rvae"]["result"]["steps"] == 4


def test_finished_pipeline_is_skipped_and_a_changed_stage_refused(straight, tmp_path):
    recipe, run = straight["recipe"], straight["run"]
    again = cli("train", "pipeline", "--recipe", recipe, "--out", run, "--quiet")
    assert again.returncode == 1 and "pass --resume" in again.stderr
    resumed = cli("train", "pipeline", "--recipe", recipe, "--out", run, "--resume", "--quiet")
    assert resumed.returncode == 0, resumed.stderr
    assert resumed.stdout.count("skipped (done)") == len(STAGES)
    # the DiT's recipe changes: the DiT folder is not silently reused
    changed = write_pipeline(tmp_path / "recipes", dit_steps=13)
    refused = cli("train", "pipeline", "--recipe", changed, "--out", run, "--resume", "--quiet")
    assert refused.returncode == 1 and f"{run / 'dit'}: made from another recipe" in refused.stderr
    assert f"remove {run / 'dit'}, {run / 'controlnet'}, {run / 'weights'}, {run / 'eval'} to" in refused.stderr
    assert "Traceback" not in refused.stderr
    # ... as it says: the removed stages are made again, the others skipped
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    for name in ("dit", "controlnet", "weights", "eval"):
        shutil.rmtree(copy / name)
    again = cli("train", "pipeline", "--recipe", changed, "--out", copy, "--resume", "--quiet")
    assert again.returncode == 0, again.stderr
    assert again.stdout.count("skipped (done)") == 3 and ckpt.load_config(copy / "dit")["step"] == 13
    # a recipe that is not a pipeline's, and a folder the pipeline did not make
    single = cli("train", "pipeline", "--recipe", run.parent / "recipes" / "dit.toml", "--out", tmp_path / "x")
    assert single.returncode == 1 and "no [pipeline] table" in single.stderr
    whole = cli("train", "rvae", "--recipe", recipe, "--out", tmp_path / "x")
    assert whole.returncode == 1 and "a pipeline recipe; run it with `cmtool train pipeline`" in whole.stderr
    (tmp_path / "y" / "rvae").mkdir(parents=True)
    (tmp_path / "y" / "rvae" / "notes.txt").write_text("mine")
    foreign = cli("train", "pipeline", "--recipe", recipe, "--out", tmp_path / "y", "--data", run / "data")
    assert foreign.returncode == 1 and "was not made by this pipeline" in foreign.stderr


def test_pipeline_resumes_after_kill_to_the_same_weights(straight, tmp_path):
    """Killed and resumed, without recordings (--no-log), the chain packs the weights of the straight run."""
    out, log = tmp_path / "crashed", tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "cmtool", "train", "pipeline", "--recipe",
                                 str(straight["recipe"]), "--out", str(out), "--quiet", "--no-log"], cwd=REPO,
                                stdout=subprocess.DEVNULL, stderr=err)
    deadline = time.time() + 900  # a loaded machine: the straight run's stages take seconds each when idle
    while proc.poll() is None and time.time() < deadline and len(ckpt.run_checkpoints(out / "dit")) < 2:
        time.sleep(0.05)
    reached = len(ckpt.run_checkpoints(out / "dit")) >= 2
    proc.kill()  # SIGKILL: no clean-up
    proc.wait()
    assert reached, f"the run never reached its second DiT checkpoint (exit {proc.returncode}):\n{log.read_text()}"
    state = read_json(out / "pipeline.json")["stages"]
    assert state["rvae"]["done"] and not state["dit"]["done"] and "controlnet" not in state
    resumed = cli("train", "pipeline", "--recipe", straight["recipe"], "--out", out, "--resume", "--quiet", "--no-log")
    assert resumed.returncode == 0, resumed.stderr
    assert resumed.stdout.count("skipped (done)") == 3  # data, rvae, decoder
    assert not list(out.rglob("*.rrd")) and (out / "eval" / "summary.md").is_file()  # --no-log: no recording
    weights = {k: v["sha256"] for k, v in read_json(out / "weights" / "MANIFEST.json")["files"].items()
               if k.endswith(ckpt.WEIGHTS)}
    expected = {k: v["sha256"] for k, v in read_json(straight["run"] / "weights" / "MANIFEST.json")["files"].items()
                if k.endswith(ckpt.WEIGHTS)}
    assert len(weights) == 2 and weights == expected  # the ControlMap and the decoder, bit for bit


@pytest.mark.parametrize("name, limit", [("tiny-cpu", 30e6), ("gpu", 60e6)])
def test_shipped_pipeline_recipes_load_and_pack_under_their_size(name, limit):
    """Every stage recipe of a shipped pipeline loads for its stage, the ControlMap's DiT is the DiT stage's,
    and what pack ships (the whole ControlMap and the RVAE's decoder, float16) stays under ``limit`` bytes."""
    import dataclasses

    from cmtool.model.controlmap import ControlMap
    from cmtool.model.dit import DiT
    from cmtool.model.rvae import ENCODER_PREFIXES, RVAE
    from cmtool.pipeline import stage_recipes
    from cmtool.train.recipe import load_recipe

    files = stage_recipes(load_recipe(REPO / "recipes" / name / "pipeline.toml"))
    recipes = {stage: load_recipe(path) for stage, path in files.items() if stage != "data"}
    assert all(r.train.stage == stage for stage, r in recipes.items())
    assert recipes["controlnet"].dit == recipes["dit"].dit
    cities = 3  # the train cities of recipes/data_cpu.toml
    dit = DiT(dataclasses.replace(recipes["dit"].dit, num_classes=cities).resolved())
    controlmap = ControlMap(dit, recipes["controlnet"].control)
    rvae = RVAE(recipes["rvae"].rvae)
    shipped = sum(v.numel() for v in controlmap.state_dict().values()) + \
        sum(v.numel() for k, v in rvae.state_dict().items() if not k.startswith(ENCODER_PREFIXES))
    assert 2 * shipped < limit
