"""The DDPM forward process: a linear (SLEDGE: betas 1e-4 .. 0.02) or cosine noise schedule over ``train_steps``
steps, ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps``, and the timesteps a sampler of fewer steps visits."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from cmtool.diffusion.settings import SamplingError
from cmtool.model.config import ScheduleConfig


class NoiseSchedule:
    """The forward process: ``betas`` and ``alphas_cumprod`` (float64, CPU, length train_steps)."""

    def __init__(self, config: ScheduleConfig):
        if config.train_steps < 1:
            raise SamplingError(f"schedule.train_steps: must be >= 1, got {config.train_steps}")
        if config.kind == "linear":
            if not 0 < config.beta_start <= config.beta_end < 1:
                raise SamplingError("schedule: need 0 < beta_start <= beta_end < 1, "
                                    f"got {config.beta_start}, {config.beta_end}")
            betas = np.linspace(config.beta_start, config.beta_end, config.train_steps)
        elif config.kind == "cosine":
            f = np.cos((np.arange(config.train_steps + 1) / config.train_steps + 0.008) / 1.008 * math.pi / 2) ** 2
            betas = np.minimum(1 - f[1:] / f[:-1], 0.999)
        else:
            raise SamplingError(f"schedule.kind: unknown kind {config.kind!r} (choose linear or cosine)")
        self.config = config
        self.train_steps = config.train_steps
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

    def timesteps(self, num_steps: int, spacing: str = "linear", top: int | None = None) -> list[int]:
        """``num_steps`` distinct timesteps descending from ``train_steps - 1``: to 0, evenly spaced in t
        (``linear``) or in log-SNR (``logsnr``, DPM-Solver's spacing: many more steps near the data); or evenly
        spaced in t with the last a whole interval above 0 (``trailing``, Lin et al., WACV 2024): the sampler
        then jumps from it to the clean estimate, where a pass at t = 0 would barely change the latent; ``top``: the
        trailing steps start there instead (a start noised part of the way, SDEdit)."""
        if not 1 <= num_steps <= self.train_steps:
            raise SamplingError(f"steps: must be in 1..{self.train_steps}, got {num_steps}")
        if spacing == "trailing":
            span = self.train_steps if top is None else top + 1
            if num_steps > span:
                raise SamplingError(f"steps: at most {span} trailing steps start at timestep {top}, got {num_steps}")
            return [int(t) - 1 for t in np.linspace(span, 0, num_steps + 1).round()[:-1]]
        if spacing == "linear" or num_steps == 1:
            return [int(t) for t in np.linspace(self.train_steps - 1, 0, num_steps).round()]
        ab = self.alphas_cumprod.numpy()
        lam = 0.5 * np.log(ab / (1 - ab))  # decreasing in t
        ts = np.searchsorted(-lam, -np.linspace(lam[-1], lam[0], num_steps)).clip(0, self.train_steps - 1)
        ts[0], ts[-1] = self.train_steps - 1, 0
        for k in range(num_steps - 2, -1, -1):  # distinct: each at least one above the next ...
            ts[k] = max(ts[k], ts[k + 1] + 1)
        return [int(min(t, self.train_steps - 1 - k)) for k, t in enumerate(ts)]  # ... and room above
