"""Training: one loop (loop.py) for the three stages (stages.py), their data, the latent cache, DDP setup."""

PRECISIONS = ("auto", "bf16", "fp32")  # train.precision: auto is bf16 autocast on CUDA, fp32 on CPU
