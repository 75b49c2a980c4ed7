"""Experiments that generate maps and score them: ``cmtool eval``, the ablations and the benches."""
