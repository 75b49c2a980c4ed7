"""The training pipeline end to end on a tiny dataset: rvae -> latent cache -> dit -> controlnet,
checkpoints, exact resume after kill -9, DDP on two CPU processes, and `cmtool info`."""

import json
import os
import shutil
import subprocess
import sys
import time
import warnings

import cv2
import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader
from safetensors.torch import load_file, save_file

from cmtool.core.errors import CmtoolError
from cmtool.model import checkpoint as ckpt
from cmtool.train.precision import cpu_has_native_bf16
from tests.conftest import REPO

TINY_MODELS = {
    "rvae": '[rvae]\nd_model = 32\ndecoder_layers = 1\nheads = 2\nffn = 64\ndropout = 0.0\n',
    "dit": '[dit]\nsize = "tiny"\ndepth = 2\nhidden = 32\nheads = 2\n',
    "controlnet": '[dit]\nsize = "tiny"\ndepth = 2\nhidden = 32\nheads = 2\n[control]\nnum_blocks = 2\nwidths = [8, 8, 16, 16]\ngroups = 4\n',
    "decoder": "",  # the decoder stage takes its model from the RVAE run
    "encoder": "",  # ... and the encoder stage from the RVAE whose decoder it trains for
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
                         ("controlnet", {"data": str(data), "rvae": str(root / "rvae"), "dit": str(root / "dit"),
                                         "min_snr_gamma": 5.0})):
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
    assert steps["/train/mse"] == {1, 2, 3, 4}  # train.min_snr_gamma: the weighted loss, and the plain MSE beside it
    assert steps["/train/preview/sample_0/control/sd"] == {4}
    assert steps["/train/preview/sample_0/generated/hd/lanes"] == {4}


def test_the_training_recording_holds_only_the_calls_since_its_last_write(tmp_path):
    """A long run's recording is merged into its file at each checkpoint, not kept whole in memory."""
    import rerun as rr

    from cmtool.viz.recording import ReplayRecording, training_blueprint

    rec = ReplayRecording("train", tmp_path / "train.rrd")
    rec.send_blueprint(training_blueprint("rvae", []))
    for step in range(1, 31):
        rec.set_time("train_step", sequence=step)
        rec.log("train/loss", rr.Scalars(float(step)))
        if step % 10 == 0:
            rec.write()
            assert rec.calls == [] and recording_steps(tmp_path / "train.rrd")["/train/loss"] == set(range(1, step + 1))
    assert [p.name for p in tmp_path.iterdir()] == ["train.rrd"]
    assert len(RrdReader(tmp_path / "train.rrd").blueprints()) == 1


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
    deadline = time.time() + 600  # a loaded machine
    while proc.poll() is None and time.time() < deadline and len(ckpt.run_checkpoints(crashed)) < 1:
        time.sleep(0.05)
    proc.kill()
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
    longer = cli("train", "controlnet", "--recipe", recipe, "--out", run, "--resume", "--steps", "6")
    assert longer.returncode == 0, longer.stderr
    assert "resumed from step 4 of 6 (step_00000004)" in longer.stderr  # and counts on from there
    assert "train controlmap  6/6 steps (100%)" in longer.stderr and "1/2 steps" not in longer.stderr
    config = ckpt.load_config(run)
    assert config["step"] == 6 and config["complete"] and config["training"]["samples"] == 6 * 4


def test_a_model_whose_rvae_trained_further_is_refused(runs, tmp_path):
    """A ControlMap names its RVAE by its run folder and records the weights it was trained on: once that run trains
    further, its latents would decode into other maps, so sampling and packing refuse it in one line."""
    rvae = tmp_path / "rvae"
    shutil.copytree(runs["rvae"], rvae)
    model = ckpt.resolve(shutil.copytree(runs["controlnet"], tmp_path / "controlnet"))
    config = ckpt.load_config(model)
    assert config["rvae_weights"] == ckpt.weights_digest(ckpt.resolve(runs["rvae"]))
    ckpt.update_config(model, {"rvae": str(rvae)})
    sample = ("sample", "--ckpt", model, "--sd", REPO / "sample_data" / "sd_lav.png", "--steps", 2, "--no-log",
              "--quiet", "--out", tmp_path / "maps")
    assert cli(*sample).returncode == 0
    further = cli("train", "rvae", "--recipe", runs["rvae_recipe"], "--out", rvae, "--resume", "--steps", 6, "--quiet")
    assert further.returncode == 0, further.stderr
    for args in (sample, ("pack", "--ckpt", model, "--out", tmp_path / "packed")):
        result = cli(*args)
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
        assert f"trained on the RVAE weights {config['rvae_weights']}, but its RVAE" in result.stderr
        assert str(rvae) in result.stderr and len(result.stderr.strip().splitlines()) == 1


