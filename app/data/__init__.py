"""Grounding cases: the evaluation file format, the builder from real layouts, and converters.

A namespace of modules; other rooms import from the defining module: `app.data.cases` (`GroundingCase`,
`read_cases`: the case files of evaluation, training and the simulator), `app.data.build` (which
objects may be targets, for the simulator's episodes) and `app.data.cli` (`vlmap data`). The box relations
the builder labels with are the proposer's and the LSM's too: `app.grounding.box_relations`.
"""
