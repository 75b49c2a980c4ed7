"""What the RVAE keeps of a scene: lane accuracy, successors, validity and driving side of its
reconstructions.

A reconstruction is the scene's HD raster encoded (posterior mean) and decoded again, as a lane
graph: the graph decoder's predicted successors (linked lanes joined at shared points), or the
successors inferred from endpoint proximity. The diffusion models generate latents that this decoder
draws, so their maps cannot do better than the decoder does with the encoder's own latents:
:func:`reconstruction_report` measures that ceiling, per split and city (``cmtool ablate rvae``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from cmtool.core.errors import CmtoolError
from cmtool.core.jsonio import write_json, write_text_atomic
from cmtool.core.progress import Progress
from cmtool.data.cache import SceneDataset, load_dataset, load_manifest
from cmtool.maps.hdmap import drives_on
from cmtool.maps.lanegraph import LaneGraph, infer_successors, join_successors
from cmtool.metrics.geometric import driving_side, oncoming_side
from cmtool.metrics.lanes import lane_scores_of_scenes, pair_distances, scores_at
from cmtool.metrics.suite import markdown_table, weighted_mean
from cmtool.metrics.validity import check
from cmtool.model.rvae import RVAE, decoded_elements
from cmtool.train.data import scene_raster

BATCH = 64
TOL_M = 1.0  # lane F1 tolerance
FINE_M = 0.5  # the finer tolerance reported beside it


@torch.no_grad()
def reconstruct(encoder: RVAE, decoder: RVAE, scenes: SceneDataset, idx: np.ndarray, device) -> list[dict]:
    """Decoded elements (``decoded_elements``) of scenes ``idx``, encoded by ``encoder``, decoded by
    ``decoder`` (the same RVAE, or a decoder trained on its latents)."""
    out = []
    for chunk in np.array_split(idx, max(1, len(idx) // BATCH)):
        raster = torch.stack([scene_raster(scenes, int(i)) for i in chunk]).to(device)
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
    scores = lane_scores_of_scenes([list(el["lines"]) for el in recon], [list(_truth(scenes, i)) for i in idx], tol=tol)
    out = {k: float(np.mean([s[k] for s in scores])) for k in ("precision", "recall", "f1")}
    return {**out, "tol_m": tol, "split": split, "scenes": len(scores)}


def reconstruction_report(encoder: RVAE, decoder: RVAE, data_dir, device, n: int, out: Path,
                          progress: bool = True, tol: float = TOL_M, splits: list[str] | None = None) -> list[dict]:
    """Per split (``splits``, default every one) and city, ``n`` scenes spread over the city's: lane F1 at
    ``tol`` metres and at 0.5 m of the reconstructions, successor precision, recall and F1
    (:func:`successor_counts`, pooled over the scenes), the mean validity score (``cmtool validate``),
    and the left-hand share (along two-way SD roads; by oncoming lanes) of the ground truth and of the
    reconstructions. Writes ``ablate_rvae.json`` and ``ablate_rvae.md`` to ``out``."""
    rows = []
    parts = []
    available = list(load_manifest(data_dir)["splits"])
    unknown = sorted(set(splits or []) - set(available))
    if unknown:
        raise CmtoolError(f"{data_dir}: no split {', '.join(unknown)} (it has {', '.join(available)})")
    for split in splits or available:
        scenes = load_dataset(data_dir, split)
        for city in sorted(set(scenes.arrays["city"].tolist())):
            parts.append((split, scenes, city))
    with Progress(len(parts), "ablate rvae", "cities", enabled=progress) as bar:
        for split, scenes, city in parts:
            members = np.flatnonzero(scenes.arrays["city"] == city)
            idx = members[spread(len(members), n)]
            graphs = [lane_graph(el, scenes.frame_m) for el in reconstruct(encoder, decoder, scenes, idx, device)]
            recon = [np.array(g.lanes).reshape(-1, scenes.arrays["lines"].shape[2], 2) for g in graphs]
            truth = [_truth(scenes, i) for i in idx]
            sds = [scenes.arrays["sd"][i] for i in idx]
            distances = [pair_distances(list(r), list(t)) for r, t in zip(recon, truth)]
            f1 = [scores_at(d, tol)["f1"] for d in distances]
            fine = [scores_at(d, FINE_M)["f1"] for d in distances]
            links = np.sum([successor_counts(g, t, _edges(scenes, i), tol)
                            for g, t, i in zip(graphs, truth, idx)], axis=0)
            rows.append({"split": split, "city": city, "drives_on": drives_on(city), "scenes": len(idx),
                         "f1": float(np.mean(f1)), f"f1_{FINE_M:g}m": float(np.mean(fine)),
                         "succ_precision": _ratio(links[0], links[1]), "succ_recall": _ratio(links[0], links[2]),
                         "succ_f1": _ratio(2 * links[0], links[1] + links[2]),
                         "validity": float(np.mean([check(g, routes=False).score for g in graphs])),
                         "left_hand_truth": _left(truth, sds), "left_hand_recon": _left(recon, sds),
                         "left_hand_oncoming_truth": _left(truth), "left_hand_oncoming_recon": _left(recon)})
            bar.update()
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ablate_rvae.json", {"scenes_per_city": n, "tol_m": tol, "rows": rows})
    write_text_atomic(out / "ablate_rvae.md", markdown_table(rows, list(rows[0]) if rows else []))
    return rows


def lane_graph(elements: dict, frame_m: float) -> LaneGraph:
    """Decoded elements as a lane graph: predicted successors with linked lanes joined, or successors
    inferred from endpoint proximity."""
    lanes = [np.asarray(l, np.float64) for l in elements["lines"]]
    if "successors" in elements:
        succ = [(int(i), int(j)) for i, j in elements["successors"]]
        lanes = join_successors(lanes, succ)
    else:
        succ = infer_successors(lanes)
    return LaneGraph(lanes=lanes, successors=succ, frame_m=frame_m)


def successor_counts(graph: LaneGraph, truth: np.ndarray, truth_edges: np.ndarray,
                     tol: float) -> tuple[int, int, int]:
    """(correct, predicted, true) successor links: lanes are matched one to one (Hungarian on the mean
    distance of their ordered points, a match within ``tol``), and a predicted link i -> j is correct
    when i and j match the two lanes of a true link, in its order."""
    pred = np.array(graph.lanes).reshape(-1, truth.shape[1], 2)
    if len(pred) and len(truth):
        cost = np.linalg.norm(pred[:, None] - truth[None], axis=-1).mean(-1)
        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] <= tol
        to_truth = dict(zip(rows[keep].tolist(), cols[keep].tolist()))
    else:
        to_truth = {}
    true = {(int(a), int(b)) for a, b in truth_edges}
    correct = sum((to_truth.get(i), to_truth.get(j)) in true for i, j in graph.successors)
    return correct, len(graph.successors), len(true)


def _ratio(num: float, den: float) -> float | None:
    return float(num / den) if den else None


def _edges(scenes: SceneDataset, i: int) -> np.ndarray:
    a = scenes.arrays
    return a["edges"][a["edge_offsets"][i]:a["edge_offsets"][i + 1]]


def _truth(scenes: SceneDataset, i: int) -> np.ndarray:
    return scenes.arrays["lines"][i][scenes.arrays["line_mask"][i]]


def _left(lanes: list, sds: list | None = None) -> float | None:
    """Left-hand share over scenes, weighted by judged points: along two-way SD roads (with ``sds``)
    or by the side of oncoming lanes; None when nothing could be judged."""
    judged = [driving_side(l, sd, "left") for l, sd in zip(lanes, sds)] if sds is not None \
        else [oncoming_side(l, "left") for l in lanes]
    return weighted_mean([s for s, _ in judged], [n for _, n in judged])
