"""Training: one loop (loop.py) for the three stages (stages.py), their data, the latent cache, DDP setup."""
