"""A seeded random exploration policy over the world's free floor, shared by every method under comparison.

The robot starts on a random free floor cell with a random heading, then repeats:

1. pick a waypoint: the first of `waypoint_tries` uniformly drawn free floor cells at least
   `min_waypoint_distance` away whose straight segment from the robot runs over free floor only
   (`SemanticVoxelWorld.segment_is_free`); with none, turn in place and try again next step;
2. drive to it in steps of at most `max_step` metres, facing the motion direction plus a Gaussian yaw
   jitter (`look_jitter_deg`), the camera pitched by `pitch_deg`;
3. look around on arrival: `spin_steps` turns in place of 360 / (spin_steps + 1) degrees each, in a random
   direction, so that the arrival view and the turns cover the full circle evenly.

One pose is one camera frame. Every random choice comes from the given numpy Generator, so a seed fixes the
trajectory, and all language sensors are compared on the same frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import islice

import numpy as np

from app.errors import InvalidInput
from app.sim.camera import Pose
from app.sim.world import SemanticVoxelWorld


@dataclass(frozen=True)
class PolicyConfig:
    max_step: float = 0.5  # metres per frame while driving
    # Camera tilt (down < 0): a level 60-degree camera at 1.2 m misses the first 2 m of floor.
    pitch_deg: float = -15.0
    look_jitter_deg: float = 15.0  # standard deviation of the yaw around the motion direction
    spin_steps: int = 4  # turns in place at each waypoint
    waypoint_tries: int = 32
    min_waypoint_distance: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_step) and self.max_step > 0):
            msg = f"max_step must be a positive number of metres, got {self.max_step}"
            raise InvalidInput(msg, "policy.max_step")
        if self.spin_steps < 0 or self.waypoint_tries < 1:
            msg = f"need spin_steps >= 0, waypoint_tries >= 1; got {self.spin_steps}, {self.waypoint_tries}"
            raise InvalidInput(msg, "policy.spin_steps")


def _wrap(angle: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _pick_waypoint(
    world: SemanticVoxelWorld,
    points: np.ndarray,
    position: np.ndarray,
    rng: np.random.Generator,
    config: PolicyConfig,
) -> np.ndarray | None:
    for k in rng.integers(len(points), size=config.waypoint_tries):
        candidate: np.ndarray = points[k]
        far_enough = np.linalg.norm(candidate - position) >= config.min_waypoint_distance
        if far_enough and world.segment_is_free(position, candidate):
            return candidate
    return None


def explore(
    world: SemanticVoxelWorld,
    rng: np.random.Generator,
    config: PolicyConfig | None = None,
    start: tuple[float, float] | None = None,
) -> Iterator[Pose]:
    """Endless camera poses of the exploration (module docstring); `start` (x, y) must be free floor."""
    config = config or PolicyConfig()
    points = world.free_floor_points()  # (K, 2)
    if len(points) == 0:
        msg = (
            f"the world has no free floor for a robot of radius {world.robot.radius} m "
            f"and height {world.robot.height} m"
        )
        raise InvalidInput(msg, "world")
    if start is None:
        position = points[rng.integers(len(points))].copy()
    else:
        position = np.asarray(start, dtype=np.float64)
        if not world.is_free_floor(position)[0]:
            msg = f"start {list(start)} is not on free floor"
            raise InvalidInput(msg, "start")
    yaw = float(rng.uniform(-math.pi, math.pi))
    pitch = math.radians(config.pitch_deg)
    turn = 2.0 * math.pi / (config.spin_steps + 1)
    z = world.camera_z

    def pose() -> Pose:
        return Pose(float(position[0]), float(position[1]), z, yaw, pitch)

    yield pose()
    waypoint: np.ndarray | None = None
    spins_left, spin_direction = 0, 1.0
    while True:
        if spins_left == 0 and waypoint is None:
            waypoint = _pick_waypoint(world, points, position, rng, config)
        if spins_left > 0 or waypoint is None:  # looking around, or boxed in for now (turn, try again)
            yaw = _wrap(yaw + spin_direction * turn)
            spins_left = max(spins_left - 1, 0)
        else:
            offset = waypoint - position
            distance = float(np.linalg.norm(offset))
            if distance <= config.max_step:
                position = waypoint.copy()
                waypoint = None
                spins_left = config.spin_steps
                spin_direction = float(rng.choice([-1.0, 1.0]))
            else:
                position = position + offset * (config.max_step / distance)
            jitter = math.radians(config.look_jitter_deg) * float(rng.standard_normal())
            yaw = _wrap(math.atan2(offset[1], offset[0]) + jitter)
        yield pose()


def trajectory(
    world: SemanticVoxelWorld,
    n_steps: int,
    rng: np.random.Generator,
    config: PolicyConfig | None = None,
    start: tuple[float, float] | None = None,
) -> list[Pose]:
    """The first `n_steps` poses of `explore`."""
    if n_steps < 0:
        msg = f"n_steps must be non-negative, got {n_steps}"
        raise InvalidInput(msg, "n_steps")
    return list(islice(explore(world, rng, config, start), n_steps))
