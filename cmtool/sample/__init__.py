"""Diffusion sampling: noise schedules and DDPM/DDIM samplers with classifier-free guidance."""

SAMPLERS = ("ddpm", "ddim")
# DDPM by default: with the small shipped models, deterministic DDIM sends about one initial noise in
# seven into the same tangle of short lanes in the frame's middle, whatever the SD map; the fresh
# noise of every ancestral step keeps the trajectory near the data (README: Shipped weights).
DEFAULT_SAMPLER = "ddpm"
