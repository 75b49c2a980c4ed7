"""Shared test helpers."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def run_cli():
    """Run ``python -m cmtool ARGS`` as a user would; returns the CompletedProcess."""

    def run(*args, cwd=None):
        return subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], capture_output=True, text=True,
                              cwd=cwd or REPO, timeout=300)

    return run


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
