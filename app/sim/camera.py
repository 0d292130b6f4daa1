"""A depth-and-semantics camera in the voxel world: a pinhole frustum of rays, each stopped by the first
occupied voxel.

Rays. Pixel (a, b) of a W x H image looks along the camera-frame direction (forward x, left y, up z)

    d_cam = (1, u_a tan(hfov/2), v_b tan(vfov/2)),   u_a = 1 - 2(a + 1/2)/W,  v_b = 1 - 2(b + 1/2)/H,

normalised, then tilted up by the pitch (elevation of the optical axis) and turned by the yaw about +z.

Traversal (Amanatides & Woo, "A fast voxel traversal algorithm for ray tracing", 1987). A ray p(t) = o + t d
(|d| = 1, so t is metres) visits the voxels it crosses in order. With t_max[k] the t at which it next crosses
a voxel boundary along axis k and t_delta[k] = s / |d_k| the t between two such crossings, each step moves
to the neighbour along k* = argmin_k t_max[k] and adds t_delta[k*] to t_max[k*]; the ray enters that
neighbour at t = the old t_max[k*]. Vectorised: the crossings along axis k are t_max[k] + n t_delta[k],
n = 0, 1, ..., so all of a ray's crossings within range are listed at once and sorted by t; the voxel
entered at each one follows from how many crossings along each axis came before.

A voxel is observed when a ray enters it at t <= max_range: the first occupied one ends the ray (a hit, with
its object), the free ones before it are observed as free (a robot's depth sensor sees through them, and the
belief's vision update lowers the target's mass there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.belief.grid import VoxelGrid
from app.errors import InvalidInput
from app.sim.world import FREE, SemanticVoxelWorld

# Direction components smaller than this are replaced by it, so that 1/d stays finite.
_TINY = 1e-12
# Offset between the sort keys of boundary crossings along successive axes, in voxel sizes (see cast_rays).
_TIE_BREAK = 1e-9


@dataclass(frozen=True)
class Pose:
    """Camera pose: position (metres); yaw about +z from +x and pitch = elevation (up > 0), in radians."""

    x: float
    y: float
    z: float
    yaw: float
    pitch: float = 0.0

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    @property
    def forward(self) -> np.ndarray:
        """Unit vector of the optical axis."""
        cp = math.cos(self.pitch)
        return np.array([cp * math.cos(self.yaw), cp * math.sin(self.yaw), math.sin(self.pitch)])


@dataclass(frozen=True)
class CameraConfig:
    hfov_deg: float = 90.0
    vfov_deg: float = 60.0
    max_range: float = 3.5
    width: int = 64  # rays per image row
    height: int = 48  # rays per image column
    observe_free: bool = True  # report the free voxels the rays pass through

    def __post_init__(self) -> None:
        for name, value in (("hfov_deg", self.hfov_deg), ("vfov_deg", self.vfov_deg)):
            if not (math.isfinite(value) and 0 < value < 180):
                msg = f"{name} must lie in (0, 180) degrees, got {value}"
                raise InvalidInput(msg, f"camera.{name}")
        if not (math.isfinite(self.max_range) and self.max_range > 0):
            msg = f"max_range must be a positive number of metres, got {self.max_range}"
            raise InvalidInput(msg, "camera.max_range")
        if self.width < 1 or self.height < 1:
            msg = f"the ray grid needs at least 1 x 1 rays, got {self.width} x {self.height}"
            raise InvalidInput(msg, "camera.width")


def camera_frame_directions(config: CameraConfig) -> np.ndarray:
    """(H * W, 3) unit ray directions in the camera frame (forward x, left y, up z), row-major."""
    u = 1.0 - 2.0 * (np.arange(config.width) + 0.5) / config.width  # (W,) left (+) to right (-)
    v = 1.0 - 2.0 * (np.arange(config.height) + 0.5) / config.height  # (H,) top (+) to bottom (-)
    vv, uu = np.meshgrid(v, u, indexing="ij")  # (H, W)
    d = np.stack(
        [
            np.ones_like(uu),
            uu * math.tan(math.radians(config.hfov_deg) / 2),
            vv * math.tan(math.radians(config.vfov_deg) / 2),
        ],
        axis=-1,
    ).reshape(-1, 3)
    unit: np.ndarray = d / np.linalg.norm(d, axis=1, keepdims=True)
    return unit


def rotate_to_world(directions: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """(R, 3) camera-frame directions -> world frame: pitch (up > 0) about the camera's y axis, then yaw."""
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    # Columns: images of the camera's forward, left and up axes.
    forward = np.array([cp * cy, cp * sy, sp])
    left = np.array([-sy, cy, 0.0])
    up = np.array([-sp * cy, -sp * sy, cp])
    world: np.ndarray = directions @ np.stack([forward, left, up])
    return world


