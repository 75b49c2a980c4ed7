"""What the RVAE keeps of a scene: lane accuracy and driving side of its reconstructions.

A reconstruction is the scene's HD raster encoded (posterior mean) and decoded again. The diffusion
models generate latents that this decoder draws, so their maps cannot keep the driving side better
than the decoder does with the encoder's own latents: :func:`reconstruction_report` measures that
ceiling next to the ground truth's, per split and city (``cmtool ablate rvae``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from cmtool.data.cache import SceneDataset, load_dataset, load_manifest
from cmtool.data.jsonio import write_json, write_text_atomic
from cmtool.eval.geometric import driving_side, oncoming_side
from cmtool.eval.lanes import lane_scores
from cmtool.eval.metrics import drives_on, markdown_table, weighted_mean
from cmtool.model.rvae import RVAE, decoded_elements
from cmtool.progress import Progress
from cmtool.train.data import SceneRasters

BATCH = 64
TOL_M = 1.0  # lane F1 tolerance


@torch.no_grad()
def reconstruct(encoder: RVAE, decoder: RVAE, scenes: SceneDataset, idx: np.ndarray, device) -> list[dict]:
    """Decoded elements (``decoded_elements``) of scenes ``idx``, encoded by ``encoder``, decoded by
    ``decoder`` (the same RVAE, or a decoder trained on its latents)."""
    items = SceneRasters(scenes)
    out = []
    for chunk in np.array_split(idx, max(1, len(idx) // BATCH)):
        raster = torch.stack([items[int(i)]["raster"] for i in chunk]).to(device)
        mean, _ = encoder.encode(raster)
        out += decoded_elements(decoder.decode(mean))
    return out


def spread(count: int, n: int) -> np.ndarray:
    """``min(n, count)`` indices evenly spread over ``range(count)``."""
    return np.linspace(0, count - 1, min(n, count)).round().astype(int)


def reconstruction_scores(rvae: RVAE, data_dir, split: str, device, n: int, tol: float = TOL_M) -> dict:
    """Mean lane precision / recall / F1 at ``tol`` metres of ``rvae``'s reconstructions of ``n``
    scenes spread over ``split``."""
    scenes = load_dataset(data_dir, split)
    idx = spread(len(scenes), n)
    recon = reconstruct(rvae, rvae, scenes, idx, device)
    scores = [lane_scores(list(el["lines"]), list(_truth(scenes, i)), tol=tol) for i, el in zip(idx, recon)]
    out = {k: float(np.mean([s[k] for s in scores])) for k in ("precision", "recall", "f1")}
    return {**out, "tol_m": tol, "split": split, "scenes": len(scores)}


def reconstruction_report(encoder: RVAE, decoder: RVAE, data_dir, device, n: int, out: Path,
                          progress: bool = True, tol: float = TOL_M) -> list[dict]:
    """Per split and city, ``n`` scenes spread over the city's: lane F1 at ``tol`` metres of the
    reconstructions, and the left-hand share (along two-way SD roads; by oncoming lanes) of the
    ground truth and of the reconstructions. Writes ``ablate_rvae.json`` and ``ablate_rvae.md`` to ``out``."""
    rows = []
    parts = []
    for split in load_manifest(data_dir)["splits"]:
        scenes = load_dataset(data_dir, split)
        for city in sorted(set(scenes.arrays["city"].tolist())):
            parts.append((split, scenes, city))
    with Progress(len(parts), "ablate rvae", "cities", enabled=progress) as bar:
        for split, scenes, city in parts:
            members = np.flatnonzero(scenes.arrays["city"] == city)
            idx = members[spread(len(members), n)]
            recon = [el["lines"] for el in reconstruct(encoder, decoder, scenes, idx, device)]
            truth = [_truth(scenes, i) for i in idx]
            sds = [scenes.arrays["sd"][i] for i in idx]
            f1 = [lane_scores(list(r), list(t), tol=tol)["f1"] for r, t in zip(recon, truth)]
            rows.append({"split": split, "city": city, "drives_on": drives_on(city), "scenes": len(idx),
                         "f1": float(np.mean(f1)),
                         "left_hand_truth": _left(truth, sds), "left_hand_recon": _left(recon, sds),
                         "left_hand_oncoming_truth": _left(truth), "left_hand_oncoming_recon": _left(recon)})
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ablate_rvae.json", {"scenes_per_city": n, "tol_m": tol, "rows": rows})
    write_text_atomic(out / "ablate_rvae.md", markdown_table(rows, list(rows[0]) if rows else []))
    return rows


def _truth(scenes: SceneDataset, i: int) -> np.ndarray:
    return scenes.arrays["lines"][i][scenes.arrays["line_mask"][i]]


def _left(lanes: list, sds: list | None = None) -> float | None:
    """Left-hand share over scenes, weighted by judged points: along two-way SD roads (with ``sds``)
    or by the side of oncoming lanes; None when nothing could be judged."""
    judged = [driving_side(l, sd, "left") for l, sd in zip(lanes, sds)] if sds is not None \
        else [oncoming_side(l, "left") for l in lanes]
    return weighted_mean([s for s, _ in judged], [n for _, n in judged])
