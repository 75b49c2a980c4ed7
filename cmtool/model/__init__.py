"""Neural networks: the RVAE (stage 1), the DiT (stage 2) and the ControlMap branch (stage 3), their configs,
checkpoints and the shipped weights' packing."""
