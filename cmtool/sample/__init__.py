"""Diffusion sampling: noise schedules and DDPM/DDIM samplers with classifier-free guidance."""

SAMPLERS = ("ddpm", "ddim")
# DDPM by default: with the small shipped models, deterministic DDIM turns about one map in nine
# into a zig-zag tangle, and the fresh noise of every ancestral step keeps the trajectory near the
# data (README: Shipped weights).
DEFAULT_SAMPLER = "ddpm"
