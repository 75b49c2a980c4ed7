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


def match_cost(pred_points: Tensor, pred_logit: Tensor, gt_points: Tensor, cost_cfg: RVAELossConfig) -> Tensor:
    """The matching cost (B, Q, G) of queries (B, Q, P, 2) / (B, Q) against targets (B, G, P, 2): ``line_l1`` of every
    pair at once, as one L1 distance between the flattened polylines (``torch.cdist``), float32."""
    points = pred_points.shape[-2]
    l1 = torch.cdist(pred_points.flatten(-2).float(), gt_points.flatten(-2).float(), p=1) / (points * cost_cfg.frame_m
                                                                                              / 2.0)
    return cost_cfg.l1_weight * l1 + cost_cfg.existence_weight * F.softplus(-pred_logit.float())[:, :, None]


Pairs = list[tuple[np.ndarray, np.ndarray]]  # per batch item: (query indices, target indices)


@torch.no_grad()
def match(sets: list[tuple[Tensor, Tensor, Tensor, Tensor]], cost_cfg: RVAELossConfig) -> list[Pairs]:
    """Hungarian matching of each ``(pred_points, pred_logit, gt_points, gt_mask)`` set, queries (B, Q, P, 2) / (B, Q)
    to the valid targets of (B, G, P, 2) / (B, G): the costs of every set are computed on their device in one batch
    each and moved to the CPU together (one transfer), then scipy assigns each batch item. Returns per set and
    batch item ``(pred_idx, gt_idx)`` int64 arrays (gt_idx indexes the full G axis)."""
    costs = [match_cost(p, logit, g, cost_cfg) for p, logit, g, _ in sets]
    masks = [m for *_, m in sets]
    host = torch.cat([c.flatten() for c in costs] + [m.flatten().float() for m in masks]).cpu().numpy()
    chunks = np.split(host, np.cumsum([c.numel() for c in costs] + [m.numel() for m in masks])[:-1])
    out = []
    for cost, flat, mask in zip(costs, chunks, chunks[len(costs):]):
        pairs = []
        for c, m in zip(flat.reshape(cost.shape), mask.reshape(cost.shape[0], cost.shape[2]) > 0):
            valid = np.flatnonzero(m)
            rows, cols = linear_sum_assignment(c[:, valid])
            pairs.append((rows.astype(np.int64), valid[cols].astype(np.int64)))
        out.append(pairs)
    return out


def pair_index(pairs: Pairs, device) -> tuple[Tensor, Tensor, Tensor]:
    """The (batch item, query, target) index tensors of every matched pair, moved to ``device`` in one transfer."""
    b = np.concatenate([np.full(len(q), k, np.int64) for k, (q, _) in enumerate(pairs)])
    index = torch.from_numpy(np.stack([b, np.concatenate([q for q, _ in pairs]), np.concatenate([g for _, g in pairs])]))
    return tuple(index.to(device))


def kl_divergence(mean: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mean, exp(logvar)) || N(0, I)), averaged over all elements."""
    return -0.5 * torch.mean(1.0 + logvar - mean.square() - logvar.exp())


def set_loss(decoded: dict[str, Tensor], batch: dict[str, Tensor], config: RVAELossConfig,
             matched: list[Pairs]) -> dict[str, Tensor]:
    """Matched L1 and existence BCE (and direction) per element type of one set of outputs
    (``{"l1/lines", "exist/lines", ...}``), given each element type's matched (query, target) pairs."""
    parts: dict[str, Tensor] = {}
    for name, pairs in zip(ELEMENTS, matched):
        pred, logit = decoded[name], decoded[f"{name}_logit"]
        gt = batch[name].to(pred)
        b, q, g = pair_index(pairs, pred.device)
        target = torch.zeros_like(logit)
        target[b, q] = 1.0
        parts[f"l1/{name}"] = line_l1(pred[b, q], gt[b, g], config.frame_m).sum() / logit.numel()
        parts[f"exist/{name}"] = F.binary_cross_entropy_with_logits(logit, target)
        if config.direction_weight > 0:
            parts[f"dir/{name}"] = direction_loss(pred[b, q], gt[b, g]).sum() / logit.numel()
    return parts


def direction_loss(pred: Tensor, gt: Tensor) -> Tensor:
    """Per polyline (..., P, 2): mean over segments of 1 - cosine between predicted and true directions."""
    return (1.0 - F.cosine_similarity(pred.diff(dim=-2), gt.diff(dim=-2), dim=-1, eps=1e-6)).mean(-1)


def successor_loss(logits: Tensor, succ: Tensor, pairs: Pairs) -> Tensor:
    """BCE of successor logits (B, Q, Q) between matched queries against the targets' successors
    (B, G, G), self pairs left out: every pair of the batch in one gather."""
    b, q, g = pair_index(pairs, logits.device)
    target_of = torch.full(logits.shape[:2], -1, dtype=torch.int64, device=logits.device)
    target_of[b, q] = g
    matched = target_of >= 0
    scored = matched[:, :, None] & matched[:, None, :] & ~torch.eye(logits.shape[1], dtype=torch.bool,
                                                                      device=logits.device)
    t = target_of.clamp(min=0)
    target = succ[torch.arange(len(t), device=t.device)[:, None, None], t[:, :, None], t[:, None, :]]
    loss = F.binary_cross_entropy_with_logits(logits[scored], target[scored].to(logits.dtype), reduction="sum")
    return loss / scored.sum().clamp(min=1)


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
    sets = [decoded, *((decoded.get("aux") or []) if config.aux_weight > 0 else [])]
    matched = match([(d[name], d[f"{name}_logit"], batch[name], batch[MASK_KEYS[name]]) for d in sets
                     for name in ELEMENTS], config)
    per_set = [matched[k:k + len(ELEMENTS)] for k in range(0, len(matched), len(ELEMENTS))]
    parts = set_loss(decoded, batch, config, per_set[0])
    if config.successor_weight > 0 and "succ_logit" in decoded:
        parts["succ/lines"] = successor_loss(decoded["succ_logit"], batch["succ"], per_set[0][0])
    parts["kl"] = kl_divergence(mean, logvar)
    total = _weighted({k: v for k, v in parts.items() if k != "kl"}, config) + config.kl_weight * parts["kl"]
    if len(sets) > 1:
        parts["aux"] = config.aux_weight * sum(_weighted(set_loss(d, batch, config, m), config)
                                               for d, m in zip(sets[1:], per_set[1:]))
        total = total + parts["aux"]
    if config.denoise_weight > 0 and "denoise" in decoded:
        parts["denoise"] = config.denoise_weight * denoise_loss(decoded["denoise"], batch, config)
        total = total + parts["denoise"]
    return total, {k: float(v.detach()) for k, v in parts.items()}
