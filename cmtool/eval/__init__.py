"""Evaluation metrics: generated maps against ground truth and SD control."""
