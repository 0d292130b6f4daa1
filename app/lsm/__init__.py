"""The learned Language Sensor Model (LSM): one calibrated Gaussian per grounding hypothesis.

`LSMGrounder.load()` (app.lsm.grounder) serves the weights shipped in models/lsm;
`vlmap train` (app.training.lsm) trains new ones.
"""