@dataclass(frozen=True)
class RayCast:
    """What each of R rays saw."""

    hit_flat: np.ndarray  # (R,) flat index of the first occupied voxel within range, -1 if none
    hit_t: np.ndarray  # (R,) distance at which the ray enters that voxel, inf if none
    voxels: np.ndarray  # (R, S) flat indices of the voxels each ray entered, in order (valid where masked)
    free_mask: np.ndarray  # (R, S) bool: the voxel is free and entered within range before the ray's hit

    @property
    def free_flat(self) -> np.ndarray:
        """(F,) the free voxels the rays entered before their hit (a voxel may repeat)."""
        free: np.ndarray = self.voxels[self.free_mask]
        return free

    @property
    def free_ray(self) -> np.ndarray:
        """(F,) the ray that entered each of `free_flat`."""
        return np.nonzero(self.free_mask)[0]


def cast_rays(
    owner: np.ndarray, grid: VoxelGrid, origin: np.ndarray, directions: np.ndarray, max_range: float
) -> RayCast:
    """Traverse (R, 3) unit-direction rays from `origin` through the owner array (FREE = empty); see the
    module docstring. The origin may lie outside the grid: rays start where they enter it."""
    o = np.asarray(origin, dtype=np.float64)  # (3,)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)  # (R, 3)
    d = np.where(np.abs(d) < _TINY, _TINY, d)
    n_rays = len(d)
    s = grid.voxel_size
    low, shape = grid.min_corner, np.asarray(grid.shape)
    inv = 1.0 / d
    # Slab test: the t interval during which each ray is inside the grid.
    t_a, t_b = (low - o) * inv, (grid.max_corner - o) * inv  # (R, 3)
    t_in = np.maximum(np.max(np.minimum(t_a, t_b), axis=1), 0.0)  # (R,)
    t_out = np.min(np.maximum(t_a, t_b), axis=1)  # (R,)
    enters = (t_in < t_out) & (t_in <= max_range)  # (R,)
    ijk0 = np.clip(np.floor((o + d * t_in[:, None] - low) / s).astype(np.int64), 0, shape - 1)  # (R, 3)
    step = np.where(d > 0, 1, -1)  # (R, 3)
    t_first = (low + (ijk0 + (step > 0)) * s - o) * inv  # (R, 3) first boundary crossing per axis
    t_delta = s * np.abs(inv)  # (R, 3)

    # Along axis k a ray crosses boundaries at t_first[k] + n t_delta[k], n = 0, 1, ...; at most C_k of them
    # lie within range (C_k: the most any ray makes). List them all, (R, C_x + C_y + C_z), and sort them by t.
    # The sort key adds a negligible per-axis offset so that exact ties (a ray through a voxel edge) go x
    # before y before z, as argmin does in the classic loop.
    per_axis = np.floor((max_range - t_first) / t_delta) + 1  # (R, 3) crossings within range
    n_cross = np.clip(per_axis.max(axis=0, initial=0), 1, math.ceil(max_range / s) + 1).astype(np.int64)
    axis_of = np.repeat(np.arange(3), n_cross)  # (C,) the axis of each column
    count = np.concatenate([np.arange(n) for n in n_cross])  # (C,) n of each column
    crossings = t_first[:, axis_of] + t_delta[:, axis_of] * count  # (R, C)
    order = np.argsort(crossings + axis_of * (_TIE_BREAK * s), axis=1)  # (R, C)
    # Keep the first S - 1 crossings, S - 1 >= the most any ray makes within range.
    n_steps = int(min(np.clip(per_axis, 0, None).sum(axis=1).max(initial=0) + 1, len(axis_of)))
    order = order[:, :n_steps]
    rows = np.arange(n_rays)
    t_enter = np.empty((n_rays, n_steps + 1))  # (R, S): the t at which each ray enters its S voxels
    t_enter[:, 0] = t_in
    t_enter[:, 1:] = crossings.ravel()[(rows * len(axis_of))[:, None] + order]
    # Each crossing moves the flat index by +-stride of its axis.
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    jumps = (step * strides).ravel()  # (3R,)
    flat = np.empty(t_enter.shape, dtype=np.int64)  # (R, S) the voxels entered
    flat[:, 0] = ijk0 @ strides
    flat[:, 1:] = jumps[(3 * rows)[:, None] + axis_of[order]]
    np.cumsum(flat, axis=1, out=flat)
    # A ray is in the (convex) grid from t_in to t_out; the crossing that leaves it is computed from the other
    # side, so compare with a margin far below a voxel to keep rounding from letting it through.
    in_grid = t_enter < (t_out - _TIE_BREAK * s)[:, None]  # (R, S)
    inside = enters[:, None] & (t_enter <= max_range) & in_grid
    flat[~inside] = 0
    occupied = inside & (owner.reshape(-1)[flat] != FREE)  # (R, S)
    has_hit = occupied.any(axis=1)  # (R,)
    first = np.where(has_hit, np.argmax(occupied, axis=1), t_enter.shape[1])  # (R,) step of the first hit
    hit_at = np.minimum(first, t_enter.shape[1] - 1)
    return RayCast(
        hit_flat=np.where(has_hit, flat[rows, hit_at], -1),
        hit_t=np.where(has_hit, t_enter[rows, hit_at], np.inf),
        voxels=flat,
        free_mask=inside & (np.arange(t_enter.shape[1]) < first[:, None]),
    )


