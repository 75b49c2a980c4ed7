"""``cmtool bench sample``: what per-step logging costs, and what batching buys.

Times the generation of maps from one SD raster (the default is a procedural Boston-style
crossing) with a loaded checkpoint, after one warm-up run: at batch 1 without logging and with
full per-step logging to a temporary ``.rrd`` (the recording closed and on disk), and at a large
batch without logging. The three settings take turns, ``repeats`` rounds; each figure is the median of
its runs.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from cmtool.sample.generator import MapGenerator
from cmtool.sample.inputs import ControlInput
from cmtool.sample.run import Job, SampleSettings, generate_maps, log_run_header, sampling_recording
from cmtool.viz.recording import close_recording

LOG_LIMIT = 1.25  # issue #4: full logging may cost at most 25% over --no-log (tiny model, batch 1)


def default_sd() -> np.ndarray:
    """The SD raster of a crossing in a procedural Boston-style city (deterministic)."""
    from cmtool.data.sd_derive import derive_sd
    from cmtool.data.sd_raster import rasterize_sd
    from cmtool.data.synth import generate_city

    hd = generate_city("BOS", seed=7, extent=400.0)
    return rasterize_sd(derive_sd(hd), 200.0, 200.0, np.pi / 2)


def _timed(gen: MapGenerator, jobs: list[Job], settings: SampleSettings, log: bool) -> float:
    began = time.perf_counter()
    if log:
        with tempfile.TemporaryDirectory() as tmp:
            rrd = Path(tmp) / "bench.rrd"
            rec = sampling_recording(rrd, None)
            log_run_header(rec, gen, jobs, settings, "cmtool bench sample")
            generate_maps(gen, jobs, settings, rec, progress=False)
            close_recording(rec, rrd)
            seconds = time.perf_counter() - began
    else:
        generate_maps(gen, jobs, settings, None, progress=False)
        seconds = time.perf_counter() - began
    return seconds


def bench_sample(gen: MapGenerator, sd: np.ndarray, settings: SampleSettings, batch: int = 64, repeats: int = 3,
                 report=print) -> dict:
    """Median seconds per map for (batch 1, no log), (batch 1, full log), (``batch``, no log)."""
    source = ControlInput("bench", sd if gen.has_control else None, "bench")
    label = gen.label(settings.city if settings.city != "auto" else "none")

    def jobs(n: int) -> list[Job]:
        made = [Job(f"bench_{i}", source, label, i) for i in range(n)]
        for i, job in enumerate(made):
            job.prefix = f"sample_{i}/" if n > 1 else ""
        return made

    setups = {key: (jobs(n), SampleSettings(**{**settings.__dict__, "batch": n}), log)
              for key, n, log in (("batch1_nolog", 1, False), ("batch1_log", 1, True),
                                  (f"batch{batch}_nolog", batch, False))}
    times: dict[str, list[float]] = {key: [] for key in setups}
    for key, (made, run, log) in setups.items():
        _timed(gen, made, run, log)  # warm-up
    for _ in range(repeats):  # the settings in turn, so that a change in the machine's load hits them alike
        for key, (made, run, log) in setups.items():
            times[key].append(_timed(gen, made, run, log) / len(made))
    results = {}
    for key, runs in times.items():
        results[key] = statistics.median(runs)
        report(f"  {key:<16} {results[key]:8.4f} s/map   (runs: {', '.join(f'{t:.4f}' for t in runs)})")
    results["log_ratio"] = results["batch1_log"] / results["batch1_nolog"]
    results["batch_speedup"] = results["batch1_nolog"] / results[f"batch{batch}_nolog"]
    return results
