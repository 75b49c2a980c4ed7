"""``cmtool bench metrics``: how long each family of metrics takes on a set of generated maps.

The set is an evaluation's cached maps (``cmtool eval --out DIR`` writes ``DIR/cache``) paired with
the scenes they were generated for, optionally repeated (``tile``) to reach the paper's test-set size
(3,904 scenes: 512 x 8 = 4,096). Every repeat runs :func:`cmtool.metrics.suite.evaluate` whole; the
report gives each family's minimum and median time over the repeats, and the whole call's.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import read_json
from cmtool.data.cache import load_dataset
from cmtool.eval.evaluation import METHODS, read_cache
from cmtool.metrics.features import FeatureExtractor, lanes_image, sd_image
from cmtool.metrics.suite import evaluate


def eval_set(eval_dir: Path, method: str = "controlmap", tile: int = 1):
    """The cached maps of ``method`` in an eval folder, their ground truth and SD controls, ``tile`` times."""
    cache = Path(eval_dir) / "cache"
    if method not in METHODS:
        raise CmtoolError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    if not (cache / "settings.json").is_file():
        raise CmtoolError(f"{eval_dir}: no eval cache here (expected {cache / 'settings.json'}; run cmtool eval)")
    settings = read_json(cache / "settings.json")
    generated = read_cache(cache / f"{method}.jsonl")
    if not generated:
        raise CmtoolError(f"{cache / f'{method}.jsonl'}: no cached maps")
    data = load_dataset(settings["data"], settings["split"])
    scenes = [data.scene(i) for i in range(min(len(generated), len(data)))]
    generated = generated[:len(scenes)]
    reference = [s.to_lanegraph() for s in scenes]
    controls = np.stack([s.sd for s in scenes])
    return generated * tile, reference * tile, np.concatenate([controls] * tile)


def bench_metrics(generated, reference, controls, extractor: FeatureExtractor | None, repeats: int = 3,
                  workers: int = 1) -> dict:
    """Per metric family (and for the whole call) the seconds of each repeat; with an ``extractor`` also the
    ResNet-50 passes alone over the same rasters (generated, reference and SD), interleaved with the whole calls.
    ``workers``: processes for the per-scene families (their seconds are summed over the processes)."""
    families: dict[str, list[float]] = {}
    total, passes = [], []
    images = None
    if extractor is not None:
        images = np.concatenate([np.stack([lanes_image(g.lanes, g.frame_m) for g in generated + reference]),
                                 np.stack([sd_image(sd) for sd in controls])])
    for _ in range(repeats):
        began = time.perf_counter()
        result = evaluate(generated, reference, controls, extractor, features=extractor is not None, workers=workers)
        total.append(time.perf_counter() - began)
        for name, seconds in result["seconds"].items():
            families.setdefault(name, []).append(seconds)
        if images is not None:
            began = time.perf_counter()
            extractor(images)
            passes.append(time.perf_counter() - began)
    report = {"scenes": len(generated), "repeats": repeats, "workers": workers, "families": families, "total": total}
    if extractor is not None:
        report |= {"resnet_passes": passes, "images": len(images), "precision": extractor.precision}
    return report


def report_table(report: dict) -> str:
    """The bench as a markdown table: minimum and median seconds per family, then the whole call (and the
    ResNet-50 passes alone, with the whole call's time as a multiple of theirs)."""
    rows = ["| metric family | min s | median s |", "|---|---|---|"]
    named = [*report["families"].items(), ("all of `evaluate`", report["total"])]
    if "resnet_passes" in report:
        named.append((f"ResNet-50 passes alone ({report['images']:,} images, {report['precision']})",
                      report["resnet_passes"]))
    for name, times in named:
        rows.append(f"| {name} | {min(times):.2f} | {statistics.median(times):.2f} |")
    head = f"{report['scenes']} scene pairs, {report['repeats']} repeats"
    if report["workers"] > 1:
        head += f", {report['workers']} processes for the per-scene families (their times summed over them)"
    if "resnet_passes" in report:
        head += (f"; all of `evaluate` is {min(report['total']) / min(report['resnet_passes']):.2f}x the ResNet-50 "
                 "passes alone (minimum over minimum)")
    return head + "\n\n" + "\n".join(rows)
