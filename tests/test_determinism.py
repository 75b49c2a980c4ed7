"""One seed, one map (issue 66): `cmtool sample` with the shipped weights writes the same files byte for byte with any
number of workers and under any torch thread count the user did not choose for it (``OMP_NUM_THREADS`` unset, 1 or
3). The commands run as a user runs them, each in its own process (torch reads the thread count as it starts)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO


def _cmtool(*args, threads: str | None = None) -> None:
    """``cmtool ARGS`` in a new process, ``OMP_NUM_THREADS`` set to ``threads`` (None: unset); it must succeed."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env |= {} if threads is None else {"OMP_NUM_THREADS": threads}
    done = subprocess.run([sys.executable, "-m", "cmtool", *map(str, args)], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_a_seed_gives_one_set_of_files_whatever_the_workers_and_threads(tmp_path):
    """Batches of two maps (their checks in the denoising process's thread or in two worker processes, which halved
    torch's threads): every file the same byte for byte, also with one torch thread and with three."""
    hd, poses = tmp_path / "pit.json", tmp_path / "poses.jsonl"
    _cmtool("data", "synth", "--city", "PIT", "--seed", 2, "--extent", 300, "--out", hd)
    _cmtool("data", "poses", hd, "--n", 8, "--out", poses)
    runs = {"1 worker": (1, None), "2 workers": (2, None), "OMP_NUM_THREADS=1": (1, "1"),
            "OMP_NUM_THREADS=3": (2, "3")}
    made = {}
    for name, (workers, threads) in runs.items():
        out = tmp_path / name.replace(" ", "_").replace("=", "")
        _cmtool("sample", "--from-hd", hd, "--pose", poses, "--batch", 2, "--workers", workers, "--no-log", "--quiet",
                "--grid", tmp_path / f"{out.name}.png", "--out", out, threads=threads)
        made[name] = _files(out) | {"grid": (tmp_path / f"{out.name}.png").read_bytes()}
    assert len(made["1 worker"]) == 8 * 3 + 1
    for name in runs:
        assert made[name] == made["1 worker"], [k for k in made[name] if made[name][k] != made["1 worker"].get(k)]

