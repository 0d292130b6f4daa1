"""The closed-loop simulator's core: scenes and episodes, a semantic voxel world, a ray-cast camera, label
noise and a seeded exploration policy. Pure numpy, deterministic under a seed; no service calls here.

`__all__` is that core. The modules that run it against a service are imported by module: `runner`
(`SimConfig`, `load_episodes`, `run_simulation`), `perception` (the realistic segmenter), `metrics`,
`report`, `cli` (`vlmap sim`) and `service` (`start_service`, `wait_ready`, `running_service`: a `vlmap
serve` subprocess, which the tests and benchmarks start too).
"""

from app.sim.camera import Camera, CameraConfig, Observation, Pose, RayCast, cast_rays
from app.sim.noise import LabelNoise
from app.sim.policy import PolicyConfig, explore, trajectory
from app.sim.scenes import (
    Episode,
    SimScene,
    episode_from_case,
    episodes_from_cases,
    load_layout_scenes,
    load_vla3d_scenes,
)
from app.sim.world import FREE, FREE_LABEL, RobotBody, SemanticVoxelWorld

__all__ = [
    "FREE",
    "FREE_LABEL",
    "Camera",
    "CameraConfig",
    "Episode",
    "LabelNoise",
    "Observation",
    "PolicyConfig",
    "Pose",
    "RayCast",
    "RobotBody",
    "SemanticVoxelWorld",
    "SimScene",
    "cast_rays",
    "episode_from_case",
    "episodes_from_cases",
    "explore",
    "load_layout_scenes",
    "load_vla3d_scenes",
    "trajectory",
]
