"""Where a run's noise comes from: the initial latent of each batch and the samplers' step noise, both from the
run's seed and the batch's first map alone, so that a map depends neither on the batches before it nor on the
process (or GPU) that makes it."""

from __future__ import annotations

import numpy as np
import torch


def scene_seed(seed: int, scene: int) -> int:
    """The seed of the initial noise of scene (or batch starting at) ``scene`` of a run seeded ``seed``
    (``eval``, ``ablate``): each scene its own noise, whatever else the run generates."""
    return seed * 1_000_003 + scene


def step_generator(seed: int) -> torch.Generator:
    """The generator of the stochastic samplers' per-step noise when the initial noise ``x_T`` was
    drawn from ``torch.Generator().manual_seed(seed)``: a stream of its own, so that no step adds
    ``x_T`` back in. (The CPU generator keeps only a seed's low 32 bits, so an offset like
    ``seed + 2**40`` would not do; the seed is hashed instead.)"""
    return torch.Generator().manual_seed(int(np.random.SeedSequence([seed, 1]).generate_state(1)[0]))


def batch_noise(shape: tuple[int, ...], seed: int, first: int, device="cpu") -> tuple[torch.Tensor, torch.Generator]:
    """The initial latents (``shape``, batch first) of the batch whose first map is map (or scene) ``first`` of a run
    seeded ``seed``, and the generator of the samplers' step noise: both from ``scene_seed(seed, first)`` alone, and
    both drawn on the CPU (a CUDA generator draws other numbers from the same seed)."""
    base = scene_seed(seed, first)
    x_t = torch.randn(shape, generator=torch.Generator().manual_seed(base))
    return x_t.to(device), step_generator(base)
