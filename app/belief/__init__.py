"""The VL-Map belief: a categorical distribution over voxels fusing language and vision log-likelihoods.

`grid` defines the voxels, `fusion` the update equations, `summary` what the posterior says, and
`session` the stateful belief and the session record that the stores in `app.stores` persist.
"""

from app.belief.fusion import LayerLimits
from app.belief.grid import VoxelGrid
from app.belief.session import (
    BeliefState,
    IncrementBatch,
    ObservationModel,
    SensorModel,
    Session,
    SessionInfo,
    UpdateResult,
    new_session,
)
from app.belief.summary import PlaceMass, PosteriorSummary, VoxelMass, summarize

__all__ = [
    "BeliefState",
    "IncrementBatch",
    "LayerLimits",
    "ObservationModel",
    "PlaceMass",
    "PosteriorSummary",
    "SensorModel",
    "Session",
    "SessionInfo",
    "UpdateResult",
    "VoxelGrid",
    "VoxelMass",
    "new_session",
    "summarize",
]
