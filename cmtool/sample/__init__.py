"""Diffusion sampling: noise schedules and DDPM, DDIM and DPM-Solver++ samplers with classifier-free
guidance."""

SAMPLERS = ("ddpm", "ddim", "dpm++2m", "dpm++2m-sde")
# DDPM by default: with the small shipped models, deterministic DDIM turns about one map in nine
# into a zig-zag tangle, and the fresh noise of every ancestral step keeps the trajectory near the
# data (docs/shipped-weights.md).
DEFAULT_SAMPLER = "ddpm"
# Each sampler's default step count. 15 steps of dpm++2m-sde keep GT Recall and validity within 0.003 of
# 50 DDPM steps on 512 held-out scenes, at 3.3x fewer model passes (docs/speed.md, "Samplers"); the
# deterministic solvers (ddim, dpm++2m) fall short of DDPM at any count with the small shipped models.
DEFAULT_STEPS = {"ddpm": 50, "ddim": 50, "dpm++2m": 15, "dpm++2m-sde": 15}
# Decoded polylines are replaced by their least-squares Bézier curves with this many control points
# (0: the decoder's raw points). 99% of the CPU dataset's ground-truth lanes lie within 5 cm of their
# fit, the shipped model's lanes half a metre from it at the median: the fit removes the decoder's
# point jitter, not the lanes' shape (docs/sampling.md).
DEFAULT_SMOOTH = 6
