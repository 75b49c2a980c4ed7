"""Sampler settings: the sampler, its step count, the guidance weight, the seed and the batch size of a run, as
``cmtool sample``, ``eval``, ``ablate``, ``bench`` and a pipeline recipe's ``[pipeline.eval]`` take them, checked once
by :meth:`SamplerSettings.check`. No torch here: the CLI reads the defaults before anything heavy is imported."""

from __future__ import annotations

import math
from dataclasses import dataclass

from cmtool.core.errors import CmtoolError

SAMPLERS = ("ddpm", "ddim", "dpm++2m", "dpm++2m-sde")
# DDPM by default: with the small shipped models, deterministic DDIM turns about one map in nine
# into a zig-zag tangle, and the fresh noise of every ancestral step keeps the trajectory near the
# data (docs/shipped-weights.md).
DEFAULT_SAMPLER = "ddpm"
# Each sampler's default step count. 15 steps of dpm++2m-sde keep GT Recall and validity within 0.003 of
# 50 DDPM steps on 512 held-out scenes, at 3.3x fewer model passes (docs/speed.md, "Samplers"); the
# deterministic solvers (ddim, dpm++2m) fall short of DDPM at any count with the small shipped models.
DEFAULT_STEPS = {"ddpm": 50, "ddim": 50, "dpm++2m": 15, "dpm++2m-sde": 15}


class SamplingError(CmtoolError, ValueError):
    """A bad schedule or sampling argument (also a ValueError for library callers)."""


@dataclass(kw_only=True)
class SamplerSettings:
    """How a run samples its maps. ``cfg`` is the guidance weight w on the SD map (0: the DiT alone); the noise of
    the batch of maps ``first, first + 1, ...`` comes from ``seed`` and ``first`` alone
    (:func:`cmtool.diffusion.noise.batch_noise`), so a map does not depend on the batches before it."""

    cfg: float = 1.0
    steps: int = DEFAULT_STEPS[DEFAULT_SAMPLER]
    sampler: str = DEFAULT_SAMPLER
    seed: int = 0
    batch: int = 16

    def check(self, prefix: str = "--") -> None:
        """Reject values no sampler can use; ``prefix`` names the options in the message (``--`` for the CLI)."""
        if not (math.isfinite(self.cfg) and self.cfg >= 0):
            raise SamplingError(f"{prefix}cfg: guidance weight must be a finite number >= 0, got {self.cfg}")
        if self.sampler not in SAMPLERS:
            raise SamplingError(f"{prefix}sampler: choose {', '.join(SAMPLERS)}, got {self.sampler!r}")
        for name in ("steps", "batch"):
            if getattr(self, name) < 1:
                raise SamplingError(f"{prefix}{name}: must be at least 1, got {getattr(self, name)}")