def _encoder(tensors):
    return {k: v for k, v in tensors.items() if k.startswith(("trunk.", "to_latent."))}


def test_encoder_stage_trains_an_encoder_for_a_frozen_packed_decoder(runs, tmp_path):
    root = runs["root"]
    packed = cli("pack", "--ckpt", runs["controlnet"], "--out", tmp_path / "w")  # a decoder-only RVAE, as shipped
    assert packed.returncode == 0, packed.stderr
    recipe = write_recipe(tmp_path / "encoder.toml", "encoder", 4, data=str(runs["data"]),
                          rvae=str(tmp_path / "w" / "rvae"))
    result = cli("train", "encoder", "--recipe", recipe, "--out", tmp_path / "enc", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "encoder: the latent scale of its train means" in result.stdout
    parent, config = ckpt.load_config(tmp_path / "w" / "rvae"), ckpt.load_config(tmp_path / "enc")
    assert config["latent_scale"] == parent["latent_scale"] and config["own_latent_scale"] > 0
    assert (tmp_path / "enc" / "latents" / "train.npz").is_file() and config["decoder_from"]
    decoder = load_file(str(tmp_path / "w" / "rvae" / ckpt.WEIGHTS))
    after = load_file(str(ckpt.resolve(tmp_path / "enc") / ckpt.WEIGHTS))
    assert all(torch.equal(v.float(), after[k]) for k, v in decoder.items())  # the decoder stayed as packed
    trained = load_file(str(ckpt.resolve(root / "rvae") / ckpt.WEIGHTS))
    assert _encoder(after) and not torch.equal(after["trunk.0.weight"], trained["trunk.0.weight"])
    # it ships beside that decoder (pack --encoder), and the packed weights then encode by themselves
    packed = cli("pack", "--ckpt", runs["controlnet"], "--rvae", tmp_path / "w" / "rvae", "--encoder", tmp_path / "enc",
                 "--out", tmp_path / "full")
    assert packed.returncode == 0, packed.stderr
    shipped = ckpt.read_weights(tmp_path / "full" / "rvae")
    assert all(torch.equal(v, after[k].half()) for k, v in shipped.items()) and _encoder(shipped).keys() == \
        _encoder(after).keys()
    assert ckpt.load_config(tmp_path / "full" / "rvae")["encoder_trained"]["step"] == 4
    assert "trained for this decoder by `cmtool train encoder`" in cli("info", tmp_path / "full" / "rvae").stdout
    from cmtool.sample.generator import MapGenerator
    assert MapGenerator.load(tmp_path / "full" / "controlmap").encode([]).shape == (0, 64, 8, 8)
    assert "frozen, from" in cli("info", tmp_path / "enc").stdout
    assert "which stays frozen" in cli("info", recipe).stdout


def test_encoder_stage_names_a_decoder_weight_of_the_wrong_shape(runs, tmp_path):
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import EncoderStage

    assert cli("pack", "--ckpt", runs["controlnet"], "--out", tmp_path / "w").returncode == 0
    weights = load_file(str(tmp_path / "w" / "rvae" / ckpt.WEIGHTS))
    weights["query.weight"] = weights["query.weight"][:-1]
    save_file(weights, str(tmp_path / "w" / "rvae" / ckpt.WEIGHTS))
    recipe = write_recipe(tmp_path / "encoder.toml", "encoder", 2, data=str(runs["data"]),
                          rvae=str(tmp_path / "w" / "rvae"))
    with pytest.raises(CmtoolError, match=r"query.weight of shape \(\d+, \d+\), not"):
        EncoderStage(load_recipe(recipe), torch.device("cpu")).model()


def test_decoder_stage_trains_the_decoder_on_the_frozen_encoder(runs, tmp_path):
    root = runs["root"]
    recipe = write_recipe(tmp_path / "decoder.toml", "decoder", 4, data=str(runs["data"]), rvae=str(root / "rvae"))
    result = cli("train", "decoder", "--recipe", recipe, "--out", tmp_path / "dec", "--quiet")
    assert result.returncode == 0, result.stderr
    assert "decoder: held-out reconstruction at 1 m" in result.stdout
    parent, config = ckpt.load_config(root / "rvae"), ckpt.load_config(tmp_path / "dec")
    assert config["kind"] == "rvae" and config["latent_scale"] == parent["latent_scale"]
    assert config["latents"] == str((root / "rvae" / "latents").resolve()) and not (tmp_path / "dec" / "latents").exists()
    before = load_file(str(ckpt.resolve(root / "rvae") / ckpt.WEIGHTS))
    after = load_file(str(ckpt.resolve(tmp_path / "dec") / ckpt.WEIGHTS))
    assert all(torch.equal(v, after[k]) for k, v in _encoder(before).items())
    assert not torch.equal(before["query.weight"], after["query.weight"])  # the decoder did train
    assert "frozen, from" in cli("info", tmp_path / "dec").stdout
    assert "its encoder stays frozen" in cli("info", recipe).stdout
    # a DiT trains on the decoder run: it reads the parent's latent cache
    dit = write_recipe(tmp_path / "dit.toml", "dit", 2, rvae=str(tmp_path / "dec"), preview_every=0)
    assert cli("train", "dit", "--recipe", dit, "--out", tmp_path / "dit", "--quiet").returncode == 0

    # cmtool pack --rvae ships the fine-tuned decoder with a ControlMap trained on the parent
    packed = cli("pack", "--ckpt", runs["controlnet"], "--rvae", tmp_path / "dec", "--out", tmp_path / "w")
    assert packed.returncode == 0, packed.stderr
    shipped = load_file(str(tmp_path / "w" / "rvae" / ckpt.WEIGHTS))
    assert not _encoder(shipped) and torch.equal(shipped["query.weight"], after["query.weight"].half())
    # an encoder for another decoder does not ship with this one
    refused = cli("pack", "--ckpt", runs["controlnet"], "--rvae", tmp_path / "dec", "--encoder", root / "rvae",
                  "--out", tmp_path / "w5")
    assert refused.returncode == 1 and "its decoder or latent scale is not the one that ships" in refused.stderr
    # ... but refuses an RVAE with another encoder
    other = tmp_path / "other"
    shutil.copytree(ckpt.resolve(tmp_path / "dec"), other)
    after["trunk.0.weight"] = after["trunk.0.weight"] + 1.0
    save_file(after, str(other / ckpt.WEIGHTS))
    refused = cli("pack", "--ckpt", runs["controlnet"], "--rvae", other, "--out", tmp_path / "w2")
    assert refused.returncode == 1 and "encoder or latent scale differs" in refused.stderr
    # an already packed decoder (no encoder to compare) ships again when its latent scale matches
    repacked = cli("pack", "--ckpt", runs["controlnet"], "--rvae", tmp_path / "w" / "rvae", "--out", tmp_path / "w3")
    assert repacked.returncode == 0, repacked.stderr
    again = load_file(str(tmp_path / "w3" / "rvae" / ckpt.WEIGHTS))
    assert again.keys() == shipped.keys() and all(torch.equal(v, shipped[k]) for k, v in again.items())
    assert ckpt.load_config(tmp_path / "w3" / "rvae")["packed_from"] == "dec/checkpoints/step_00000004"
    config = json.loads((tmp_path / "w" / "rvae" / ckpt.CONFIG).read_text())
    (tmp_path / "w" / "rvae" / ckpt.CONFIG).write_text(json.dumps({**config, "latent_scale": config["latent_scale"] * 2}))
    refused = cli("pack", "--ckpt", runs["controlnet"], "--rvae", tmp_path / "w" / "rvae", "--out", tmp_path / "w4")
    assert refused.returncode == 1 and "encoder or latent scale differs" in refused.stderr


def test_mirrored_scenes_take_a_label_of_the_other_driving_side(runs, tmp_path):
    from cmtool.data.cache import load_dataset
    from cmtool.maps.hdmap import drives_on
    from cmtool.train.data import SceneRasters
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import ControlNetStage, DiTStage

    # the mirrored HD raster is the plain one flipped left-right (to within the one pixel by which
    # OpenCV's thick lines lean), its heading sine negated
    scenes = load_dataset(runs["data"], "train")
    plain, mirrored = SceneRasters(scenes)[0]["raster"].numpy(), SceneRasters(scenes, mirror=True)[0]["raster"].numpy()
    a, b = plain[0, :, ::-1] > 0, mirrored[0] > 0
    near = lambda m: cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # noqa: E731
    assert a.sum() > 100 and (a & near(b)).sum() / a.sum() > 0.97 and (b & near(a)).sum() / b.sum() > 0.97
    both = a & b
    assert np.abs(mirrored[1][both] - (1.0 - plain[1, :, ::-1][both])).mean() < 0.05
    assert np.abs(mirrored[0][both] - plain[0, :, ::-1][both]).mean() < 0.05

    root = runs["root"]
    rvae = tmp_path / "rvae"
    shutil.copytree(root / "rvae", rvae)
    recipe = write_recipe(tmp_path / "c.toml", "controlnet", 2, data=str(runs["data"]), rvae=str(rvae),
                          dit=str(root / "dit"), mirror=0.5, sd_shift_m=3.0, preview_every=0)
    result = cli("train", "controlnet", "--recipe", recipe, "--out", tmp_path / "cn", "--quiet")
    assert result.returncode == 0, result.stderr
    with np.load(rvae / "latents" / "train.npz") as p, np.load(rvae / "latents" / "train_mirrored.npz") as m:
        assert p["mean"].shape == m["mean"].shape and not np.array_equal(p["mean"], m["mean"])
        assert np.array_equal(p["pose"], m["pose"])
    stage = ControlNetStage(load_recipe(recipe), torch.device("cpu"))
    assert stage.cities == ["LAV", "PIT", "SGP"] and stage.shift_px == 6  # 3 m at 0.5 m per pixel
    # right-hand LAV and PIT become left-hand SGP; SGP cycles through LAV and PIT
    assert stage.mirror_labels(np.array(["LAV", "PIT", "SGP", "SGP"])).tolist() == [2, 2, 0, 1]

    # the DiT stage mirrors the same way, drawing the scenes from the dataset its RVAE was trained on
    # (no train.data), and reuses the cached mirrored latents
    (rvae / "latents" / "train_mirrored.npz").rename(tmp_path / "first.npz")
    dit = write_recipe(tmp_path / "d.toml", "dit", 2, rvae=str(rvae), mirror=0.5, preview_every=0)
    result = cli("train", "dit", "--recipe", dit, "--out", tmp_path / "dit", "--quiet")
    assert result.returncode == 0, result.stderr
    with np.load(tmp_path / "first.npz") as a, np.load(rvae / "latents" / "train_mirrored.npz") as b:
        assert np.array_equal(a["mean"], b["mean"])
    dit_stage = DiTStage(load_recipe(dit), torch.device("cpu"))
    items = dit_stage.dataset()
    sides = [drives_on(c) for c in dit_stage.cities]
    assert all(sides[a] != sides[b] for a, b in zip(items.label, items.mirrored[2]))
    assert items[0]["mirror_mean"].shape == items[0]["mean"].shape


def test_control_branch_starts_from_another_controlmap(runs, tmp_path):
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import ControlNetStage

    root = runs["root"]
    recipe = write_recipe(tmp_path / "c.toml", "controlnet", 2, data=str(runs["data"]), rvae=str(root / "rvae"),
                          dit=str(root / "dit"), branch_from=str(runs["controlnet"]), preview_every=0)
    model = ControlNetStage(load_recipe(recipe), torch.device("cpu")).model()
    start = model.state_dict()
    branch = load_file(str(ckpt.resolve(runs["controlnet"]) / ckpt.WEIGHTS))
    dit = load_file(str(ckpt.resolve(runs["dit"]) / ckpt.WEIGHTS))
    assert any("zero" in k and v.abs().sum() > 0 for k, v in branch.items())  # a trained branch, not zeros
    for k, v in start.items():
        want = dit[k[len("base."):]] if k.startswith("base.") else branch[k]
        assert torch.equal(v, want), k

    result = cli("train", "controlnet", "--recipe", recipe, "--out", tmp_path / "cn", "--quiet")
    assert result.returncode == 0, result.stderr
    assert ckpt.load_config(tmp_path / "cn")["branch_from"] == str(ckpt.resolve(runs["controlnet"]).resolve())
    assert "branch_from" in cli("info", tmp_path / "cn").stdout

    other = recipe.read_text().replace("num_blocks = 2", "num_blocks = 1")
    (tmp_path / "other.toml").write_text(other)
    with pytest.raises(CmtoolError, match="branch_from needs a ControlMap"):
        ControlNetStage(load_recipe(tmp_path / "other.toml"), torch.device("cpu")).model()


def test_a_branch_that_reads_the_rule_layout_starts_as_the_branch_without(runs, tmp_path, capsys):
    from cmtool.data.cache import load_dataset
    from cmtool.data.synth import generate_city
    from cmtool.model.controlmap import sd_tensor
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import ControlNetStage
    from tests.conftest import in_process

    root = runs["root"]
    layout = '\nin_channels = 5\nlayout = "rules"\n'
    recipe = write_recipe(tmp_path / "c.toml", "controlnet", 2, data=str(runs["data"]), rvae=str(root / "rvae"),
                          dit=str(runs["controlnet"]), branch_from=str(runs["controlnet"]), layout_dropout=0.5,
                          preview_every=0)
    recipe.write_text(recipe.read_text() + layout)
    stage = ControlNetStage(load_recipe(recipe), torch.device("cpu"))  # the DiT taken from a ControlMap's base
    model = stage.model().eval()
    old, _ = ckpt.load_model(runs["controlnet"], "cpu")
    first = model.encoder.stages[0].down.weight
    assert first.shape[1] == 5 and torch.equal(first[:, 3:], torch.zeros_like(first[:, 3:]))
    # the control images of the train scenes: SD raster, then the rule layout's lanes on the SD roads
    images = stage.dataset().sd
    scenes = load_dataset(runs["data"], "train")
    assert images.shape == (24, 128, 128, 5) and np.array_equal(images[..., :3], scenes.arrays["sd"])
    lanes = images[..., 3:].any(-1)
    near = np.stack([cv2.dilate((sd[..., 0] > 0).astype(np.uint8), np.ones((25, 25))) > 0 for sd in images])
    assert lanes.sum() > 24 * 200 and (lanes & near).sum() > 0.9 * lanes.sum()
    x, t, y = torch.randn(4, 64, 8, 8), torch.tensor([10, 200, 500, 900]), torch.tensor([0, 1, 2, 3])
    control = torch.stack([sd_tensor(c) for c in images[:4]])
    with torch.no_grad():
        assert torch.allclose(model(x, t, y, control=control), old(x, t, y, control=control[:, :3]), atol=1e-5)

    result = cli("train", "controlnet", "--recipe", recipe, "--out", tmp_path / "cn", "--quiet")
    assert result.returncode == 0, result.stderr
    city = tmp_path / "pit.json"
    generate_city("PIT", seed=2, extent=300.0).save(city)
    code, _, err = in_process(capsys, "sample", "--ckpt", tmp_path / "cn", "--from-hd", city, "--steps", 3, "--quiet",
                              "--out", tmp_path / "maps")
    assert code == 0, err
    (made,) = [p for p in (tmp_path / "maps").glob("*.json") if not p.name.endswith(".gt.json")]
    assert json.loads(made.read_text())["meta"]["layout"] == "rules"
    assert "/control/layout" in {str(c.entity_path) for c in RrdReader(tmp_path / "maps" / "sample.rrd").stream()}
    code, _, err = in_process(capsys, "sample", "--ckpt", tmp_path / "cn", "--sd", REPO / "sample_data" / "sd_lav.png",
                              "--steps", 3, "--no-log", "--quiet", "--out", tmp_path / "pic")  # its roads traced
    assert code == 0, err
    (made,) = (tmp_path / "pic").glob("*.json")
    assert json.loads(made.read_text())["meta"]["layout"] == "rules"

    bad = recipe.read_text().replace("in_channels = 5", "in_channels = 3")
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(CmtoolError, match="control.in_channels: must be 5"):
        ControlNetStage(load_recipe(tmp_path / "bad.toml"), torch.device("cpu")).model()


def test_dit_starts_from_a_dit_or_a_controlmaps_frozen_base(runs, tmp_path, capsys):
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import DiTStage

    root = runs["root"]
    dit = load_file(str(ckpt.resolve(runs["dit"]) / ckpt.WEIGHTS))
    base = {k[len("base."):]: v for k, v in load_file(str(ckpt.resolve(runs["controlnet"]) / ckpt.WEIGHTS)).items()
            if k.startswith("base.")}
    assert not any(torch.equal(v, torch.zeros_like(v)) for k, v in dit.items() if "adaLN" in k)  # trained, not init
    for source, want in ((runs["dit"], dit), (runs["controlnet"], base)):
        recipe = write_recipe(tmp_path / "d.toml", "dit", 2, rvae=str(root / "rvae"), init_from=str(source),
                              preview_every=0)
        start = DiTStage(load_recipe(recipe), torch.device("cpu")).model().state_dict()
        assert start.keys() == want.keys() and all(torch.equal(start[k], want[k]) for k in want)

    result = cli("train", "dit", "--recipe", recipe, "--out", tmp_path / "further", "--quiet")
    assert result.returncode == 0, result.stderr
    record = ckpt.load_config(tmp_path / "further")["init_from"]
    assert record["path"] == str(ckpt.resolve(runs["controlnet"]).resolve())
    assert record["training"] == ckpt.load_config(runs["dit"])["training"]  # the ControlMap's DiT, not the ControlMap
    assert record["training"] != ckpt.load_config(runs["controlnet"])["training"]
    assert "DiT started from" in cli("info", tmp_path / "further").stdout

    (tmp_path / "deeper.toml").write_text(recipe.read_text().replace("depth = 2", "depth = 3"))
    with pytest.raises(CmtoolError, match="not the one this recipe builds"):
        DiTStage(load_recipe(tmp_path / "deeper.toml"), torch.device("cpu")).model()
    # a DiT of another RVAE's latents is a starting point only: a warning, recorded
    other = tmp_path / "other_dit"
    shutil.copytree(ckpt.resolve(runs["dit"]), other)
    config = json.loads((other / ckpt.CONFIG).read_text())
    (other / ckpt.CONFIG).write_text(json.dumps({**config, "latent_scale": config["latent_scale"] * 1.01}))
    (tmp_path / "other.toml").write_text(recipe.read_text().replace(str(runs["controlnet"]), str(other)))
    stage = DiTStage(load_recipe(tmp_path / "other.toml"), torch.device("cpu"))
    stage.model()
    assert "trained on other latents" in capsys.readouterr().err
    assert stage.config()["init_from"]["latent_scale"] == config["latent_scale"] * 1.01


def test_stages_from_checkpoints_check_their_size_without_their_weights(runs, tmp_path):
    """The size check builds a stage's model on the meta device; weights read into it did nothing but make torch warn
    once per tensor (309 warnings in the decoder stage)."""
    from cmtool.train.loop import _check_size
    from cmtool.train.recipe import load_recipe
    from cmtool.train.stages import ControlNetStage, DecoderStage, DiTStage, EncoderStage

    root, data = runs["root"], str(runs["data"])
    stages = {DecoderStage: write_recipe(tmp_path / "dec.toml", "decoder", 2, data=data, rvae=str(root / "rvae")),
              EncoderStage: write_recipe(tmp_path / "enc.toml", "encoder", 2, data=data,
                                         rvae=str(REPO / "cmtool" / "weights" / "rvae")),
              DiTStage: write_recipe(tmp_path / "dit.toml", "dit", 2, rvae=str(root / "rvae"),
                                     init_from=str(runs["dit"])),
              ControlNetStage: write_recipe(tmp_path / "cn.toml", "controlnet", 2, data=data, rvae=str(root / "rvae"),
                                            dit=str(runs["dit"]), branch_from=str(runs["controlnet"]))}
    for kind, recipe in stages.items():
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            _check_size(kind(load_recipe(recipe), torch.device("cpu")))


def test_progress_prints_its_final_line_once():
    import io

    from cmtool.core.progress import Progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for stream in (io.StringIO(), Terminal()):
        for steps in ([3], [2, 1]):  # the last update drawn (the first one always is), or not
            stream.seek(0)
            stream.truncate()
            with Progress(3, "train", "steps", stream=stream) as bar:
                for n in steps:
                    bar.update(n)
            lines = stream.getvalue().replace("\r\033[K", "\n").splitlines()
            assert sum("3/3 steps (100%)" in line for line in lines) == 1, (lines, steps)
            assert stream.getvalue().endswith("\n")


def test_bf16_precision_trains_under_autocast_on_cpu(runs, tmp_path):
    auto = ckpt.load_config(runs["dit"])["training"]["precision"]
    assert auto == "fp32" or cpu_has_native_bf16()  # auto: bf16 only where the CPU computes it natively
    recipe = write_recipe(tmp_path / "dit.toml", "dit", 2, rvae=str(runs["root"] / "rvae"), preview_every=0)
    weights = {}
    for precision in ("fp32", "bf16"):
        result = cli("train", "dit", "--recipe", recipe, "--out", tmp_path / precision, "--precision", precision,
                     "--quiet")
        assert result.returncode == 0, result.stderr
        # bf16 emulated on this CPU is many times slower than fp32: the run says so
        assert ("without native bf16" in result.stderr) == (precision == "bf16" and not cpu_has_native_bf16())
        config = ckpt.load_config(tmp_path / precision)
        assert config["training"]["precision"] == precision and config["recipe"]["train"]["precision"] == precision
        weights[precision] = load_file(str(ckpt.resolve(tmp_path / precision) / ckpt.WEIGHTS))
    differ = [k for k, v in weights["fp32"].items() if not torch.equal(v, weights["bf16"][k])]
    assert differ  # the same seed and data: only the autocast tells the two runs apart
    assert all(torch.allclose(v, weights["bf16"][k], atol=0.05) for k, v in weights["fp32"].items())


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
    narrow = write_recipe(tmp_path / "n.toml", "rvae", 2, data=str(runs["data"]))
    narrow.write_text(narrow.read_text() + "num_lines = 30\n")  # into [rvae]; the tiny data has 50 lines
    parent = shutil.copytree(ckpt.resolve(root / "rvae"), tmp_path / "narrow")  # an RVAE with 30 line queries
    config = json.loads((parent / ckpt.CONFIG).read_text())
    config["model"]["num_lines"] = 30
    (parent / ckpt.CONFIG).write_text(json.dumps(config))
    bad = [
        (["train", "rvae", "--recipe", narrow, "--out", tmp_path / "n"],
         "rvae.num_lines 30 is fewer than the dataset's num_lines 50"),
        (["train", "decoder", "--recipe", write_recipe(tmp_path / "dn.toml", "decoder", 2, data=str(runs["data"]),
                                                        rvae=str(parent)),
          "--out", tmp_path / "dn"], "train it on data built with data.num_lines = 30"),
        (["train", "dit", "--recipe", runs["rvae_recipe"], "--out", tmp_path / "x"], "rvae stage"),
        (["train", "controlnet", "--recipe", write_recipe(tmp_path / "c.toml", "controlnet", 2, data=str(runs["data"]),
                                                           rvae=str(root / "rvae"), dit=str(root / "rvae")),
          "--out", tmp_path / "y"], "needs a DiT"),
        (["train", "dit", "--recipe", write_recipe(tmp_path / "d.toml", "dit", 2, rvae=str(tmp_path / "none")),
          "--out", tmp_path / "z"], "train the rvae stage into it first: `cmtool train rvae"),
        (["pack", "--ckpt", tmp_path / "none", "--out", tmp_path / "p"], "train a ControlMap first"),
        (["info", tmp_path], "not a checkpoint"),
        (["train", "rvae", "--recipe", write_recipe(tmp_path / "m.toml", "rvae", 2, data=str(runs["data"]), mirror=0.5),
          "--out", tmp_path / "m"], "dit- and controlnet-stage option"),
        (["train", "rvae", "--recipe", write_recipe(tmp_path / "s.toml", "rvae", 2, data=str(runs["data"]),
                                                     min_snr_gamma=5.0),
          "--out", tmp_path / "s"], "train.min_snr_gamma: a dit- and controlnet-stage option"),
        (["train", "dit", "--recipe", write_recipe(tmp_path / "b.toml", "dit", 2, rvae=str(root / "rvae"),
                                                    branch_from=str(runs["controlnet"])),
          "--out", tmp_path / "b"], "controlnet-stage option"),
        (["train", "controlnet", "--recipe", write_recipe(tmp_path / "i.toml", "controlnet", 2, data=str(runs["data"]),
                                                           rvae=str(root / "rvae"), dit=str(root / "dit"),
                                                           init_from=str(root / "dit")),
          "--out", tmp_path / "i"], "dit-stage option"),
        (["train", "dit", "--recipe", write_recipe(tmp_path / "p.toml", "dit", 2, rvae=str(root / "rvae"),
                                                    precision="fp16"),
          "--out", tmp_path / "p"], "train.precision: expected one of auto, bf16, fp32"),
        (["train", "rvae", "--recipe", runs["rvae_recipe"], "--data", tmp_path / "elsewhere", "--out", tmp_path / "e"],
         "elsewhere"),  # --data replaces the recipe's (existing) dataset
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
        ckpt.load_weights(module, target)
    (target / ckpt.WEIGHTS).write_bytes(b"garbage")
    with pytest.raises(CmtoolError, match="not a valid safetensors file"):
        ckpt.load_tensors(target / ckpt.WEIGHTS)


def test_a_prune_killed_midway_leaves_no_half_deleted_checkpoint(tmp_path):
    """kill -9 while old checkpoints are deleted: what is left is a temporary folder that the next prune removes,
    never a step_* folder missing files."""
    for step in (1, 2, 3):
        ckpt.save_checkpoint(ckpt.step_dir(tmp_path, step), {"kind": "dit"}, {"w": torch.full((2,), float(step))},
                             state={"s": torch.ones(1)})
    killed = subprocess.run([sys.executable, "-c", (
        "import os, shutil, signal, sys\n"
        "import cmtool.model.checkpoint as c\n"
        "def rmtree(path, *a, **k):\n"
        "    os.remove(os.path.join(path, c.CONFIG))  # part of the folder is gone, then the process dies\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "shutil.rmtree = rmtree\n"
        "c.prune(sys.argv[1], 1)\n"), str(tmp_path)], cwd=REPO)
    assert killed.returncode == -9
    folders = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert [f for f in folders if f.startswith("step_")] == ["step_00000002", "step_00000003"]  # 1 was renamed away
    assert ckpt.resolve(tmp_path) == ckpt.step_dir(tmp_path, 3)
    (ckpt.step_dir(tmp_path, 2) / ckpt.CONFIG).unlink()  # a folder half deleted by an older cmtool
    ckpt.prune(tmp_path, 1)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step_00000003"]


def test_sd_shift_moves_each_raster_sideways_by_at_most_max_px():
    from cmtool.train.data import shift_sideways

    torch.manual_seed(0)
    x = torch.rand(64, 3, 8, 16) + 0.1  # no empty pixel, so the uncovered columns show
    y = shift_sideways(x, 3)

    def moved(a, s):
        out = torch.roll(a, s, dims=-1)
        if s > 0:
            out[..., :s] = 0
        if s < 0:
            out[..., s:] = 0
        return out

    shifts = [next((s for s in range(-3, 4) if torch.equal(b, moved(a, s))), None) for a, b in zip(x, y)]
    assert None not in shifts and set(shifts) == set(range(-3, 4))


@pytest.mark.parametrize("mirror", [False, True])
def test_training_rasters_drawn_once_equal_the_per_scene_drawing(tiny_data, mirror, monkeypatch):
    """The RVAE's items take their rasters from one drawing of every scene (in worker processes or not): the same
    floats as drawing each item's scene when it is asked for."""
    from cmtool.data.cache import load_dataset
    from cmtool.data.hd_raster import rasterize_scene
    from cmtool.train import data
    from cmtool.train.data import SceneRasters, drawn_scenes, vector_targets

    monkeypatch.setattr(data, "DRAW_CHUNK", 5)  # several chunks, for the workers
    scenes = load_dataset(tiny_data, "train")
    items = SceneRasters(scenes, mirror)
    assert all(np.array_equal(a, b) for a, b in zip(drawn_scenes(scenes, mirror, workers=1),
                                                    drawn_scenes(scenes, mirror, workers=2)))
    for i in range(len(scenes)):
        t = vector_targets(scenes.arrays, i, mirror)
        drawn = rasterize_scene(*(t[k].numpy() for k in ("lines", "line_mask", "green", "green_mask", "red",
                                                          "red_mask")), px_m=scenes.px_m, frame_m=scenes.frame_m)
        assert drawn.any() and np.array_equal(items[i]["raster"].numpy(), drawn)


@pytest.mark.skipif(not (REPO.parent / "shared" / "data" / "real").is_dir(), reason="no shared real maps here")
def test_real_frames_reach_the_batches_of_the_shipped_branch_trained_further(tmp_path):
    """A dataset with real maps (an Apollo and a Lanelet2 map) in its train split trains the shipped control branch
    further, as recipes/tiny-cpu/controlnet-real.toml does: the shipped RVAE encodes the new data into the data
    folder, the branch of SD encoding 1 starts one of encoding 2, and real scenes are in every batch; and the shipped
    DiT further, as dit-real.toml does, on the same latents."""
    from cmtool.data.cache import build_dataset, load_dataset
    from cmtool.train.data import StepBatches
    from cmtool.train.recipe import load_recipe

    shared = REPO.parent / "shared" / "data"
    text = (REPO / "recipes" / "data_tiny.toml").read_text().replace('train_cities = ["LAV", "PIT", "SGP"]',
                                                                     'train_cities = ["LAV"]')
    text += "".join(f'\n[[data.real_maps]]\nformat = "{fmt}"\npath = "{path}"\nscenes_per_map = 8\n'
                    for fmt, path in (("apollo", shared / "real" / "apollo" / "borregas_ave_base_map.bin"),
                                      ("lanelet2", shared / "lanelet2" / "mapping_example.osm")))
    (tmp_path / "data.toml").write_text(text)
    data = tmp_path / "data"
    build_dataset(load_recipe(tmp_path / "data.toml"), data, workers=1, progress=False)
    sources = load_dataset(data, "train").arrays["source"]
    real = np.array([not str(s).startswith("procedural") for s in sources])
    assert len(sources) == 24 and real.sum() == 16
    for batch in StepBatches(range(len(sources)), 8, 0, 1, 0, 0, 6):
        assert real[batch].any()

    def trained(stage: str, name: str, dit: str = "") -> dict:
        """The config of a 2-step run of recipes/tiny-cpu/NAME.toml on the data, at a batch the 24 scenes hold (over
        the DiT run ``dit`` where given)."""
        recipe = tmp_path / f"{name}.toml"
        text = (REPO / "recipes" / "tiny-cpu" / f"{name}.toml").read_text().replace("batch_size = 64", "batch_size = 8")
        recipe.write_text(text.replace('dit = "runs/tiny-cpu/dit-real"', f'dit = "{dit}"') if dit else text)
        result = cli("train", stage, "--recipe", recipe, "--data", data, "--out", tmp_path / name, "--steps", 2,
                     "--quiet", "--no-log")
        assert result.returncode == 0, result.stderr
        return ckpt.load_config(tmp_path / name)

    config = trained("controlnet", "controlnet-real")
    assert config["control"]["sd_encoding"] == 2 and config["branch_from"].endswith("weights/controlmap")
    (cache,) = (data / "latents").iterdir()
    with np.load(cache / "train.npz") as z:
        assert np.array_equal(z["pose"], load_dataset(data, "train").arrays["pose"])
    # the shipped DiT trained further on the same frames (dit-real.toml): the same latents, its own labels kept
    config = trained("dit", "dit-real")
    assert config["cities"] == ckpt.load_config(REPO / "cmtool" / "weights" / "controlmap")["cities"]
    assert config["init_from"]["path"].endswith("weights/controlmap") and [cache] == list((data / "latents").iterdir())
    # and the branch trained again over that DiT (controlnet-real-dit.toml)
    config = trained("controlnet", "controlnet-real-dit", dit=str(tmp_path / "dit-real"))
    assert config["dit"].startswith(str(tmp_path / "dit-real")) and config["branch_from"].endswith("weights/controlmap")
    assert config["control"]["sd_encoding"] == 2 and [cache] == list((data / "latents").iterdir())
