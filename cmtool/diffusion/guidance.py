"""Classifier-free guidance: one noise prediction from the conditioned and unconditioned passes of a step.

SD-map guidance (ControlMap paper, eq. 1): ``eps = eps_uncond + w (eps_cond - eps_uncond)``, where the
conditioned prediction uses the SD map and the unconditioned one is the frozen base DiT; ``w = 0``
runs the base DiT alone and reproduces its samples exactly, and ``w = 1`` is the conditioned prediction alone,
which one pass of the conditioned rows gives (no unconditioned pass: half the rows of a guided step).

City-label guidance (DiT-style, optional): with ``city_cfg = s != 1`` one more base pass with the null
label gives ``eps_null``, and both predictions move by ``(s - 1) (eps_uncond - eps_null)``, so that
``eps = eps_null + s (eps_uncond - eps_null) + w (eps_cond - eps_uncond)``; ``s = 1`` is the plain
label conditioning the models were trained with, ``s > 1`` strengthens the city's style.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor, nn


@dataclass
class Prediction:
    """A step's guided noise prediction ``eps`` and what it was made of (None where no such pass ran)."""

    eps: Tensor
    eps_cond: Tensor | None
    eps_uncond: Tensor | None  # None at w = 1, where no unconditioned pass runs
    residuals: list[Tensor] | None  # the control residual each injected DiT block received


def guided_eps(model: nn.Module, x: Tensor, t: Tensor, y: Tensor, *, tokens: Tensor | None, cfg: float,
               city_cfg: float = 1.0, null: Tensor | None = None) -> Prediction:
    """The guided prediction at ``x`` (B, C, H, W), timesteps ``t`` and labels ``y`` (B,): with control ``tokens``
    (a ControlMap's encoded SD rasters) one batched guided pass, else the base model alone; ``null`` (labels of
    the null class) for city-label guidance when ``city_cfg != 1``. Under bf16 autocast the model answers in
    bf16; the prediction is float32."""
    if tokens is not None and cfg == 1 and city_cfg == 1:
        eps_cond, residuals = model.forward_cond(x, t, y, tokens=tokens)
        eps_cond = eps_cond.float()
        return Prediction(eps_cond, eps_cond, None, residuals)
    if tokens is not None:
        eps_cond, eps_uncond, residuals = model.forward_cfg(x, t, y, tokens=tokens)
        eps_cond, eps_uncond = eps_cond.float(), eps_uncond.float()
        eps = eps_uncond + cfg * (eps_cond - eps_uncond)
    else:
        eps_cond, residuals = None, None
        eps = eps_uncond = model(x, t, y).float()
    if city_cfg != 1:
        push = (city_cfg - 1) * (eps_uncond - model(x, t, null).float())
        eps, eps_uncond = eps + push, eps_uncond + push
        eps_cond = None if eps_cond is None else eps_cond + push
    return Prediction(eps, eps_cond, eps_uncond, residuals)
