"""All metrics of a generated set of lane graphs against its reference (ground truth), and its SD
controls when known; scene i of one set is paired with scene i of the other.

- topology Fréchet distances (:mod:`cmtool.metrics.topology`);
- improved precision / recall and Ground-Truth Recall on ResNet-50 features of the map rasters,
  Control Recall against the SD rasters (:mod:`cmtool.metrics.features`, :mod:`cmtool.metrics.retrieval`);
- lane Chamfer distance, lane precision / recall / F1 at 1 m, SD adherence, driving side and legal
  one-way direction (:mod:`cmtool.metrics.geometric`), the validity score, the dangling lanes and
  crossings per map and the lane pairs routable with lane changes (:mod:`cmtool.metrics.validity`),
  averaged over scenes (scenes where a score is undefined, e.g. an empty map's Chamfer distance,
  are left out of that average and counted).
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.progress import Progress
from cmtool.maps.hdmap import drives_on
from cmtool.metrics.features import FeatureExtractor, lanes_image, sd_image
from cmtool.metrics.retrieval import batch_recall, improved_precision_recall
from cmtool.metrics.scenes import scene_scores
from cmtool.metrics.topology import frechet_distances

RECALL_BATCH, RECALL_K, PR_K = 64, 3, 3


def load_controls(path) -> np.ndarray:
    """SD controls: a folder of SD pictures (sorted by name) or a ``.npy`` stack (N, 128, 128, 3)."""
    from pathlib import Path

    from cmtool.data.sd_raster import IMAGE_SUFFIXES, read_sd_image

    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CmtoolError(f"{path}: no SD pictures in the folder")
        return np.stack([read_sd_image(f)[0] for f in files])
    if path.suffix == ".npy" and path.is_file():
        try:  # mapped, not read: the header's dtype and shape are checked before the data is loaded
            stack = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as e:
            raise CmtoolError(f"{path}: not a .npy array of SD rasters ({e})") from None
        if stack.ndim != 4 or stack.shape[1:] != (128, 128, 3) or stack.dtype != np.uint8:
            raise CmtoolError(f"{path}: expected a uint8 array of shape (N, 128, 128, 3), got {stack.dtype} "
                              f"{stack.shape}")
        return np.array(stack)
    raise CmtoolError(f"{path}: expected a folder of SD pictures or a .npy stack of SD rasters")


def evaluate(generated, reference, controls: np.ndarray | None = None, extractor: FeatureExtractor | None = None,
             features: bool = True, reference_features: np.ndarray | None = None,
             control_features: np.ndarray | None = None, progress: bool = False, workers: int = 1) -> dict:
    """Every metric of ``generated`` against ``reference`` (lists of LaneGraph) and ``controls``
    ((N, 128, 128, 3) SD rasters or None). ``features=False`` skips the ResNet-50 metrics; the
    reference's and controls' features can be passed in when several sets share them. ``progress``: a status
    line on stderr (scenes done, the family of metrics at work); ``workers``: processes for the per-scene work
    (:func:`cmtool.metrics.scenes.scene_scores`); ``seconds`` in the result: each family's time, the per-scene
    families' (topology, lanes, validity, SD) summed over the processes."""
    if len(generated) != len(reference):
        raise CmtoolError(f"{len(generated)} generated scenes but {len(reference)} reference scenes; "
                          "scene i of one set pairs with scene i of the other")
    if controls is not None and len(controls) != len(generated):
        raise CmtoolError(f"{len(controls)} SD controls for {len(generated)} scenes")
    if not generated:
        raise CmtoolError("no scenes to evaluate")
    out: dict = {"scenes": len(generated)}
    seconds: dict[str, float] = {}
    bar = Progress(len(generated), label="metrics", unit="scenes", enabled=progress)
    bar.update(0, family="topology, lanes, validity" + (", SD" if controls is not None else ""))
    sides = [drives_on(g.city or r.city) for g, r in zip(generated, reference)]
    scores = scene_scores(generated, reference, controls, sides, workers, bar.update)
    seconds.update(scores.seconds)
    out["topology_fd"] = frechet_distances(scores.statistics["generated"], scores.statistics["reference"])
    out["geometry"] = geometry(scores.rows, scores.judged)
    if features:
        extractor = extractor or FeatureExtractor()
        bar.update(0, family="features")
        with _timed(seconds, "features"):  # the rasters and their ResNet-50 passes
            gen = extractor(np.stack([lanes_image(g.lanes, g.frame_m) for g in generated]))
            ref = reference_features if reference_features is not None else \
                reference_image_features(reference, extractor)
            if controls is not None and control_features is None:
                control_features = extractor(np.stack([sd_image(sd) for sd in controls]))
        out["backbone"] = {"name": extractor.backbone, "weights": extractor.source}
        with _timed(seconds, "recall"):
            out["precision_recall"] = (improved_precision_recall(ref, gen, PR_K) if len(gen) > PR_K else
                                       {"precision": math.nan, "recall": math.nan, "k": PR_K})
            out["gt_recall"] = batch_recall(gen, ref, RECALL_BATCH, RECALL_K)
            if controls is not None:
                out["control_recall"] = batch_recall(gen, control_features, RECALL_BATCH, RECALL_K)
    bar.close()
    out["seconds"] = seconds
    return out


@contextmanager
def _timed(seconds: dict[str, float], family: str):
    """Add the time the block takes to ``seconds[family]``."""
    began = time.perf_counter()
    try:
        yield
    finally:
        seconds[family] = seconds.get(family, 0.0) + time.perf_counter() - began


