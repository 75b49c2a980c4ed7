"""``cmtool bench metrics``: how long each family of metrics takes on a set of generated maps.

The set is an evaluation's cached maps (``cmtool eval --out DIR`` writes ``DIR/cache``) paired with
the scenes they were generated for, optionally repeated (``tile``) to reach the paper's test-set size
(3,904 scenes: 512 x 8 = 4,096). Every repeat runs :func:`cmtool.eval.metrics.evaluate` whole; the
report gives each family's minimum and median time over the repeats, and the whole call's.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from cmtool.data.cache import load_dataset
from cmtool.data.jsonio import read_json
from cmtool.errors import CmtoolError
from cmtool.eval.evaluation import METHODS, read_cache
from cmtool.eval.features import FeatureExtractor
from cmtool.eval.metrics import evaluate


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


def bench_metrics(generated, reference, controls, extractor: FeatureExtractor | None, repeats: int = 3) -> dict:
    """Per metric family (and for the whole call) the seconds of each repeat."""
    families: dict[str, list[float]] = {}
    total = []
    for _ in range(repeats):
        began = time.perf_counter()
        result = evaluate(generated, reference, controls, extractor, features=extractor is not None)
        total.append(time.perf_counter() - began)
        for name, seconds in result["seconds"].items():
            families.setdefault(name, []).append(seconds)
    return {"scenes": len(generated), "repeats": repeats, "families": families, "total": total}


def report_table(report: dict) -> str:
    """The bench as a markdown table: minimum and median seconds per family, then the whole call."""
    rows = ["| metric family | min s | median s |", "|---|---|---|"]
    for name, times in [*report["families"].items(), ("all of `evaluate`", report["total"])]:
        rows.append(f"| {name} | {min(times):.2f} | {statistics.median(times):.2f} |")
    return f"{report['scenes']} scene pairs, {report['repeats']} repeats\n\n" + "\n".join(rows)
