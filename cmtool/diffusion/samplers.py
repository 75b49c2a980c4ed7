"""The samplers: DDPM, DDIM and DPM-Solver++ from ``x_T`` to a clean latent, guided at every step
(:mod:`cmtool.diffusion.guidance`), with a record of each step for whoever watches (:class:`StepInfo`).

Sampling runs on ``steps`` timesteps of the training schedule (:mod:`cmtool.diffusion.schedule`);
DDPM uses the respaced betas ``1 - abar_t / abar_prev`` (``steps == train_steps`` is plain DDPM);
``ddpm-trailing`` is DDPM on trailing timesteps, whose last step jumps to the clean estimate from a whole
interval above t = 0 instead of spending a pass at t = 0 (two of its steps make maps of the quality of
three, docs/speed.md);
DDIM interpolates between deterministic (``eta = 0``) and ancestral (``eta = 1``). ``dpm++2m`` is
DPM-Solver++(2M) (Lu et al., 2022): a second-order multistep solver on the clean estimates in log-SNR
time, deterministic; ``dpm++2m-sde`` its stochastic form, which adds fresh noise every step as DDPM
does. Both take a first-order step first and last, on timesteps evenly spaced in log-SNR (with the
linear schedule, evenly spaced t would leave the last steps far too coarse).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from cmtool.diffusion.guidance import guided_eps
from cmtool.diffusion.schedule import NoiseSchedule
from cmtool.diffusion.settings import SAMPLERS, SPACINGS, SamplingError
from cmtool.model.controlmap import ControlMap


@dataclass
class StepInfo:
    """What one sampling step saw and predicted (handed to the callback after the step)."""

    step: int
    t: int
    x_t: Tensor
    x0: Tensor
    eps_cond: Tensor | None
    eps_uncond: Tensor | None
    eps: Tensor
    residuals: list[Tensor] | None


@torch.no_grad()
def sample(model: nn.Module, schedule: NoiseSchedule, y: Tensor, *, control: Tensor | None = None,
           cfg: float = 1.0, city_cfg: float = 1.0, steps: int = 50, sampler: str = "ddpm",
           eta: float = 0.0, generator: torch.Generator | None = None, noise: Tensor | None = None,
           init: Tensor | None = None, strength: float = 1.0,
           callback: Callable[[StepInfo], None] | None = None) -> Tensor:
    """Denoise from ``x_T`` to a clean latent ``(B, C, H, W)`` for labels ``y`` (B,).

    ``model`` is a DiT (or any ``eps = model(x, t, y)`` with ``latent_shape``) or a ControlMap. With
    a ControlMap, a ``control`` image (B, 3, px, px) and ``cfg > 0``, each step makes one batched
    guided pass; ``cfg == 0`` or no control runs the base DiT only. ``city_cfg != 1`` adds a pass
    with the null label (module doc). All randomness comes from ``generator`` (a CPU generator gives the same
    noise on every device), including ``x_T`` unless ``noise`` is given.

    ``init`` (a clean latent, e.g. an encoded rule layout) starts the denoising from it instead of from
    pure noise (SDEdit, Meng et al., ICLR 2022): it is noised to the timestep ``strength`` of the way
    up the schedule (with ``noise`` as the noise) and only the sampler's timesteps from there down run
    (``ddpm-trailing`` spreads all its steps below it); ``strength = 1`` is plain sampling, small strengths keep
    ``init`` nearly as it is.
    """
    if not (math.isfinite(cfg) and cfg >= 0):
        raise SamplingError(f"cfg: guidance scale must be finite and >= 0, got {cfg}")
    if not (math.isfinite(city_cfg) and city_cfg >= 0):
        raise SamplingError(f"city_cfg: city-label guidance scale must be finite and >= 0, got {city_cfg}")
    if sampler not in SAMPLERS:
        raise SamplingError(f"sampler: unknown sampler {sampler!r} (choose {', '.join(SAMPLERS)})")
    if not (math.isfinite(eta) and eta >= 0):
        raise SamplingError(f"eta: must be finite and >= 0, got {eta}")
    if control is not None and not isinstance(model, ControlMap):
        raise SamplingError("control: a control image needs a ControlMap model")
    shape = (y.shape[0], *model.latent_shape)
    if noise is not None and tuple(noise.shape) != shape:
        raise SamplingError(f"noise: expected shape {shape}, got {tuple(noise.shape)}")
    if not (math.isfinite(strength) and 0 < strength <= 1):
        raise SamplingError(f"strength: must be in (0, 1], got {strength}")
    if init is not None and tuple(init.shape) != shape:
        raise SamplingError(f"init: expected shape {shape}, got {tuple(init.shape)}")
    spacing = SPACINGS.get(sampler, "linear")
    ts = schedule.timesteps(steps, spacing)
    if init is not None:  # the steps below the strength; trailing steps are all spread below it
        top = round(strength * (schedule.train_steps - 1))
        ts = schedule.timesteps(min(steps, top + 1), spacing, top) if spacing == "trailing" else \
            [t for t in ts if t <= top] or [top]
    guided = control is not None and cfg > 0
    tokens = model.encode_control(control) if guided else None
    base = model.base if isinstance(model, ControlMap) else model
    null = torch.full_like(y, base.null_label) if city_cfg != 1 else None
    x = noise.to(y.device, copy=True) if noise is not None else _randn_like(torch.empty(shape, device=y.device),
                                                                             generator)
    if init is not None:
        x = schedule.q_sample(init.to(x.device, x.dtype), torch.full((shape[0],), ts[0], device=x.device), x)
    previous, ab_last = None, 0.0  # the multistep solvers' clean estimate and abar of the step before
    for i, t in enumerate(ts):
        tt = torch.full((shape[0],), t, dtype=torch.long, device=x.device)
        pred = guided_eps(model, x, tt, y, tokens=tokens, cfg=cfg, city_cfg=city_cfg, null=null)
        x0 = schedule.predict_x0(x, tt, pred.eps)
        x_t = x
        ab_t = float(schedule.alphas_cumprod[t])
        ab_prev = float(schedule.alphas_cumprod[ts[i + 1]]) if i + 1 < len(ts) else 1.0
        if sampler == "ddim":
            x = _ddim_step(x0, pred.eps, ab_t, ab_prev, eta, generator)
        elif sampler.startswith("dpm++"):
            second = i > 0 and i + 1 < len(ts)
            x = _dpm_step(x, x0, previous if second else None, ab_t, ab_prev, ab_last,
                          sampler.endswith("sde"), generator)
            previous, ab_last = x0, ab_t
        else:  # ddpm, ddpm-trailing
            x = _ddpm_step(x, pred.eps, ab_t, ab_prev, generator)
        if callback is not None:
            callback(StepInfo(i, t, x_t, x0, pred.eps_cond, pred.eps_uncond, pred.eps, pred.residuals))
    return x


def _ddim_step(x0: Tensor, eps: Tensor, ab_t: float, ab_prev: float, eta: float,
               generator: torch.Generator | None) -> Tensor:
    """DDIM update to the previous timestep; ``eta = 1`` matches DDPM's posterior variance."""
    sigma = eta * math.sqrt((1 - ab_prev) / (1 - ab_t) * (1 - ab_t / ab_prev))
    x = math.sqrt(ab_prev) * x0 + math.sqrt(max(1 - ab_prev - sigma**2, 0.0)) * eps
    return x + sigma * _randn_like(x, generator) if sigma > 0 else x


