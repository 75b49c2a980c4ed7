"""The RVAE training loss: Hungarian-matched polyline L1 + existence BCE per element type, + KL.

Per element type (lines, green-light lines, red-light lines) every ground-truth polyline is matched to
one query by minimising ``l1_weight * L1 + existence_weight * BCE(logit, 1)`` (scipy's
``linear_sum_assignment``, as SLEDGE). L1 is the mean over points of the x + y absolute error of the
ordered points (lines are directed: no reversal), in units of half the frame, so coordinates lie in
[-1, 1]. The loss then takes, as SLEDGE does, the matched L1 summed and divided by the number of
query slots, the existence BCE over all queries (matched = 1, others = 0), and the KL divergence of
the posterior to N(0, I) averaged over latent elements.

With ``aux_weight`` > 0 the matched L1 and existence terms are added again, so weighted, for the
outputs of each earlier decoder layer, each matched on its own (DETR's auxiliary decoding losses).
``direction_weight`` adds 1 - cosine between the matched lines' segment directions (MapTR's
edge-direction loss), ``successor_weight`` the BCE of the graph decoder's successor logits between
matched lines against the ground truth's successors (final layer only; pairs of a line with itself
left out). ``denoise_weight`` adds, for the graph decoder's denoising queries (started from noised
true lines, :func:`denoise_input`), the same L1, direction and successor terms against the line each
started from, every layer, no matching needed.

Weights follow SLEDGE (line reconstruction 2.0 per metre, existence 5.0, KL 0.1); SLEDGE measures L1
in metres, so its reconstruction weight is multiplied by the half frame (32 m) to keep the same
balance with the normalised L1.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from cmtool.model.config import RVAELossConfig
from cmtool.model.graph import noised_lines
from cmtool.model.rvae import ELEMENTS

MASK_KEYS = {"lines": "line_mask", "green": "green_mask", "red": "red_mask"}


def line_l1(pred: Tensor, gt: Tensor, frame_m: float) -> Tensor:
    """Mean over points of |dx| + |dy| between ordered polylines (..., P, 2), in half-frame units."""
    return (pred - gt).abs().sum(-1).mean(-1) / (frame_m / 2.0)


@torch.no_grad()
def match(pred_points: Tensor, pred_logit: Tensor, gt_points: Tensor, gt_mask: Tensor,
          cost_cfg: RVAELossConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Hungarian matching of queries (B, Q, P, 2) / (B, Q) to the valid targets of (B, G, P, 2) / (B, G).

    Returns per batch item ``(pred_idx, gt_idx)`` int64 arrays (gt_idx indexes the full G axis).
    """
    l1 = line_l1(pred_points[:, :, None], gt_points[:, None], cost_cfg.frame_m)  # (B, Q, G)
    cost = cost_cfg.l1_weight * l1 + cost_cfg.existence_weight * F.softplus(-pred_logit)[:, :, None]
    cost = cost.float().cpu().numpy()
    mask = gt_mask.bool().cpu().numpy()
    out = []
    for c, m in zip(cost, mask):
        valid = np.flatnonzero(m)
        rows, cols = linear_sum_assignment(c[:, valid])
        out.append((rows.astype(np.int64), valid[cols].astype(np.int64)))
    return out