def reference_image_features(graphs, extractor: FeatureExtractor) -> np.ndarray:
    """ResNet-50 features of lane graphs' rasters."""
    return extractor(np.stack([lanes_image(g.lanes, g.frame_m) for g in graphs]))


def shared_features(reference, controls: np.ndarray, extractor: FeatureExtractor) -> dict[str, np.ndarray]:
    """The ground truth's and the SD controls' features, for :func:`evaluate` calls on several sets of maps of the same
    scenes (``reference_features``, ``control_features``)."""
    return {"reference_features": reference_image_features(reference, extractor),
            "control_features": extractor(np.stack([sd_image(sd) for sd in controls]))}


def geometry(rows: dict[str, list], judged: list[float]) -> dict:
    """Per-scene geometric scores (``per_scene``, None where undefined) and their averages (with the number of
    scenes each average covers) from :func:`cmtool.metrics.scenes.scene_scores`' rows; ``legal_oneway`` is averaged
    by the lane length ``judged``."""
    out = {}
    for k, values in rows.items():
        v = np.asarray(values, float)
        ok = ~np.isnan(v)
        mean = float(v[ok].mean()) if ok.any() else math.nan
        if k == "legal_oneway" and ok.any():
            mean = float(np.average(v[ok], weights=np.asarray(judged)[ok]))
        out[k] = {"mean": mean, "scenes": int(ok.sum()),
                  "per_scene": [None if math.isnan(x) else round(float(x), 6) for x in v]}
    return out


def summary_table(results: dict[str, dict]) -> str:
    """Markdown tables with one column per evaluated method (``results``: name -> :func:`evaluate`),
    shaped like the paper's Table 1 (topology), Table 2 (realism and control fidelity), then ours."""
    topology = [(f"FD {k}" + (" (x10)" if k in ("connectivity", "convenience") else "") + " ↓",
                 lambda r, k=k: _num(r["topology_fd"][k])) for k in ("connectivity", "density", "reach", "convenience")]
    fidelity = [("precision ↑", lambda r: _num(r.get("precision_recall", {}).get("precision"))),
                ("recall ↑", lambda r: _num(r.get("precision_recall", {}).get("recall"))),
                ("Control Recall ↑ (p)", lambda r: _recall(r.get("control_recall"))),
                ("GT Recall ↑ (p)", lambda r: _recall(r.get("gt_recall")))]
    geometric = [("lane Chamfer m ↓", lambda r: _num(r["geometry"]["chamfer_m"]["mean"])),
                 ("lane precision @1 m ↑", lambda r: _num(r["geometry"]["lane_precision"]["mean"])),
                 ("lane recall @1 m ↑", lambda r: _num(r["geometry"]["lane_recall"]["mean"])),
                 ("lane F1 @1 m ↑", lambda r: _num(r["geometry"]["lane_f1"]["mean"])),
                 ("SD road within 3 m of a lane ↑", lambda r: _num(r["geometry"].get("sd_coverage", {}).get("mean"))),
                 ("lane length within 5 m of SD ↑", lambda r: _num(r["geometry"].get("lane_on_sd", {}).get("mean"))),
                 ("driving side ↑", lambda r: _num(r["geometry"].get("driving_side", {}).get("mean"))),
                 ("lane length on one-way SD roads running the legal way ↑",
                  lambda r: _num(r["geometry"].get("legal_oneway", {}).get("mean"))),
                 ("validity score ↑", lambda r: _num(r["geometry"].get("validity", {}).get("mean"))),
                 ("lanes joined to nothing, per map ↓",
                  lambda r: _num(r["geometry"].get("dangling", {}).get("mean"))),
                 ("lane crossings outside junctions, per map ↓",
                  lambda r: _num(r["geometry"].get("crossings", {}).get("mean"))),
                 ("lane pairs routable, lane changes allowed ↑",
                  lambda r: _num(r["geometry"].get("routable", {}).get("mean")))]
    names = list(results)
    scenes = ", ".join(f"{n}: {results[n]['scenes']}" for n in names)
    parts = [f"Scenes: {scenes}."]
    for title, rows in (("Topology (Fréchet distances, as the paper's Table 1)", topology),
                        ("Realism and control fidelity (as the paper's Table 2; p-values in brackets)", fidelity),
                        ("Lane geometry (ours)", geometric)):
        lines = [f"### {title}", "", "| metric | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        lines += [f"| {label} | " + " | ".join(fn(results[n]) for n in names) + " |" for label, fn in rows]
        parts.append("\n".join(lines))
    return "\n\n".join(parts)


def _num(value) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.3f}"


def _recall(r) -> str:
    if not r or math.isnan(r["recall"]):
        return "–"
    p = r["p_value"]
    return f"{r['recall']:.3f} ({'< 1e-300' if p == 0 else f'{p:.2g}'})"


def weighted_mean(values, weights) -> float | None:
    """Mean of the finite ``values`` weighted by ``weights`` (None when no weight is left)."""
    pairs = [(v, w) for v, w in zip(values, weights) if w and math.isfinite(v)]
    return float(sum(v * w for v, w in pairs) / sum(w for _, w in pairs)) if pairs else None


def markdown_table(rows: list[dict], keys: list[str]) -> str:
    """``rows`` as a markdown table of the columns ``keys`` (floats to 3 places, None as a dash)."""
    def cell(v):
        return "–" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(r.get(k)) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"
