"""The simulator's voxel world (voxelisation, floor, free floor) and its scene loaders."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.data.cases import read_cases
from app.data.synthetic import synthetic_rooms, write_synthetic_rooms
from app.errors import InvalidInput, NotFound
from app.scene_graph.model import SceneGraph, SceneObject
from app.sim.scenes import (
    DEFAULT_TARGET_SIZE,
    episode_from_case,
    episodes_from_cases,
    load_layout_scenes,
    load_vla3d_scenes,
)
from app.sim.world import (
    FREE,
    FREE_LABEL,
    SYNTHETIC_FLOOR_ID,
    RobotBody,
    SemanticVoxelWorld,
    estimate_floor_z,
)

SIM = Path(__file__).parent / "resources" / "sim"


def box(object_id: str, label: str, low: list[float], high: list[float]) -> SceneObject:
    lo, hi = np.asarray(low), np.asarray(high)
    return SceneObject(id=object_id, label=label, center=((lo + hi) / 2).tolist(), size=(hi - lo).tolist())


def unit_grid(shape: tuple[int, int, int] = (20, 20, 20)) -> VoxelGrid:
    return VoxelGrid(origin=(0.0, 0.0, 0.0), shape=shape, voxel_size=0.1)


def room(extra: list[SceneObject] | None = None) -> list[SceneObject]:
    """A 4 m x 4 m room at [0.5, 4.5]^2: floor, four 0.2 m walls 2.5 m high, optional extras."""
    return [
        box("floor", "floor", [0.5, 0.5, -0.2], [4.5, 4.5, 0.1]),
        box("w_south", "wall", [0.5, 0.5, 0.0], [4.5, 0.7, 2.5]),
        box("w_north", "wall", [0.5, 4.3, 0.0], [4.5, 4.5, 2.5]),
        box("w_west", "wall", [0.5, 0.5, 0.0], [0.7, 4.5, 2.5]),
        box("w_east", "wall", [4.3, 0.5, 0.0], [4.5, 4.5, 2.5]),
        *(extra or []),
    ]


ROOM_GRID = VoxelGrid(origin=(0.0, 0.0, -0.5), shape=(50, 50, 35), voxel_size=0.1)


# --- voxelisation ---------------------------------------------------------------------------------------


def test_box_voxel_counts_and_ids() -> None:
    # Centres at 0.25..0.55 (4) x 0.25..0.45 (3) x 0.25..0.35 (2) lie in the box.
    objects = [
        box("a", "box", [0.2, 0.2, 0.2], [0.6, 0.5, 0.4]),
        box("b", "lamp", [1.0, 1.0, 1.0], [1.3, 1.3, 1.3]),
    ]
    world = SemanticVoxelWorld(unit_grid(), objects, floor_z=0.0)
    a = world.object_voxels("a")
    assert len(a) == 24
    ijk = world.grid.flat_to_ijk(a)
    assert (ijk.min(axis=0).tolist(), ijk.max(axis=0).tolist()) == ([2, 2, 2], [5, 4, 3])
    assert len(world.object_voxels("b")) == 27
    assert set(world.labels_of(world.owner.ravel()[a])) == {"box"}
    # Everything else is free, apart from the floor slab the world adds under a scene without one.
    floor = world.object_voxels(SYNTHETIC_FLOOR_ID)
    assert np.count_nonzero(world.owner != FREE) == 24 + 27 + len(floor)
    assert set(world.grid.flat_to_ijk(floor)[:, 2]) == {world.floor_layer}


def test_thin_objects_keep_one_voxel_layer() -> None:
    # A 2 cm picture between voxel centres still gets the voxels it crosses (one layer thick).
    objects = [box("p", "picture", [0.21, 0.02, 0.4], [0.69, 0.04, 0.8])]
    world = SemanticVoxelWorld(unit_grid(), objects, floor_z=0.0)
    ijk = world.grid.flat_to_ijk(world.object_voxels("p"))
    assert set(ijk[:, 1]) == {0}
    assert len(ijk) == 5 * 4  # x centres 0.25..0.65, z centres 0.45..0.75


def test_smaller_box_wins_overlap() -> None:
    table = box("t", "table", [0.2, 0.2, 0.0], [1.0, 1.0, 0.8])
    book = box("b", "book", [0.4, 0.4, 0.6], [0.6, 0.6, 1.0])  # half inside the table's box
    world = SemanticVoxelWorld(unit_grid(), [book, table], floor_z=0.0)  # order must not matter
    assert len(world.object_voxels("b")) == 2 * 2 * 4
    overlap = 2 * 2 * 2  # z centres 0.65, 0.75 shared
    assert len(world.object_voxels("t")) == 8 * 8 * 8 - overlap


COUCH_GRID = VoxelGrid(origin=(-1.0, -3.0, -0.5), shape=(40, 50, 25), voxel_size=0.1)
COUCH = box("couch", "couch", [0.0, 0.0, 0.0], [2.0, 1.0, 0.9])  # 20 x 10 x 9 voxels
PILLOW = box("pillow", "pillow", [0.5, 0.3, 0.5], [0.9, 0.7, 0.8])  # 4 x 4 x 3 voxels, inside the couch's box
REMOTE = box("remote", "remote", [0.6, 0.4, 0.8], [0.7, 0.5, 0.9])  # 1 voxel, on top of the pillow


def test_enclosed_objects_are_opened_by_the_shortest_tunnel() -> None:
    buried = SemanticVoxelWorld(COUCH_GRID, [COUCH, PILLOW], floor_z=0.0, open_enclosed=False)
    assert len(buried.object_voxels("couch")) == 1800 - 48
    world = SemanticVoxelWorld(COUCH_GRID, [COUCH, PILLOW], floor_z=0.0)
    assert len(world.object_voxels("pillow")) == 48
    # Up is shortest (one layer between the pillow and the top of the couch's box): 4 x 4 voxels freed.
    assert len(world.object_voxels("couch")) == 1800 - 48 - 16
    opened = np.flatnonzero((buried.owner != FREE) & (world.owner == FREE))
    assert set(world.grid.centers(opened)[:, 2].round(2)) == {0.85}


def test_tunnels_never_cut_smaller_objects() -> None:
    # The remote blocks the way up; the next shortest tunnel runs to the front (-y, three layers).
    world = SemanticVoxelWorld(COUCH_GRID, [COUCH, PILLOW, REMOTE], floor_z=0.0)
    assert len(world.object_voxels("remote")) == 1
    assert len(world.object_voxels("couch")) == 1800 - 48 - 1 - 4 * 3 * 3
    buried = SemanticVoxelWorld(COUCH_GRID, [COUCH, PILLOW, REMOTE], floor_z=0.0, open_enclosed=False)
    opened = world.grid.centers(np.flatnonzero((buried.owner != FREE) & (world.owner == FREE)))
    assert set(opened[:, 1].round(2)) == {0.05, 0.15, 0.25}


@pytest.mark.parametrize("label", ["Floor", "shower floor"])
def test_floor_objects_fill_one_layer_below_the_floor(label: str) -> None:
    # A 0.5 m thick floor box (as in ScanNet) must not bury what stands on it; every label of the floor's
    # class is a floor (the vocabulary's `is_floor`), ScanNet's "shower floor" as well.
    objects = [
        box("f", label, [0.0, 0.0, -0.2], [2.0, 2.0, 0.3]),
        box("s", "shoe", [0.5, 0.5, 0.0], [0.8, 0.7, 0.1]),
        box("c", "chair", [1.0, 1.0, 0.0], [1.5, 1.5, 0.9]),
    ]
    grid = VoxelGrid(origin=(0.0, 0.0, -0.5), shape=(20, 20, 20), voxel_size=0.1)
    world = SemanticVoxelWorld(grid, objects)
    assert world.floor_z == pytest.approx(0.0)  # the chair's and shoe's bottoms, inside the floor box
    floor_ijk = world.grid.flat_to_ijk(world.object_voxels("f"))
    assert set(floor_ijk[:, 2]) == {world.floor_layer}
    assert world.grid.axis_centers(2)[world.floor_layer] == pytest.approx(-0.05)
    assert len(world.object_voxels("s")) == 3 * 2 * 1
    # The world's own floor lies under the objects' extent, beneath the scene's floor.
    assert len(world.object_voxels(SYNTHETIC_FLOOR_ID)) == 0
    assert world.free_floor.shape == (20, 20) and world.free_floor[2, 2] and not world.free_floor[12, 12]


def test_floor_z_estimate_ignores_outliers_and_clips_to_the_floor_box() -> None:
    furniture = [box(str(k), "chair", [k, 0.0, -0.02], [k + 0.5, 0.5, 0.9]) for k in range(12)]
    sunk = box("x", "pipe", [0.0, 2.0, -1.0], [0.2, 2.2, 0.5])  # pokes far below the floor
    assert estimate_floor_z([*furniture, sunk]) == pytest.approx(-0.02)
    # Only wall-mounted things: the quantile lies high, the floor box's top bounds it.
    hung = [box(str(k), "picture", [k, 0.0, 1.2], [k + 0.5, 0.1, 1.6]) for k in range(3)]
    floor = box("f", "floor", [0.0, 0.0, -0.3], [3.0, 3.0, 0.0])
    assert estimate_floor_z([*hung, floor]) == pytest.approx(0.0)


def test_objects_outside_the_grid_are_left_out() -> None:
    world = SemanticVoxelWorld(unit_grid(), [box("o", "box", [5.0, 5.0, 5.0], [5.5, 5.5, 5.5])], floor_z=0.0)
    assert len(world.object_voxels("o")) == 0
    with pytest.raises(NotFound):
        world.object_voxels("missing")
    assert world.labels_of(np.array([FREE]))[0] == FREE_LABEL


# --- free floor -----------------------------------------------------------------------------------------


def test_free_floor_inside_walls_around_obstacles() -> None:
    table = box("t", "table", [2.0, 2.0, 0.0], [3.0, 3.0, 0.75])
    rug = box("r", "rug", [1.0, 3.0, 0.0], [2.0, 4.0, 0.02])  # below the step height: drivable
    lamp = box("l", "lamp", [3.5, 1.0, 1.8], [4.0, 1.5, 2.2])  # above the robot: drivable under
    world = SemanticVoxelWorld(ROOM_GRID, room([table, rug, lamp]), robot=RobotBody(radius=0.2))
    free = world.free_floor

    def cell_free(x: float, y: float) -> bool:
        return bool(world.is_free_floor(np.array([[x, y]]))[0])

    assert cell_free(1.5, 1.5)
    assert cell_free(1.5, 3.5)  # on the rug
    assert cell_free(3.75, 1.25)  # under the lamp
    assert not cell_free(2.5, 2.5)  # under the table
    assert not cell_free(1.95, 2.5)  # 5 cm from the table's edge: the robot's 0.2 m radius
    assert cell_free(1.65, 2.5)  # 35 cm away
    assert not cell_free(0.6, 2.0)  # in a wall
    assert not cell_free(0.85, 2.0)  # 15 cm from the wall
    assert not cell_free(0.2, 0.2) and not cell_free(4.8, 4.8)  # outside the room: no floor
    # Inside the walls (0.7..4.3) less the 0.2 m margin: 3.2 m -> 32 cells a side, less the inflated table
    # (1.0 m + 2 x 0.15 m reach of 0.1 m cells: 14 cells a side, minus the four 0.2 m-radius corners).
    assert free.sum() == 32 * 32 - (14 * 14 - 4)
    assert world.free_floor_area == pytest.approx(free.sum() * 0.01)
    points = world.free_floor_points()
    assert len(points) == free.sum() and np.all(world.is_free_floor(points))


def test_free_floor_keeps_the_largest_connected_region() -> None:
    divider = box("d", "wall", [3.3, 0.5, 0.0], [3.5, 4.5, 2.5])  # splits the room 2.6 m | 0.8 m
    world = SemanticVoxelWorld(ROOM_GRID, room([divider]))
    assert world.is_free_floor(np.array([[2.0, 2.0]]))[0]
    assert not world.is_free_floor(np.array([[3.9, 2.0]]))[0]  # free, but cut off from the larger side


def test_segment_is_free() -> None:
    pillar = box("p", "pillar", [2.3, 2.3, 0.0], [2.7, 2.7, 2.5])
    world = SemanticVoxelWorld(ROOM_GRID, room([pillar]))
    assert world.segment_is_free(np.array([1.2, 1.2]), np.array([3.8, 1.2]))
    assert not world.segment_is_free(np.array([1.2, 2.5]), np.array([3.8, 2.5]))  # through the pillar
    assert world.camera_z == pytest.approx(world.floor_z + world.robot.camera_height)


def test_robot_body_is_validated() -> None:
    with pytest.raises(InvalidInput):
        RobotBody(height=1.0, camera_height=1.2)
    with pytest.raises(InvalidInput):
        RobotBody(radius=-0.1)


# --- scene loaders --------------------------------------------------------------------------------------


def test_scannet_layout_episode_keeps_the_target_in_the_world_only() -> None:
    (scene,) = load_layout_scenes(SIM / "scannet_scene0000_00.jsonl")
    assert (scene.source, scene.scene_id, len(scene.graph.objects)) == ("scannet", "scene0000_00", 67)
    assert "18" in scene.candidate_target_ids  # the backpack
    assert "19" not in scene.candidate_target_ids  # a wall
    episode = scene.episode("18")
    assert episode.target.label == "backpack" and episode.utterance is None
    assert "18" not in {o.id for o in episode.service_graph.objects}
    assert len(episode.service_graph.objects) == 66 and len(episode.scene.objects) == 67
    world = episode.world()
    assert world.grid == VoxelGrid.around(episode.service_graph)  # the service's grid
    assert len(world.object_voxels("18")) > 0
    with pytest.raises(NotFound):
        scene.episode("nope")


def test_synthetic_rooms_load_as_their_own_source(tmp_path: Path) -> None:
    path = tmp_path / "rooms.jsonl"
    write_synthetic_rooms(path, 2, seed=0)
    scenes = load_layout_scenes(path)
    assert [s.source for s in scenes] == ["synthetic", "synthetic"]
    assert [s.graph.regions[0].name for s in scenes] == [r["room"] for r in synthetic_rooms(2, seed=0)]
    assert all(s.candidate_target_ids for s in scenes)


def test_ai2thor_layout_labels_are_words() -> None:
    (scene,) = load_layout_scenes(SIM / "ai2thor_living_rooms_01.jsonl", scene_ids=["living_rooms_01"])
    labels = {o.label for o in scene.graph.objects}
    assert {"floor", "coffee table", "remote control", "armchair"} <= labels
    assert scene.source == "ai2thor"
    with pytest.raises(NotFound):
        load_layout_scenes(SIM / "ai2thor_living_rooms_01.jsonl", scene_ids=["kitchens_00"])


def test_case_episodes_put_the_target_back() -> None:
    sized, unsized = list(episodes_from_cases(SIM / "cases_scene0000_00.jsonl"))
    assert sized.utterance == "I left my backpack next to the bicycle"
    assert (sized.source, sized.scene_id, sized.target.id) == ("scannet", "scene0000_00", "18")
    assert sized.target.size == pytest.approx([0.4783, 0.3533, 0.4626])
    assert sized.target.center == pytest.approx([-1.8682, 0.4251, 0.2189])
    assert sized.target in sized.scene.objects and sized.target not in sized.service_graph.objects
    assert len(sized.scene.objects) == len(sized.service_graph.objects) + 1
    assert unsized.target.id == "target" and tuple(unsized.target.size) == DEFAULT_TARGET_SIZE
    assert len(sized.world().object_voxels("18")) > 0


def test_case_target_id_never_collides() -> None:
    (episode, _) = list(episodes_from_cases(SIM / "cases_scene0000_00.jsonl"))
    graph = episode.service_graph
    clash = graph.model_copy(
        update={"objects": [*graph.objects, box("18", "mug", [0, 0, 0], [0.1, 0.1, 0.1])]}
    )
    case = next(read_cases(SIM / "cases_scene0000_00.jsonl")).model_copy(update={"scene_graph": clash})
    moved = episode_from_case(case)
    assert moved.target.id == "18_1"
    SceneGraph.model_validate(moved.scene.model_dump())  # ids stay unique


def test_vla3d_scenes() -> None:
    (scene,) = load_vla3d_scenes(SIM / "vla3d")
    assert (scene.source, scene.scene_id) == ("vla3d", "scene0010_01")
    assert len(scene.graph.objects) == 59
    assert scene.candidate_target_ids
    episode = scene.episode(scene.candidate_target_ids[0])
    assert len(episode.world().object_voxels(episode.target.id)) > 0


def test_episode_language_says_who_wrote_the_utterance() -> None:
    sized, _ = list(episodes_from_cases(SIM / "cases_scene0000_00.jsonl"))
    assert sized.language == "templated"  # the case builder's template (source scannet)
    for source, language in (("nr3d", "human"), ("scanrefer", "human"), ("sr3d", "templated")):
        assert replace(sized, source=source).language == language
    assert replace(sized, meta={"language": "human"}).language == "human"
    assert replace(sized, utterance=None).language is None
    layout = load_layout_scenes(SIM / "scannet_scene0000_00.jsonl")[0]
    assert layout.episode(layout.candidate_target_ids[0]).language is None
