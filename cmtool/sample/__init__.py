"""Sampling maps: SD inputs, the map generator (checkpoints loaded, the one generate loop) and ``cmtool sample``."""

# Decoded polylines are replaced by their least-squares Bézier curves with this many control points
# (0: the decoder's raw points). 99% of the CPU dataset's ground-truth lanes lie within 5 cm of their
# fit, the shipped model's lanes half a metre from it at the median: the fit removes the decoder's
# point jitter, not the lanes' shape (docs/sampling.md).
DEFAULT_SMOOTH = 6

# Where an untagged SD road's lanes per direction come from in the maps ``cmtool sample`` writes
# (:mod:`cmtool.sample.compose`): its class's usual count, or as many as the model drew along it (the class's where it
# drew none). On 96 Argoverse 2 frames without lane tags the model's counts give lane F1 0.672 against the class's
# 0.550 (docs/baselines.md).
COUNTS = ("class", "model")
DEFAULT_COUNTS = "model"
