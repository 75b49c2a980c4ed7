"""Diffusion sampling: noise schedules and DDIM/DDPM samplers with classifier-free guidance."""
