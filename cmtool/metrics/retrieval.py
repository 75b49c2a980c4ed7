"""Feature-space metrics: improved precision / recall (Kynkäänniemi et al., 2019) and the
paper's Control Recall and Ground-Truth Recall with one-sided binomial p-values (§3.3, §4.3).
"""

from __future__ import annotations

import numpy as np
import torch


def _pairwise(a: np.ndarray, b: np.ndarray) -> torch.Tensor:
    return torch.cdist(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64))


def _radii(x: np.ndarray, k: int) -> np.ndarray:
    """Distance from each row to its k-th nearest other row."""
    d = _pairwise(x, x)
    return torch.kthvalue(d, k + 1, dim=1).values.numpy()  # the 1st is the row itself (distance 0)


def improved_precision_recall(real: np.ndarray, fake: np.ndarray, k: int = 3) -> dict[str, float]:
    """precision: share of ``fake`` features inside the union of k-NN balls of ``real``; recall:
    share of ``real`` features inside the union of k-NN balls of ``fake``."""
    if len(real) <= k or len(fake) <= k:
        raise ValueError(f"improved precision/recall with k={k} needs more than {k} samples per set")
    real_r, fake_r = _radii(real, k), _radii(fake, k)
    d = _pairwise(fake, real).numpy()  # (fake, real)
    precision = float(np.mean((d <= real_r[None, :]).any(axis=1)))
    recall = float(np.mean((d <= fake_r[:, None]).any(axis=0)))
    return {"precision": precision, "recall": recall, "k": k}


def batch_recall(generated: np.ndarray, targets: np.ndarray, batch: int = 64, k: int = 3) -> dict:
    """Share of generated maps whose own target (control or ground truth, same row) is among the ``k``
    most cosine-similar targets of its batch of ``batch`` consecutive scenes, with the p-value
    ``P(M' >= M)`` for ``M' ~ Binomial(N, k / batch)`` (chance level). An incomplete last batch is left out."""
    if generated.shape != targets.shape:
        raise ValueError(f"generated {generated.shape} and targets {targets.shape} must pair row by row")
    if not 0 < k <= batch:
        raise ValueError(f"need 0 < k <= batch, got k={k}, batch={batch}")
    n = (len(generated) // batch) * batch
    g = _unit(generated[:n]).reshape(-1, batch, generated.shape[1])
    t = _unit(targets[:n]).reshape(-1, batch, targets.shape[1])
    sim = np.einsum("bid,bjd->bij", g, t)  # (batches, generated i, target j)
    own = np.take_along_axis(sim, np.arange(batch)[None, :, None].repeat(len(sim), 0), axis=2)  # (batches, batch, 1)
    rank = (sim > own).sum(axis=2)  # targets strictly more similar than the own one
    hits = int((rank < k).sum())
    from scipy.stats import binom  # here: scipy.stats takes half a second to import

    p_value = float(binom.sf(hits - 1, n, k / batch)) if n else float("nan")
    return {"recall": hits / n if n else float("nan"), "hits": hits, "n": n, "batch": batch, "k": k,
            "p_value": p_value, "chance": k / batch}


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
