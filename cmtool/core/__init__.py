"""Ground utilities every layer may use: errors, JSON I/O, geometry, geographic projection, progress lines,
TOML tables as dataclasses, a union-find, processes under torchrun."""
