"""Metrics for grounding accuracy and calibration, shared by training and the evaluation CLI.

A namespace of modules; other rooms import from the defining module: `app.evaluation.metrics` (pure metric
functions: `nees`, `gaussian_nll`, ...), `app.evaluation.static` (`expected_calibration_error`, the static
evaluation) and `app.evaluation.cli` (`vlmap eval`).
"""