def kl_divergence(mean: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mean, exp(logvar)) || N(0, I)), averaged over all elements."""
    return -0.5 * torch.mean(1.0 + logvar - mean.square() - logvar.exp())


def set_loss(decoded: dict[str, Tensor], batch: dict[str, Tensor],
             config: RVAELossConfig) -> tuple[dict[str, Tensor], list[tuple[np.ndarray, np.ndarray]]]:
    """Matched L1 and existence BCE (and direction) per element type of one set of outputs
    (``{"l1/lines", "exist/lines", ...}``), and the matched (query, target) pairs of the lines."""
    parts: dict[str, Tensor] = {}
    line_pairs = []
    for name in ELEMENTS:
        pred, logit = decoded[name], decoded[f"{name}_logit"]
        gt, mask = batch[name].to(pred), batch[MASK_KEYS[name]].to(pred.device)
        pairs = match(pred, logit, gt, mask, config)
        b = torch.cat([torch.full((len(p),), i, dtype=torch.int64) for i, (p, _) in enumerate(pairs)]).to(pred.device)
        q = torch.from_numpy(np.concatenate([p for p, _ in pairs])).to(pred.device)
        g = torch.from_numpy(np.concatenate([t for _, t in pairs])).to(pred.device)
        target = torch.zeros_like(logit)
        target[b, q] = 1.0
        parts[f"l1/{name}"] = line_l1(pred[b, q], gt[b, g], config.frame_m).sum() / logit.numel()
        parts[f"exist/{name}"] = F.binary_cross_entropy_with_logits(logit, target)
        if config.direction_weight > 0:
            parts[f"dir/{name}"] = direction_loss(pred[b, q], gt[b, g]).sum() / logit.numel()
        if name == "lines":
            line_pairs = pairs
    return parts, line_pairs


def direction_loss(pred: Tensor, gt: Tensor) -> Tensor:
    """Per polyline (..., P, 2): mean over segments of 1 - cosine between predicted and true directions."""
    return (1.0 - F.cosine_similarity(pred.diff(dim=-2), gt.diff(dim=-2), dim=-1, eps=1e-6)).mean(-1)


def successor_loss(logits: Tensor, succ: Tensor, pairs: list[tuple[np.ndarray, np.ndarray]]) -> Tensor:
    """BCE of successor logits (B, Q, Q) between matched queries against the targets' successors
    (B, G, G), self pairs left out."""
    terms = []
    for k, (q, g) in enumerate(pairs):
        if len(q) < 2:
            continue
        q_t, g_t = torch.from_numpy(q).to(logits.device), torch.from_numpy(g).to(logits.device)
        off = ~torch.eye(len(q), dtype=torch.bool, device=logits.device)
        target = succ[k][g_t][:, g_t].to(logits.dtype)
        terms.append(F.binary_cross_entropy_with_logits(logits[k][q_t][:, q_t][off], target[off], reduction="sum"))
    count = sum(len(q) * (len(q) - 1) for q, _ in pairs)
    return sum(terms) / max(count, 1) if terms else logits.sum() * 0.0


def denoise_input(batch: dict[str, Tensor], config: RVAELossConfig) -> Tensor | None:
    """The denoising queries' noised starts for ``batch`` (None when ``config.denoise_weight`` is 0)."""
    return noised_lines(batch["lines"], config.denoise_m) if config.denoise_weight > 0 else None


def denoise_loss(outputs: list[dict[str, Tensor]], batch: dict[str, Tensor], config: RVAELossConfig) -> Tensor:
    """Weighted L1 + direction + successor loss of the denoising queries of every layer, each against the
    true line it started from (normalised per line slot, as the matched terms)."""
    gt, valid = batch["lines"], batch["line_mask"].bool()
    pairs = valid[:, :, None] & valid[:, None, :] & ~torch.eye(valid.shape[1], dtype=torch.bool, device=valid.device)
    total = gt.new_zeros(())
    for out in outputs:
        pred = out["lines"].to(gt)
        total = total + config.l1_weight * line_l1(pred[valid], gt[valid], config.frame_m).sum() / valid.numel()
        if config.direction_weight > 0:
            total = total + config.direction_weight * direction_loss(pred[valid], gt[valid]).sum() / valid.numel()
        if config.successor_weight > 0 and pairs.any():
            total = total + config.successor_weight * F.binary_cross_entropy_with_logits(
                out["succ_logit"][pairs].float(), batch["succ"][pairs].float())
    return total


_WEIGHTS = {"l1/": "l1_weight", "exist/": "existence_weight", "dir/": "direction_weight", "succ/": "successor_weight"}


def _weighted(parts: dict[str, Tensor], config: RVAELossConfig) -> Tensor:
    return sum(getattr(config, next(w for p, w in _WEIGHTS.items() if k.startswith(p))) * v for k, v in parts.items())


def rvae_loss(decoded: dict[str, Tensor], mean: Tensor, logvar: Tensor, batch: dict[str, Tensor],
              config: RVAELossConfig) -> tuple[Tensor, dict[str, float]]:
    """Total loss and its unweighted parts ``{"l1/lines", "exist/lines", ..., "kl"}`` (and ``"aux"``, the
    weighted loss of the earlier layers, when ``decoded`` holds them and ``config.aux_weight`` > 0, and
    ``"denoise"``, the weighted loss of the denoising queries, when ``decoded`` holds them) as floats.

    ``batch`` holds the targets: "lines" (B, L, P, 2) metres with "line_mask" (B, L) bool, and
    "green"/"green_mask", "red"/"red_mask" likewise, and "succ" (B, L, L) bool (line i flows into
    line j) for the successor loss.
    """
    parts, pairs = set_loss(decoded, batch, config)
    if config.successor_weight > 0 and "succ_logit" in decoded:
        parts["succ/lines"] = successor_loss(decoded["succ_logit"], batch["succ"], pairs)
    parts["kl"] = kl_divergence(mean, logvar)
    total = _weighted({k: v for k, v in parts.items() if k != "kl"}, config) + config.kl_weight * parts["kl"]
    if config.aux_weight > 0 and decoded.get("aux"):
        parts["aux"] = config.aux_weight * sum(_weighted(set_loss(d, batch, config)[0], config) for d in decoded["aux"])
        total = total + parts["aux"]
    if config.denoise_weight > 0 and "denoise" in decoded:
        parts["denoise"] = config.denoise_weight * denoise_loss(decoded["denoise"], batch, config)
        total = total + parts["denoise"]
    return total, {k: float(v.detach()) for k, v in parts.items()}
