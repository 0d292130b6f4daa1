"""Fitting the models the service ships: the LSM (`lsm`, `vlmap train`) and the proposer (`referents`,
`vlmap fit-proposer`). The runtime rooms (grounding, lsm, api) never import this one."""
