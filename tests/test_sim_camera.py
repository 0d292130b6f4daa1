"""The simulated camera: frustum, range and occlusion on hand-made worlds, and the vectorised voxel traversal
against a slow exact reference (ray-box slab tests against every voxel)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.errors import InvalidInput
from app.scene_graph.model import SceneObject
from app.sim.camera import (
    Camera,
    CameraConfig,
    Pose,
    camera_frame_directions,
    cast_rays,
    rotate_to_world,
)
from app.sim.world import FREE, FREE_LABEL, SemanticVoxelWorld

# 10 m x 10 m x 3.5 m around the camera at the origin, 1 m above the floor.
GRID = VoxelGrid(origin=(-5.0, -5.0, -0.5), shape=(100, 100, 35), voxel_size=0.1)
EYE = Pose(0.0, 0.0, 1.0, yaw=0.0)


def cube(
    object_id: str, center: tuple[float, float, float], side: float = 0.4, label: str = "box"
) -> SceneObject:
    return SceneObject(id=object_id, label=label, center=list(center), size=[side, side, side])


def seen_ids(objects: list[SceneObject], pose: Pose = EYE, config: CameraConfig | None = None) -> set[str]:
    world = SemanticVoxelWorld(GRID, objects, floor_z=0.0)
    observation = Camera(config).observe(world, pose)
    return {world.objects[k].id for k in np.unique(observation.owner[observation.hit_mask])}


# --- frustum and range ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("center", "visible"),
    [
        ((2.0, 0.0, 1.0), True),  # straight ahead
        ((-2.0, 0.0, 1.0), False),  # behind
        ((0.0, 2.0, 1.0), False),  # 90 degrees left, outside the 90-degree horizontal field
        ((2.0, 1.0, 1.0), True),  # 27 degrees left
        ((2.0, -1.6, 1.0), True),  # 39 degrees right
        ((2.0, 2.6, 1.0), False),  # 52 degrees left
        ((2.0, 0.0, 2.9), False),  # 43 degrees up, outside the 60-degree vertical field
        ((3.2, 0.0, 1.0), True),  # front face at 3.0 m
        ((4.2, 0.0, 1.0), False),  # front face at 4.0 m, beyond the 3.5 m range
    ],
)
def test_frustum_and_range(center: tuple[float, float, float], visible: bool) -> None:
    assert ("b" in seen_ids([cube("b", center)])) is visible


def test_range_is_configurable() -> None:
    far = [cube("b", (4.2, 0.0, 1.0))]
    assert "b" in seen_ids(far, config=CameraConfig(max_range=5.0))


def test_yaw_and_pitch_turn_the_view() -> None:
    left = [cube("b", (0.0, 2.0, 1.0))]
    assert "b" in seen_ids(left, Pose(0.0, 0.0, 1.0, yaw=math.pi / 2))
    low = [cube("b", (0.8, 0.0, 0.15), side=0.3)]  # its top far edge 36 degrees below the horizon
    assert "b" not in seen_ids(low)
    assert "b" in seen_ids(low, Pose(0.0, 0.0, 1.0, yaw=0.0, pitch=math.radians(-30)))


def test_camera_frame_spans_the_field_of_view() -> None:
    config = CameraConfig(hfov_deg=90.0, vfov_deg=60.0, width=64, height=48)
    d = camera_frame_directions(config)
    assert d.shape == (64 * 48, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    yaw = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    pitch = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    # Pixel centres sit half a pixel inside the image edges.
    assert 43.0 < yaw.max() < 45.0 and -45.0 < yaw.min() < -43.0
    assert pitch.max() < 30.0 and pitch.max() > 28.0
    # Turned by yaw then pitched, the optical axis is the pose's forward vector.
    pose = Pose(0.0, 0.0, 0.0, yaw=0.7, pitch=-0.3)
    axis = rotate_to_world(np.array([[1.0, 0.0, 0.0]]), pose.yaw, pose.pitch)[0]
    np.testing.assert_allclose(axis, pose.forward, atol=1e-12)


def test_camera_config_is_validated() -> None:
    with pytest.raises(InvalidInput):
        CameraConfig(hfov_deg=180.0)
    with pytest.raises(InvalidInput):
        CameraConfig(max_range=0.0)


# --- occlusion ------------------------------------------------------------------------------------------


WALL = SceneObject(id="wall", label="wall", center=[1.5, 0.0, 1.25], size=[0.2, 1.2, 2.5])


def test_box_behind_a_wall_is_hidden_one_beside_it_is_seen() -> None:
    behind = cube("behind", (2.5, 0.0, 1.0))
    beside = cube("beside", (2.5, 1.5, 1.0))
    assert seen_ids([behind, beside]) == {"behind", "beside", "__floor__"}  # control: no wall
    assert seen_ids([WALL, behind, beside]) == {"wall", "beside", "__floor__"}


def test_only_the_near_face_is_observed_and_free_space_before_it() -> None:
    world = SemanticVoxelWorld(GRID, [cube("b", (2.2, 0.0, 1.0))], floor_z=0.0)  # x from 2.0 to 2.4
    observation = Camera().observe(world, EYE)
    assert np.all(np.diff(observation.flat_idx) > 0)  # unique, sorted
    box_cells = world.grid.flat_to_ijk(observation.flat_idx[observation.owner == world.index_of("b")])
    assert set(box_cells[:, 0]) == {70}  # the voxel layer x in [2.0, 2.1): the face towards the camera
    # On the optical axis every voxel from the camera to the box is observed free, nothing behind it.
    on_axis = world.grid.locate(np.array([[x, 0.05, 1.05] for x in np.arange(0.05, 4.0, 0.1)]))[0]
    observed = set(observation.flat_idx.tolist())
    assert all(int(v) in observed for v in on_axis[:20])  # x < 2.0
    assert not any(int(v) in observed for v in on_axis[21:])  # x > 2.1
    free = observation.owner == FREE
    labels = world.labels_of(observation.owner)
    assert set(labels[free]) == {FREE_LABEL} and set(labels[~free]) <= {
        "box",
        "floor",
    }
    assert len(Camera(CameraConfig(observe_free=False)).observe(world, EYE)) == np.count_nonzero(~free)


def test_opened_contents_are_seen_through_their_tunnel() -> None:
    couch = SceneObject(id="couch", label="couch", center=[1.0, 0.5, 0.45], size=[2.0, 1.0, 0.9])
    pillow = SceneObject(id="pillow", label="pillow", center=[0.7, 0.5, 0.65], size=[0.4, 0.4, 0.3])
    remote = SceneObject(id="remote", label="remote", center=[0.65, 0.45, 0.85], size=[0.1, 0.1, 0.1])
    front = Pose(0.7, -2.0, 1.0, yaw=math.pi / 2)  # 2 m in front of the couch, looking at it
    assert "pillow" in seen_ids([couch, pillow, remote], front)  # through the tunnel to the couch's front
    world = SemanticVoxelWorld(GRID, [couch, pillow, remote], floor_z=0.0, open_enclosed=False)
    observation = Camera().observe(world, front)
    assert world.index_of("pillow") not in set(observation.owner.tolist())


def test_camera_inside_an_object_sees_only_that_voxel() -> None:
    world = SemanticVoxelWorld(GRID, [cube("b", (0.0, 0.0, 1.0), side=1.0)], floor_z=0.0)
    observation = Camera().observe(world, EYE)
    assert len(observation) == 1 and observation.owner[0] == world.index_of("b")


# --- traversal against an exact reference ---------------------------------------------------------------


def reference_cast(
    owner: np.ndarray, grid: VoxelGrid, origin: np.ndarray, direction: np.ndarray, max_range: float
) -> tuple[int, set[int]]:
    """First occupied voxel (or -1) and the free voxels before it, by slab tests against every voxel."""
    ijk = grid.flat_to_ijk(np.arange(grid.n_voxels))
    low = grid.min_corner + ijk * grid.voxel_size  # (N, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a = (low - origin) / direction
        t_b = (low + grid.voxel_size - origin) / direction
    t_near = np.max(np.minimum(t_a, t_b), axis=1)
    t_far = np.min(np.maximum(t_a, t_b), axis=1)
    enter = np.maximum(t_near, 0.0)
    crossed = (t_near < t_far) & (t_far > 0) & (enter <= max_range)  # the ray passes through the voxel
    candidates = np.flatnonzero(crossed)
    candidates = candidates[np.argsort(enter[candidates])]
    occupied = owner.ravel()[candidates] != FREE
    if not occupied.any():
        return -1, set(candidates.tolist())
    first = int(np.argmax(occupied))
    return int(candidates[first]), set(candidates[:first].tolist())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_traversal_matches_exact_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = VoxelGrid(origin=(-1.0, -0.5, 0.0), shape=(24, 20, 12), voxel_size=0.1)
    owner = np.where(rng.random(grid.shape) < 0.02, 0, FREE).astype(np.int32)
    # Cameras inside the grid and outside it (rays must enter it first).
    origins = [
        grid.min_corner + rng.random(3) * (grid.max_corner - grid.min_corner),
        np.array([-1.7, 0.3, 0.5]),
    ]
    for origin in origins:
        directions = rng.normal(size=(150, 3))
        directions[:, 0] = np.abs(directions[:, 0])  # mostly towards the grid from the outside camera
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        result = cast_rays(owner, grid, origin, directions, max_range=2.0)
        for r in range(len(directions)):
            hit, free = reference_cast(owner, grid, origin, directions[r], 2.0)
            assert result.hit_flat[r] == hit
            assert set(result.free_flat[result.free_ray == r].tolist()) == free
            if hit >= 0:
                # The hit distance is where the ray enters the hit voxel.
                point = origin + result.hit_t[r] * directions[r]
                centre = grid.centers(np.array([hit]))[0]
                assert np.max(np.abs(point - centre)) <= grid.voxel_size / 2 + 1e-9


def test_axis_aligned_rays_and_grid_edges() -> None:
    grid = VoxelGrid(origin=(0.0, 0.0, 0.0), shape=(10, 10, 10), voxel_size=0.1)
    owner = np.full(grid.shape, FREE, dtype=np.int32)
    owner[7, 5, 5] = 3
    origin = np.array([0.05, 0.55, 0.55])
    result = cast_rays(
        owner, grid, origin, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), 5.0
    )
    assert result.hit_flat.tolist() == [grid.ijk_to_flat(np.array([7, 5, 5])), -1, -1]
    assert result.hit_t[0] == pytest.approx(0.65)
    assert sorted(grid.flat_to_ijk(result.free_flat[result.free_ray == 0])[:, 0].tolist()) == list(range(7))
    assert sorted(grid.flat_to_ijk(result.free_flat[result.free_ray == 1])[:, 1].tolist()) == list(
        range(5, 10)
    )
    assert np.count_nonzero(result.free_ray == 2) == 1  # its own voxel, then out of the grid
