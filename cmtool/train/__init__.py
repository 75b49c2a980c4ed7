"""Training: recipes, one loop (loop.py) for every stage (stages.py), their data, the latent cache, reconstruction
scores, DDP setup."""

PRECISIONS = ("auto", "bf16", "fp32")  # train.precision: auto is bf16 where native and faster (precision.py)
