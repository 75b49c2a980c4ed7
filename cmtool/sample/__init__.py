"""Sampling maps: SD inputs, the map generator (checkpoints loaded, the one generate loop) and ``cmtool sample``."""

# Decoded polylines are replaced by their least-squares Bézier curves with this many control points
# (0: the decoder's raw points). 99% of the CPU dataset's ground-truth lanes lie within 5 cm of their
# fit, the shipped model's lanes half a metre from it at the median: the fit removes the decoder's
# point jitter, not the lanes' shape (docs/sampling.md).
DEFAULT_SMOOTH = 6
