"""Noise schedules and the DDPM, DDIM and DPM-Solver++ samplers with classifier-free guidance on the
SD-map control and, optionally, on the city label.

Training uses the DDPM forward process ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` over
``train_steps`` steps (SLEDGE: linear betas 1e-4 .. 0.02). Sampling runs on ``steps`` evenly spaced
timesteps; DDPM uses the respaced betas ``1 - abar_t / abar_prev`` (``steps == train_steps`` is
plain DDPM), DDIM interpolates between deterministic (``eta = 0``) and ancestral (``eta = 1``).
``dpm++2m`` is DPM-Solver++(2M) (Lu et al., 2022): a second-order multistep solver on the clean
estimates in log-SNR time, deterministic; ``dpm++2m-sde`` its stochastic form, which adds fresh noise
every step as DDPM does. Both take a first-order step first and last, on timesteps evenly spaced in
log-SNR (with the linear schedule, evenly spaced t would leave the last steps far too coarse).

Guidance (ControlMap paper, eq. 1): ``eps = eps_uncond + w (eps_cond - eps_uncond)``, where the
conditioned prediction uses the SD map and the unconditioned one is the frozen base DiT; ``w = 0``
runs the base DiT alone and reproduces its samples exactly.

City-label guidance (DiT-style, optional): with ``city_cfg = s != 1`` one more base pass with the null
label gives ``eps_null``, and both predictions move by ``(s - 1) (eps_uncond - eps_null)``, so that
``eps = eps_null + s (eps_uncond - eps_null) + w (eps_cond - eps_uncond)``; ``s = 1`` is the plain
label conditioning the models were trained with, ``s > 1`` strengthens the city's style.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor, nn

from cmtool.errors import CmtoolError
from cmtool.model.config import ScheduleConfig
from cmtool.model.controlmap import ControlMap
from cmtool.sample import DEFAULT_SAMPLER, SAMPLERS


class SamplingError(CmtoolError, ValueError):
    """A bad schedule or sampling argument (also a ValueError for library callers)."""


class NoiseSchedule:
    """The forward process: ``betas`` and ``alphas_cumprod`` (float64, CPU, length train_steps)."""

    def __init__(self, cfg: ScheduleConfig):
        if cfg.train_steps < 1:
            raise SamplingError(f"schedule.train_steps: must be >= 1, got {cfg.train_steps}")
        if cfg.kind == "linear":
            if not 0 < cfg.beta_start <= cfg.beta_end < 1:
                raise SamplingError("schedule: need 0 < beta_start <= beta_end < 1, "
                                    f"got {cfg.beta_start}, {cfg.beta_end}")
            betas = np.linspace(cfg.beta_start, cfg.beta_end, cfg.train_steps)
        elif cfg.kind == "cosine":
            f = np.cos((np.arange(cfg.train_steps + 1) / cfg.train_steps + 0.008) / 1.008 * math.pi / 2) ** 2
            betas = np.minimum(1 - f[1:] / f[:-1], 0.999)
        else:
            raise SamplingError(f"schedule.kind: unknown kind {cfg.kind!r} (choose linear or cosine)")
        self.cfg = cfg
        self.train_steps = cfg.train_steps
        self.betas = torch.from_numpy(betas)
        self.alphas_cumprod = torch.cumprod(1 - self.betas, dim=0)

    def _at(self, values: Tensor, t: Tensor, like: Tensor) -> Tensor:
        """``values[t]`` shaped to broadcast over ``like`` (B, ...), on its device and dtype."""
        return values[t.cpu().long()].to(like.device, like.dtype).reshape(-1, *[1] * (like.ndim - 1))

    def q_sample(self, x0: Tensor, t: Tensor, noise: Tensor) -> Tensor:
        """Noisy ``x_t`` for clean ``x0`` at timesteps ``t`` (B,)."""
        ab = self._at(self.alphas_cumprod, t, x0)
        return ab.sqrt() * x0 + (1 - ab).sqrt() * noise

    def min_snr_weight(self, t: Tensor, gamma: float) -> Tensor:
        """Min-SNR-gamma loss weights (Hang et al., ICCV 2023) of an epsilon-prediction loss at timesteps
        ``t`` (B,): ``min(SNR_t, gamma) / SNR_t`` with ``SNR_t = abar_t / (1 - abar_t)``."""
        ab = self.alphas_cumprod[t.cpu().long()]
        snr = ab / (1 - ab)
        return (snr.clamp(max=gamma) / snr).to(t.device, torch.float32)

    def predict_x0(self, x_t: Tensor, t: Tensor, eps: Tensor) -> Tensor:
        """Clean estimate from ``x_t`` and predicted noise ``eps`` at timesteps ``t`` (B,)."""
        ab = self._at(self.alphas_cumprod, t, x_t)
        return (x_t - (1 - ab).sqrt() * eps) / ab.sqrt()

    def timesteps(self, num_steps: int, spacing: str = "linear") -> list[int]:
        """``num_steps`` distinct timesteps descending from ``train_steps - 1`` to 0: evenly spaced in t
        (``linear``), or in log-SNR (``logsnr``, DPM-Solver's spacing: many more steps near the data)."""
        if not 1 <= num_steps <= self.train_steps:
            raise SamplingError(f"steps: must be in 1..{self.train_steps}, got {num_steps}")
        if spacing == "linear" or num_steps == 1:
            return [int(t) for t in np.linspace(self.train_steps - 1, 0, num_steps).round()]
        ab = self.alphas_cumprod.numpy()
        lam = 0.5 * np.log(ab / (1 - ab))  # decreasing in t
        ts = np.searchsorted(-lam, -np.linspace(lam[-1], lam[0], num_steps)).clip(0, self.train_steps - 1)
        ts[0], ts[-1] = self.train_steps - 1, 0
        for k in range(num_steps - 2, -1, -1):  # distinct: each at least one above the next ...
            ts[k] = max(ts[k], ts[k + 1] + 1)
        return [int(min(t, self.train_steps - 1 - k)) for k, t in enumerate(ts)]  # ... and room above


def scene_seed(seed: int, scene: int) -> int:
    """The seed of the initial noise of scene (or batch starting at) ``scene`` of a run seeded ``seed``
    (``eval``, ``ablate``): each scene its own noise, whatever else the run generates."""
    return seed * 1_000_003 + scene


def step_generator(seed: int, device="cpu") -> torch.Generator:
    """The generator of the stochastic samplers' per-step noise when the initial noise ``x_T`` was
    drawn from ``torch.Generator().manual_seed(seed)``: a stream of its own, so that no step adds
    ``x_T`` back in. (The CPU generator keeps only a seed's low 32 bits, so an offset like
    ``seed + 2**40`` would not do; the seed is hashed instead.)"""
    return torch.Generator(device).manual_seed(int(np.random.SeedSequence([seed, 1]).generate_state(1)[0]))


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
           cfg: float = 1.0, city_cfg: float = 1.0, steps: int = 50, sampler: str = DEFAULT_SAMPLER,
           eta: float = 0.0, generator: torch.Generator | None = None, noise: Tensor | None = None,
           callback: Callable[[StepInfo], None] | None = None) -> Tensor:
    """Denoise from ``x_T`` to a clean latent ``(B, C, H, W)`` for labels ``y`` (B,).

    ``model`` is a DiT (or any ``eps = model(x, t, y)`` with ``latent_shape``) or a ControlMap. With
    a ControlMap, a ``control`` image (B, 3, px, px) and ``cfg > 0``, each step makes one batched
    guided pass; ``cfg == 0`` or no control runs the base DiT only. ``city_cfg != 1`` adds a pass
    with the null label (module doc). All randomness comes from ``generator`` (which must live on
    ``y``'s device), including ``x_T`` unless ``noise`` is given.
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
    ts = schedule.timesteps(steps, "logsnr" if sampler.startswith("dpm++") else "linear")
    guided = control is not None and cfg > 0
    tokens = model.encode_control(control) if guided else None
    base = model.base if isinstance(model, ControlMap) else model
    null = torch.full_like(y, base.null_label) if city_cfg != 1 else None
    x = noise.clone() if noise is not None else torch.randn(shape, generator=generator, device=y.device)
    previous, ab_last = None, 0.0  # the multistep solvers' clean estimate and abar of the step before
    for i, t in enumerate(ts):
        tt = torch.full((shape[0],), t, dtype=torch.long, device=x.device)
        if guided:  # under bf16 autocast the model answers in bf16: the update runs in float32
            eps_cond, eps_uncond, residuals = model.forward_cfg(x, tt, y, tokens=tokens)
            eps_cond, eps_uncond = eps_cond.float(), eps_uncond.float()
            eps = eps_uncond + cfg * (eps_cond - eps_uncond)
        else:
            eps_cond, residuals = None, None
            eps = eps_uncond = model(x, tt, y).float()
        if city_cfg != 1:
            push = (city_cfg - 1) * (eps_uncond - model(x, tt, null).float())
            eps, eps_uncond = eps + push, eps_uncond + push
            eps_cond = None if eps_cond is None else eps_cond + push
        x0 = schedule.predict_x0(x, tt, eps)
        x_t = x
        ab_t = float(schedule.alphas_cumprod[t])
        ab_prev = float(schedule.alphas_cumprod[ts[i + 1]]) if i + 1 < len(ts) else 1.0
        if sampler == "ddim":
            x = _ddim_step(x0, eps, ab_t, ab_prev, eta, generator)
        elif sampler.startswith("dpm++"):
            second = i > 0 and i + 1 < len(ts)
            x = _dpm_step(x, x0, previous if second else None, ab_t, ab_prev, ab_last,
                          sampler.endswith("sde"), generator)
            previous, ab_last = x0, ab_t
        else:
            x = _ddpm_step(x, eps, ab_t, ab_prev, generator)
        if callback is not None:
            callback(StepInfo(i, t, x_t, x0, eps_cond, eps_uncond, eps, residuals))
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
    return torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
