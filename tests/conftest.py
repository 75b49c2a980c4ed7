"""Shared test helpers."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def run_cli():
    """Run ``python -m cmtool ARGS`` as a user would; returns the CompletedProcess."""

    def run(*args, cwd=None):
        return subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], capture_output=True, text=True,
                              cwd=cwd or REPO, timeout=300)

    return run
