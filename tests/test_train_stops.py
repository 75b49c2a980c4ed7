"""What a training run does after its last step, and how it picks its precision: a stop while the RVAE encodes its
latent cache (Ctrl-C, kill -9) keeps the last step, `cmtool info` says how far the encoding got, and the same command
again finishes the encoding without training; ``precision = auto`` decides from the device and a measurement, and
says why."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from cmtool.model import checkpoint as ckpt
from cmtool.train import latents
from cmtool.train import precision as P
from tests.conftest import REPO, in_process, interrupted_at
from tests.test_train import write_recipe

pytestmark = pytest.mark.usefixtures("one_thread")

PART = 8  # scenes a part of the latent encoding holds here: the tiny data's 24 train scenes make 3 parts


def test_auto_precision_takes_bf16_only_where_native_and_faster(tmp_path, monkeypatch):
    cpu = torch.device("cpu")
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse avx512f avx512_bf16 amx_tile amx_bf16\n\nprocessor\t: 1\n")
    assert P.cpu_bf16_flags(info) == {"avx512_bf16", "amx_bf16"}
    info.write_text("flags\t\t: fpu sse avx2\n")
    assert P.cpu_bf16_flags(info) == set()
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    assert P.cpu_bf16_flags(tmp_path / "none") == {"avx512_bf16"}  # no /proc/cpuinfo: torch's checks

    assert P.native_bf16(cpu, {"amx_bf16", "avx512_bf16"}) == (True, "CPU has AMX-BF16 and AVX512-BF16")
    assert P.native_bf16(cpu, set()) == (False, "CPU lacks native bf16")
    assert P.auto_choice(False, "CPU lacks native bf16") == (False, "precision auto: fp32 (CPU lacks native bf16)")
    assert P.auto_choice(True, "CPU has AMX-BF16", (1.8, 1.0)) == \
        (True, "precision auto: bf16 (CPU has AMX-BF16; 1.8x faster on a test block)")
    bf16, line = P.auto_choice(True, "CPU has AVX512-BF16", (1.0, 0.95))  # within the noise: not faster
    assert not bf16 and line.startswith("precision auto: fp32 (CPU has AVX512-BF16, but bf16 was not faster")

    measured = []
    monkeypatch.setattr(P, "time_block", lambda device: measured.append(device) or (2.0, 1.0))
    monkeypatch.setattr(P, "cpu_bf16_flags", lambda: {"amx_bf16"})
    assert P.resolve("auto", cpu) == (True, "precision auto: bf16 (CPU has AMX-BF16; 2.0x faster on a test block)")
    assert P.resolve("auto", cpu, kept="fp32") == (False, "precision auto: fp32 (kept: the run trained in it so far)")
    assert P.resolve("fp32", cpu) == (False, "") and len(measured) == 1  # measured only when auto decides
    monkeypatch.setattr(P, "cpu_bf16_flags", lambda: set())
    assert P.resolve("auto", cpu)[0] is False and len(measured) == 1  # no native bf16: nothing to measure
    assert "emulates it" in P.resolve("bf16", cpu)[1]


def test_the_test_block_times_both_precisions_quickly():
    fp32_s, bf16_s = P.time_block(torch.device("cpu"))
    assert 0 < fp32_s < 1 and 0 < bf16_s < 5


@pytest.fixture
def recipe(tmp_path, tiny_data):
    return write_recipe(tmp_path / "rvae.toml", "rvae", 2, data=str(tiny_data), preview_every=0)


def _stopped_while_encoding(how, recipe, run, monkeypatch, capsys) -> str:
    """Train ``recipe`` into ``run``, stopped (``how``) as the second part of the latent cache is written; its
    stderr."""
    if how == "ctrl-c":
        monkeypatch.setattr(latents, "CHUNK", PART)
        interrupted_at(monkeypatch, latents, "_save", 2)
        code, _, err = in_process(capsys, "train", "rvae", "--recipe", recipe, "--out", run, "--no-log")
        assert code == 130, err
        return err
    script = ("import os, signal, sys\nimport torch\nfrom cmtool.train import latents\n"  # kill -9 amid a part's file
              "torch.set_num_threads(1)\n"  # as this process: the parts before the kill are the ones it would encode
              f"latents.CHUNK = {PART}\nreal, calls = latents._save, []\n"
              "def save(path, **arrays):\n    calls.append(path)\n    if len(calls) == 2:\n"
              "        with latents.atomic_open(path, 'wb') as f:\n            f.write(b'PK half a part')\n"
              "            f.flush()\n            os.kill(os.getpid(), signal.SIGKILL)\n    real(path, **arrays)\n"
              "latents._save = save\nfrom cmtool.cli import main\nmain(sys.argv[1:])\n")
    killed = subprocess.run([sys.executable, "-c", script, "train", "rvae", "--recipe", str(recipe), "--out",
                             str(run), "--no-log"], capture_output=True, text=True, cwd=REPO, timeout=600, check=False)
    assert killed.returncode == -9, killed.stderr
    return killed.stderr


@pytest.mark.parametrize("how", ["ctrl-c", "kill -9"])
def test_a_stop_while_encoding_latents_keeps_the_last_step(how, recipe, tmp_path, monkeypatch, capsys):
    """The final checkpoint is written before the latent cache: a stop there keeps step 2/2, `cmtool info` says how
    far the encoding got, and the same command again encodes the rest (as an unstopped encoding would) without
    training."""
    run = tmp_path / "run"
    err = _stopped_while_encoding(how, recipe, run, monkeypatch, capsys)
    chosen = next(line for line in err.splitlines() if line.startswith("precision auto: "))  # says what and why
    final = ckpt.step_dir(run, 2)
    config = ckpt.load_config(run)
    assert ckpt.resolve(run) == final and config["step"] == config["steps"] == 2 and not config["complete"]
    assert chosen.startswith(f"precision auto: {config['training']['precision']} (")
    trained = {name: (final / name).read_bytes() for name in (ckpt.WEIGHTS, ckpt.STATE, ckpt.STATE_META)}
    code, out, _ = in_process(capsys, "info", run)
    assert code == 0 and "rvae (trained, encoding latents 8/32, step 2/2)" in out, out

    monkeypatch.undo()
    monkeypatch.setattr(latents, "CHUNK", PART)
    code, out, err = in_process(capsys, "train", "rvae", "--recipe", recipe, "--out", run, "--no-log")
    assert code == 0, err
    assert f"{run}: trained to step 2 before (no training now); finishing the rvae stage" in err
    assert "encode train: going on from 8 of 24 scenes encoded before" in err
    assert "train rvae" not in err and "precision auto" not in err  # no step trained
    assert {name: (final / name).read_bytes() for name in trained} == trained
    config = ckpt.load_config(run)
    assert config["complete"] and config["latent_scale"] > 0 and "reconstruction" in config
    assert not list(run.rglob(".*")), "parts or temporary files left behind"

    model, _ = ckpt.load_model(run)
    reference = tmp_path / "reference"
    latents.write_latents(model, config["data"], reference, "cpu", ckpt.weights_digest(final), progress=False)
    for split in ("train", "test"):
        with np.load(run / "latents" / f"{split}.npz") as a, np.load(reference / f"{split}.npz") as b:
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files), split
    code, out, _ = in_process(capsys, "info", run)
    assert "rvae (complete, step 2/2)" in out
    code, _, err = in_process(capsys, "train", "rvae", "--recipe", recipe, "--out", run, "--no-log")
    assert code == 1 and "pass --resume" in err  # a complete run is not trained again by accident


def test_a_run_trained_further_encodes_its_latents_again(recipe, tiny_data, tmp_path, monkeypatch, capsys):
    """Latent files and their parts record the weights that encoded them: a run trained on after a stop while
    encoding encodes everything anew, none of the parts of its earlier weights kept."""
    run = tmp_path / "run"
    _stopped_while_encoding("ctrl-c", recipe, run, monkeypatch, capsys)
    monkeypatch.undo()
    monkeypatch.setattr(latents, "CHUNK", PART)
    longer = write_recipe(tmp_path / "longer.toml", "rvae", 3, data=str(tiny_data), preview_every=0)
    code, _, err = in_process(capsys, "train", "rvae", "--recipe", longer, "--out", run, "--no-log", "--resume")
    assert code == 0, err
    assert "going on from" not in err and "train rvae  3/3 steps" in err
    digest = ckpt.weights_digest(ckpt.resolve(run))
    assert all(latents.weights_of(run / "latents" / f"{s}.npz") == digest for s in ("train", "test"))