@dataclass(frozen=True)
class Observation:
    """The voxels one camera frame observed, each once, sorted by flat index, with their true contents, and
    per ray what it stopped on (a segmenter's view of the same frame: which object each pixel shows)."""

    pose: Pose
    flat_idx: np.ndarray  # (M,) int64 flat voxel indices of the world's grid
    owner: np.ndarray  # (M,) int32 object index in the world, FREE for free voxels (names: world.labels_of)
    # (R,) int32 object index of each ray's hit, FREE for a ray that hit nothing within range; empty when
    # the observation was made without rays.
    ray_owner: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int32))
    # (R,) metres to each ray's hit, inf for none.
    ray_distance: np.ndarray = field(default_factory=lambda: np.empty(0))

    @property
    def hit_mask(self) -> np.ndarray:
        """(M,) bool: the voxel is occupied (some ray stopped on it)."""
        hit: np.ndarray = self.owner != FREE
        return hit

    def __len__(self) -> int:
        return len(self.flat_idx)


class Camera:
    """A camera that sees the world's voxels along a fixed grid of rays."""

    def __init__(self, config: CameraConfig | None = None) -> None:
        self.config = config or CameraConfig()
        self._directions = camera_frame_directions(self.config)  # (R, 3)

    @property
    def n_rays(self) -> int:
        return len(self._directions)

    def cast(self, world: SemanticVoxelWorld, pose: Pose) -> RayCast:
        directions = rotate_to_world(self._directions, pose.yaw, pose.pitch)
        return cast_rays(world.owner, world.grid, pose.position, directions, self.config.max_range)

    def observe(self, world: SemanticVoxelWorld, pose: Pose) -> Observation:
        """The voxels seen from `pose`: every ray's first hit, and the free voxels before it if configured."""
        result = self.cast(world, pose)
        n_voxels = world.grid.n_voxels
        # A mask over the grid (plus one slot for "nothing") is cheaper than np.unique at these sizes.
        seen = np.zeros(n_voxels + 1, dtype=bool)
        seen[np.where(result.hit_flat >= 0, result.hit_flat, n_voxels)] = True
        if self.config.observe_free:
            seen[np.where(result.free_mask, result.voxels, n_voxels)] = True
        flat_idx = np.flatnonzero(seen[:n_voxels])
        owners = world.owner.reshape(-1)
        owner = owners[flat_idx]
        ray_owner = np.where(result.hit_flat >= 0, owners[np.maximum(result.hit_flat, 0)], FREE)
        return Observation(
            pose=pose,
            flat_idx=flat_idx,
            owner=owner,
            ray_owner=ray_owner.astype(np.int32),
            ray_distance=result.hit_t,
        )
