"""Fitting the models the service ships: the LSM (`lsm`, `vlmap train`) and the proposer (`referents`,
`vlmap fit-proposer`). The runtime rooms (grounding, lsm, api) never import this one.

A namespace of modules with no public API for other rooms: `app.cli` reaches them through
the `add_parser` of `app.training.cli` and `app.training.referents`.
"""
