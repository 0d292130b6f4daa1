"""Fitting the models the service ships: the proposer (`referents`); see also `app.lsm.train`."""
