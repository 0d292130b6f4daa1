"""The learned Language Sensor Model (LSM): one calibrated Gaussian per grounding hypothesis.

`LSMGrounder.load()` (app.lsm.grounder) serves the weights shipped in models/lsm;
`vlmap train` (app.training.lsm) trains new ones.

A namespace of modules, re-exporting nothing: `app.lsm.checkpoint` describes a checkpoint without importing
torch (the request process of a service with grounding workers), which a package-level import of the
grounder would defeat. Other rooms import from the defining module: `app.lsm.grounder` (`LSMGrounder`,
`DEFAULT_MODEL_DIR`), `app.lsm.checkpoint` (`describe_checkpoint`), `app.lsm.text_encoder` (`TextEncoder`,
`default_text_encoder`), and for training `app.lsm.model` and `app.lsm.features`.
"""
