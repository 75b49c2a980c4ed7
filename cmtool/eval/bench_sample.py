"""``cmtool bench sample``: what per-step logging costs, what batching buys, what each sampler's steps buy, and
whole runs' maps per second.

:func:`bench_sample` times the generation of maps from one SD raster (the default is a procedural Boston-style
crossing) with a loaded checkpoint, after one warm-up run: at batch 1 without logging and with
full per-step logging to a temporary ``.rrd`` (the recording closed and on disk), and at a large
batch without logging. The three settings take turns, ``repeats`` rounds; each figure is the median of
its runs.

:func:`sampler_table` makes the maps of a dataset's first scenes with every sampler at several step counts (the same
initial noise per scene, as ``cmtool eval`` draws it) and scores them against the ground truth: the quality-speed
table of the samplers.

:func:`end_to_end` times whole ``cmtool sample`` runs in this process (the model loaded once): frames in, files out,
for 1..N worker processes and with the recording on.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from cmtool.diffusion.settings import SAMPLERS, TABLE_STEPS, SamplerSettings
from cmtool.eval.evaluation import lane_count_agreement
from cmtool.metrics.decisions import decision_scores, truth_frames
from cmtool.metrics.features import FeatureExtractor
from cmtool.metrics.suite import evaluate, shared_features
from cmtool.sample.generator import MapGenerator
from cmtool.sample.inputs import ControlInput
from cmtool.sample.job import Job, SampleSettings
from cmtool.sample.roads import frame_roads
from cmtool.sample.run import generate_maps, log_run_header, plan, run_sample
from cmtool.viz.recording import close_recording, open_recording

LOG_LIMIT = 1.10  # full logging may cost at most 10% over --no-log (tiny model, batch 1)


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
            rec = open_recording("sample")
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


def end_to_end(gen: MapGenerator, inputs, settings: SampleSettings, workers: list[int], repeats: int = 2,
               report=print) -> list[dict]:
    """Maps per second of whole runs as ``cmtool sample`` makes them, the model loaded once: ``inputs()`` read
    (the map, each frame's SD raster and ground truth), the jobs planned, the maps generated, checked and their
    files written to a temporary folder; without a recording for each count of ``workers``, and with one
    (``sample.rrd``: every step of every map). The settings take turns, ``repeats`` rounds after a warm-up run; one
    row per setting with the min and median seconds."""
    setups = {f"--no-log, --workers {n}": (n, False) for n in workers}
    setups["recording on (sample.rrd)"] = (workers[0], True)

    def run(n: int, log: bool) -> tuple[float, int]:
        with tempfile.TemporaryDirectory() as tmp:
            began = time.perf_counter()
            jobs = plan(gen, inputs(), settings)
            out = Path(tmp) / "out"
            run_sample(gen, jobs, settings, out, out / "sample.rrd" if log else None, progress=False, workers=n)
            return time.perf_counter() - began, len(jobs)

    run(workers[0], False)  # warm-up
    times: dict[str, list[float]] = {key: [] for key in setups}
    maps = 0
    for _ in range(repeats):
        for key, (n, log) in setups.items():
            seconds, maps = run(n, log)
            times[key].append(seconds)
    rows = []
    base = statistics.median(times[next(iter(setups))])
    for key, runs in times.items():
        median = statistics.median(runs)
        rows.append({"setting": key, "maps": maps, "min_s": min(runs), "median_s": median,
                     "maps_per_s": maps / median, "against_first": base / median})
        report(f"| {key} | {maps} | {min(runs):.2f} | {median:.2f} | {maps / median:.1f} | {base / median:.2f} |")
    return rows


E2E_HEAD = ("| setting | maps | min s | median s | maps per second (median) | speed against the first row |\n"
            "|---|---|---|---|---|---|")


def sampler_table(gen: MapGenerator, scenes, cfg: float = 1.0, samplers=SAMPLERS, steps=TABLE_STEPS, batch: int = 64,
                  seed: int = 0, extractor: FeatureExtractor | None = None, report=print, final=None,
                  sd_maps=None, baselines: dict | None = None) -> list[dict]:
    """One row per sampler and step count: seconds per map of generating the maps of ``scenes`` (denoising,
    decoding and lane graphs, ``batch`` maps at a time, in turn with nothing else) and their scores against the
    scenes' ground truth (validity, lane F1 and precision at 1 m, Chamfer distance, legal one-way share, SD road
    covered, and with ``extractor`` GT Recall and the improved precision and recall of the maps' features against
    the ground truth's). ``final``: scores the maps it makes of the model's (the maps as ``cmtool sample`` writes
    them), not timed. ``sd_maps``: the scenes' SD maps (:func:`cmtool.data.cache.scene_sd_maps`): the decisions on
    the SD roads too (:func:`decisions_row`), and of the maps in ``baselines`` (method -> the scenes' maps: the rules'
    and netconvert's layouts), a line each before the table. ``report`` gets each row as a line of the table as soon
    as it is done."""
    labels = [gen.known_label(s.city) for s in scenes]
    sds = np.stack([s.sd for s in scenes])
    reference = [s.to_lanegraph() for s in scenes]
    shared = {}
    if extractor is not None:  # the ground truth's and the controls' features serve every row
        shared = shared_features(reference, sds, extractor)
    roads = frames = None
    if sd_maps is not None:
        roads = [frame_roads(m, s.pose.as_array(), s.frame_m) for s, m in zip(scenes, sd_maps)]
        frames = truth_frames(reference, roads)
        for method, maps in (baselines or {}).items():
            d = decisions_row(maps, scenes, sd_maps, frames, roads)
            report(f"{method} (the SD map's layout): " + ", ".join(f"{DECISION_NAMES[k]} {d[k]:.3f}" for k in DECISIONS))
    gen.generate_all(sds[:1], labels[:1], SamplerSettings(cfg=cfg, steps=1, sampler=samplers[0], batch=1))  # warm-up
    head = TABLE_HEAD + (FEATURE_HEAD if extractor is not None else "") + (DECISION_HEAD if roads is not None else "")
    report(head + "\n" + "|---" * (head.count("|") - 1) + "|")
    rows = []
    for sampler in samplers:
        for n in steps:
            settings = SamplerSettings(cfg=cfg, steps=n, sampler=sampler, seed=seed, batch=batch)
            began = time.perf_counter()
            maps = gen.generate_all(sds, labels, settings)
            seconds = (time.perf_counter() - began) / len(maps)
            if final is not None:
                maps = final(maps)
            scores = evaluate(maps, reference, sds, extractor, features=extractor is not None, **shared)
            g = scores["geometry"]
            row = {"sampler": sampler, "steps": n, "seconds_per_map": seconds,
                   **{k: g[k]["mean"] for k in QUALITY}}
            if extractor is not None:
                fidelity = scores["precision_recall"]
                row |= {"gt_recall": scores["gt_recall"]["recall"], "precision": fidelity["precision"],
                        "recall": fidelity["recall"]}
            if roads is not None:
                row |= decisions_row(maps, scenes, sd_maps, frames, roads)
            rows.append(row)
            report(table_row(row))
    return rows


QUALITY = ("validity", "lane_f1", "lane_precision", "chamfer_m", "legal_oneway", "sd_coverage")
TABLE_HEAD = ("| sampler | steps | s per map | maps per second | validity | lane F1 @1 m | lane precision @1 m | "
              "Chamfer m | legal one-way | SD covered |")
FEATURE_HEAD = " GT Recall | precision | recall |"
DECISIONS = ("lane_count_equal", "movement_precision", "movement_recall", "movement_f1", "unexplained_share")
DECISION_NAMES = {"lane_count_equal": "lanes per road direction as the truth's",
                  "movement_precision": "movement precision", "movement_recall": "movement recall",
                  "movement_f1": "movement F1", "unexplained_share": "lane length no SD road explains"}
DECISION_HEAD = "".join(f" {DECISION_NAMES[k]} |" for k in DECISIONS)


def decisions_row(maps, scenes, sd_maps, frames, roads) -> dict:
    """The decisions of ``maps`` on the scenes' SD roads: the share of SD road directions with ground-truth lanes
    where they draw as many lanes as the truth (:func:`cmtool.eval.evaluation.lane_count_agreement`), junction
    movement precision, recall and F1 and the unexplained share of the lane length
    (:func:`cmtool.metrics.decisions.decision_scores` against ``frames``, :func:`truth_frames`)."""
    counts = lane_count_agreement(scenes, {"maps": maps}, sd_maps).get("maps")
    return {"lane_count_equal": counts["equal"] if counts else float("nan"),
            **{k: v for k, v in decision_scores(maps, frames, roads).items() if k in DECISIONS}}


def table_row(row: dict) -> str:
    """A markdown row of :func:`sampler_table`."""
    cells = [row["sampler"], str(row["steps"]), f"{row['seconds_per_map']:.4f}", f"{1 / row['seconds_per_map']:.1f}",
             *(f"{row[k]:.3f}" for k in QUALITY)]
    if "gt_recall" in row:
        cells += [f"{row[k]:.3f}" for k in ("gt_recall", "precision", "recall")]
    if "movement_f1" in row:
        cells += [f"{row[k]:.3f}" for k in DECISIONS]
    return "| " + " | ".join(cells) + " |"
