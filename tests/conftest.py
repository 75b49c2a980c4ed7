"""Shared test helpers."""

import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

# A suite started in the background (`nohup pytest &` from a script) has Ctrl-C ignored, and the commands it starts
# would inherit that: the tests of what Ctrl-C does need it at its default
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def run_cli():
    """Run ``python -m cmtool ARGS`` as a user would; returns the CompletedProcess."""

    def run(*args, cwd=None):
        return subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], capture_output=True, text=True,
                              cwd=cwd or REPO, timeout=300)

    return run


def in_process(capsys, *args) -> tuple[int, str, str]:
    """Run the CLI in this process (as `cmtool ARGS`, faster than a subprocess); returns
    (exit code, stdout, stderr)."""
    from cmtool.cli import main

    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def interrupted_at(monkeypatch, module, name: str, call: int):
    """Make ``module.name`` raise KeyboardInterrupt (a Ctrl-C) at its ``call``-th call; returns the real function."""
    real, calls = getattr(module, name), []

    def stops(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, stops)
    return real


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module (`pytestmark = pytest.mark.usefixtures("one_thread")`)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def perturb(model: torch.nn.Module, scale: float = 0.05) -> None:
    """Add Gaussian noise to every parameter (a stand-in for a trained model)."""
    with torch.no_grad():
        for p in model.parameters():
            p.add_(scale * torch.randn_like(p))


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """The tiny dataset cache (recipes/data_tiny.toml: 24 train scenes, 8 BOS test scenes)."""
    from cmtool.data.cache import build_dataset
    from cmtool.train.recipe import load_recipe

    data = tmp_path_factory.mktemp("data") / "tiny"
    build_dataset(load_recipe(REPO / "recipes" / "data_tiny.toml"), data, workers=1, progress=False)
    return data


@pytest.fixture(scope="session")
def sampling_ckpt(tmp_path_factory):
    """Small untrained RVAE, DiT and ControlMap checkpoints (branch weights perturbed so the control
    changes the output), wired like a trained run: returns the ControlMap and DiT checkpoint dirs."""
    import dataclasses

    from cmtool.model import checkpoint as ckpt
    from cmtool.model.config import ControlConfig, DiTConfig, RVAEConfig, ScheduleConfig
    from cmtool.model.controlmap import ControlMap
    from cmtool.model.dit import DiT
    from cmtool.model.rvae import RVAE

    root = tmp_path_factory.mktemp("ckpt")
    torch.manual_seed(0)
    rvae_cfg = RVAEConfig(d_model=32, decoder_layers=1, heads=2, ffn=64, dropout=0.0)
    rvae = RVAE(rvae_cfg)
    with torch.no_grad():  # existence logits around 0 so the decoded maps have lanes
        for head in rvae.heads.values():
            head.logit.bias.fill_(0.5)
    ckpt.save_checkpoint(root / "rvae", {"kind": "rvae", "model": dataclasses.asdict(rvae_cfg), "latent_scale": 0.7},
                         rvae.state_dict())
    cities = ["LAV", "PIT", "SGP"]
    dit_cfg = DiTConfig(size="tiny", depth=2, hidden=32, heads=2, num_classes=len(cities)).resolved()
    dit = DiT(dit_cfg)
    perturb(dit, 0.02)
    common = {"cities": cities, "schedule": dataclasses.asdict(ScheduleConfig()), "latent_scale": 0.7,
              "rvae": str(root / "rvae"), "model": dataclasses.asdict(dit_cfg)}
    ckpt.save_checkpoint(root / "dit", {"kind": "dit", **common}, dit.state_dict())
    control_cfg = ControlConfig(num_blocks=2, widths=(8, 8, 16, 16), groups=4)
    cm = ControlMap(dit, control_cfg)
    with torch.no_grad():
        for p in cm.branch_parameters():
            p.add_(0.05 * torch.randn_like(p))
    ckpt.save_checkpoint(root / "controlmap", {"kind": "controlmap", "control": dataclasses.asdict(control_cfg),
                                               "dit": str(root / "dit"), **common}, cm.state_dict())
    return {"controlmap": root / "controlmap", "dit": root / "dit", "rvae": root / "rvae"}
