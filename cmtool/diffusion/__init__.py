"""The diffusion core shared by training and sampling: noise schedule, guidance, samplers, the noise of a run
and its sampler settings."""
