"""Sampler settings: the sampler, its step count, the guidance weight, the seed and the batch size of a run, as
``cmtool sample``, ``eval``, ``ablate``, ``bench`` and a pipeline recipe's ``[pipeline.eval]`` take them, checked once
by :meth:`SamplerSettings.check`. No torch here: the CLI reads the defaults before anything heavy is imported."""

from __future__ import annotations

import math
from dataclasses import dataclass

from cmtool.core.errors import CmtoolError

SAMPLERS = ("ddpm", "ddpm-trailing", "ddim", "dpm++2m", "dpm++2m-sde")
# The timestep spacing of each sampler (cmtool.diffusion.schedule.NoiseSchedule.timesteps); "linear" otherwise.
SPACINGS = {"ddpm-trailing": "trailing", "dpm++2m": "logsnr", "dpm++2m-sde": "logsnr"}
# The default: DDPM on trailing timesteps in 2 steps. From the same noise its maps keep the quality of 50 DDPM steps
# on 512 held-out scenes at a twenty-fifth of the model passes (docs/speed.md, "Few steps"); the fresh noise of an
# ancestral step keeps the small shipped models near the data, where deterministic DDIM turns about one map in nine
# into a zig-zag tangle (docs/shipped-weights.md).
DEFAULT_SAMPLER = "ddpm-trailing"
# Each sampler's default step count. 15 steps of dpm++2m-sde keep GT Recall and validity within 0.003 of
# 50 DDPM steps on 512 held-out scenes, at 3.3x fewer model passes (docs/speed.md, "Samplers"); the
# deterministic solvers (ddim, dpm++2m) fall short of DDPM at any count with the small shipped models.
DEFAULT_STEPS = {"ddpm": 50, "ddpm-trailing": 2, "ddim": 50, "dpm++2m": 15, "dpm++2m-sde": 15}
TABLE_STEPS = (1, 2, 3, 4, 6, 8, 10, 15, 20, 30, 50)  # the step counts of `cmtool bench sample --data`'s table


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
