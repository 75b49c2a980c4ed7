"""The metric library: generated lane graphs against ground truth and SD control, validity and repair. It
imports no model."""