def _ddpm_step(x: Tensor, eps: Tensor, ab_t: float, ab_prev: float, generator: torch.Generator | None) -> Tensor:
    """Ancestral DDPM update with the respaced beta ``1 - ab_t / ab_prev`` and posterior variance."""
    beta = 1 - ab_t / ab_prev
    mean = (x - beta / math.sqrt(1 - ab_t) * eps) / math.sqrt(1 - beta)
    var = beta * (1 - ab_prev) / (1 - ab_t)
    return mean + math.sqrt(var) * _randn_like(x, generator) if var > 0 else mean


def _dpm_step(x: Tensor, x0: Tensor, x0_before: Tensor | None, ab_t: float, ab_prev: float, ab_before: float,
              sde: bool, generator: torch.Generator | None) -> Tensor:
    """DPM-Solver++(2M) from timestep t (``ab_t``) to the next (``ab_prev``; 1 is the clean end) on the clean
    estimate ``x0``, second order with the estimate of the step before (at ``ab_before``) when given.
    With ``sde``, the stochastic form: the old state decays by exp(-2h) instead of exp(-h) and fresh noise
    makes up the variance."""
    if ab_prev >= 1.0:
        return x0
    lam = lambda ab: 0.5 * math.log(ab / (1 - ab))  # noqa: E731  log(alpha / sigma)
    h = lam(ab_prev) - lam(ab_t)
    alpha, sigma, sigma_t = math.sqrt(ab_prev), math.sqrt(1 - ab_prev), math.sqrt(1 - ab_t)
    d = x0
    if x0_before is not None:  # D0 + (D0 - D_before) / (2 r), r = h_before / h
        r = (lam(ab_t) - lam(ab_before)) / h
        d = x0 + (x0 - x0_before) / (2 * r)
    if not sde:
        return sigma / sigma_t * x + alpha * (-math.expm1(-h)) * d
    decay = math.exp(-2 * h)
    return (sigma / sigma_t * math.exp(-h) * x + alpha * (1 - decay) * d
            + sigma * math.sqrt(1 - decay) * _randn_like(x, generator))


def _randn_like(x: Tensor, generator: torch.Generator | None) -> Tensor:
    """Noise like ``x`` drawn where ``generator`` lives (the CPU without one), so a seed gives the same noise on
    every device."""
    where = generator.device if generator is not None else "cpu"
    return torch.randn(x.shape, generator=generator, device=where, dtype=x.dtype).to(x.device)
