"""Metrics for grounding accuracy and calibration, shared by training and the evaluation CLI."""
