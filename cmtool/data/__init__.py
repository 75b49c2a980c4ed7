"""Map data for training and evaluation: procedural cities, SD derivation and jitter, rule-based layouts, frames,
scenes, rasters, data recipes and the dataset cache."""
