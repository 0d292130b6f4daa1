"""The VL-Map belief: a categorical distribution over voxels fusing language and vision log-likelihoods.

`grid` defines the voxels, `fusion` the update equations, `summary` what the posterior says, and
`session` the stateful belief and the session record that the stores in `app.stores` persist.

`__all__` is what the other rooms (sessions, stores, api, the simulator) use; the stores also apply the
update equations of `app.belief.fusion` to their own arrays, by module.
"""

from app.belief.fusion import LayerLimits
from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_MAX_VOXELS, DEFAULT_VOXEL_SIZE_M, VoxelGrid
from app.belief.session import (
    BeliefState,
    IncrementBatch,
    LabelNames,
    Labels,
    ObservationModel,
    SensorModel,
    Session,
    SessionInfo,
    UpdateResult,
    check_target_label,
    language_log_likelihood,
    mapped_look_alikes,
    new_session,
)
from app.belief.summary import PlaceMass, PosteriorSummary, VoxelMass, place_voxels, summarize

__all__ = [
    "DEFAULT_MARGIN_M",
    "DEFAULT_MAX_VOXELS",
    "DEFAULT_VOXEL_SIZE_M",
    "BeliefState",
    "IncrementBatch",
    "LabelNames",
    "Labels",
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
    "check_target_label",
    "language_log_likelihood",
    "mapped_look_alikes",
    "new_session",
    "place_voxels",
    "summarize",
]
