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


def set_loss(decoded: dict[str, Tensor], batch: dict[str, Tensor], cfg: RVAELossConfig) -> dict[str, Tensor]:
    """Matched L1 and existence BCE per element type of one set of outputs: ``{"l1/lines", "exist/lines", ...}``."""
    parts: dict[str, Tensor] = {}
    for name in ELEMENTS:
        pred, logit = decoded[name], decoded[f"{name}_logit"]
        gt, mask = batch[name].to(pred), batch[MASK_KEYS[name]].to(pred.device)
        pairs = match(pred, logit, gt, mask, cfg)
        b = torch.cat([torch.full((len(p),), i, dtype=torch.int64) for i, (p, _) in enumerate(pairs)]).to(pred.device)
        q = torch.from_numpy(np.concatenate([p for p, _ in pairs])).to(pred.device)
        g = torch.from_numpy(np.concatenate([t for _, t in pairs])).to(pred.device)
        target = torch.zeros_like(logit)
        target[b, q] = 1.0
        parts[f"l1/{name}"] = line_l1(pred[b, q], gt[b, g], cfg.frame_m).sum() / logit.numel()
        parts[f"exist/{name}"] = F.binary_cross_entropy_with_logits(logit, target)
    return parts


def _weighted(parts: dict[str, Tensor], cfg: RVAELossConfig) -> Tensor:
    return sum((cfg.l1_weight if k.startswith("l1/") else cfg.existence_weight) * v for k, v in parts.items())


def rvae_loss(decoded: dict[str, Tensor], mean: Tensor, logvar: Tensor, batch: dict[str, Tensor],
              cfg: RVAELossConfig) -> tuple[Tensor, dict[str, float]]:
    """Total loss and its unweighted parts ``{"l1/lines", "exist/lines", ..., "kl"}`` (and ``"aux"``, the
    weighted loss of the earlier layers, when ``decoded`` holds them and ``cfg.aux_weight`` > 0) as floats.

    ``batch`` holds the targets: "lines" (B, L, P, 2) metres with "line_mask" (B, L) bool, and
    "green"/"green_mask", "red"/"red_mask" likewise.
    """
    parts = set_loss(decoded, batch, cfg)
    parts["kl"] = kl_divergence(mean, logvar)
    total = _weighted({k: v for k, v in parts.items() if k != "kl"}, cfg) + cfg.kl_weight * parts["kl"]
    if cfg.aux_weight > 0 and decoded.get("aux"):
        parts["aux"] = cfg.aux_weight * sum(_weighted(set_loss(d, batch, cfg), cfg) for d in decoded["aux"])
        total = total + parts["aux"]
    return total, {k: float(v.detach()) for k, v in parts.items()}
