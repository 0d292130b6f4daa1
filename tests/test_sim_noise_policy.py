"""The label noise model's rates and the exploration policy's guarantees."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.errors import InvalidInput
from app.scene_graph.model import SceneObject
from app.sim.noise import UNKNOWN_LABEL, LabelNoise
from app.sim.policy import PolicyConfig, trajectory
from app.sim.world import FREE_LABEL, SemanticVoxelWorld

# --- noise ----------------------------------------------------------------------------------------------

N_DRAWS = 200_000


def within(count: int, n: int, p: float, sigmas: float = 5.0) -> bool:
    """Whether count successes of n are consistent with rate p (binomial, `sigmas` standard deviations)."""
    return abs(count - n * p) <= sigmas * math.sqrt(n * p * (1 - p)) + 1


def sample_labels(rng: np.random.Generator) -> np.ndarray:
    """A quarter target class (with spelling variants), half other objects, a quarter free."""
    kinds = np.array(["chair", "Chairs", "table", "lamp", "sofa", "table", FREE_LABEL, FREE_LABEL])
    return kinds[rng.integers(len(kinds), size=N_DRAWS)]


@pytest.mark.parametrize(("tp", "fp", "confusion"), [(0.9, 0.05, 0.05), (0.6, 0.2, 0.3)])
def test_noise_rates_match_the_settings(tp: float, fp: float, confusion: float) -> None:
    noise = LabelNoise(tp=tp, fp=fp, confusion=confusion)
    true = sample_labels(np.random.default_rng(0))
    reported = noise.corrupt(true, "chair", np.random.default_rng(1))
    is_target = np.isin(true, ["chair", "Chairs"])
    says_target = reported == "chair"
    unchanged = reported == true
    objects = ~is_target & (true != FREE_LABEL)
    free = true == FREE_LABEL

    n = int(is_target.sum())
    # A target-class voxel is reported as its own spelling (the true label) with prob. tp.
    assert within(int(unchanged[is_target].sum()), n, tp)
    assert not np.any(np.isin(reported[is_target & ~unchanged], ["chair", "Chairs", FREE_LABEL]))
    assert within(int(says_target[objects].sum()), int(objects.sum()), fp)
    assert within(int(says_target[free].sum()), int(free.sum()), fp)
    confused = objects & ~unchanged & ~says_target
    assert within(int(confused.sum()), int(objects.sum()), confusion)
    assert set(reported[confused]) <= {"table", "lamp", "sofa"}
    assert set(reported[free]) <= {FREE_LABEL, "chair"}
    # Confusions spread over the other classes: each table confusion is a lamp or sofa, about half each.
    tables = confused & (true == "table")
    assert set(reported[tables]) == {"lamp", "sofa"}
    assert within(int((reported[tables] == "lamp").sum()), int(tables.sum()), 0.5)


def test_noise_is_seeded() -> None:
    noise = LabelNoise()
    true = sample_labels(np.random.default_rng(0))[:5000]
    first = noise.corrupt(true, "chair", np.random.default_rng(7))
    np.testing.assert_array_equal(first, noise.corrupt(true, "chair", np.random.default_rng(7)))
    assert np.any(first != noise.corrupt(true, "chair", np.random.default_rng(8)))


def test_noise_vocabulary() -> None:
    noise = LabelNoise(tp=0.5, fp=0.0, confusion=1.0)
    true = np.array(["chair"] * 2000 + ["table"] * 2000)
    reported = noise.corrupt(
        true, "chair", np.random.default_rng(0), vocabulary=["table", "bed", "chair", "free"]
    )
    assert set(reported[:2000]) == {"chair", "table", "bed"}
    assert set(reported[2000:]) == {"bed"}  # always confused, and "bed" is the only other class
    # Nothing else to confuse with: a missed target becomes "unknown", other objects keep their label.
    alone = noise.corrupt(np.array(["chair"] * 200 + [FREE_LABEL]), "chair", np.random.default_rng(0))
    assert set(alone[:200]) == {"chair", UNKNOWN_LABEL} and alone[200] == FREE_LABEL
    single = noise.corrupt(np.array(["table"] * 50), "chair", np.random.default_rng(0))
    assert set(single) == {"table"}


@pytest.mark.parametrize(
    "rates", [{"tp": 1.2}, {"fp": -0.1}, {"fp": 0.6, "confusion": 0.6}, {"tp": math.nan}]
)
def test_noise_rates_are_validated(rates: dict[str, float]) -> None:
    with pytest.raises(InvalidInput):
        LabelNoise(**rates)


# --- policy ---------------------------------------------------------------------------------------------


def box(object_id: str, label: str, low: list[float], high: list[float]) -> SceneObject:
    lo, hi = np.asarray(low), np.asarray(high)
    return SceneObject(id=object_id, label=label, center=((lo + hi) / 2).tolist(), size=(hi - lo).tolist())


@pytest.fixture(scope="module")
def world() -> SemanticVoxelWorld:
    """A 6 m x 4 m room with a table and an L-shaped inner wall."""
    objects = [
        box("floor", "floor", [0.0, 0.0, -0.1], [6.0, 4.0, 0.0]),
        box("ws", "wall", [0.0, 0.0, 0.0], [6.0, 0.2, 2.5]),
        box("wn", "wall", [0.0, 3.8, 0.0], [6.0, 4.0, 2.5]),
        box("ww", "wall", [0.0, 0.0, 0.0], [0.2, 4.0, 2.5]),
        box("we", "wall", [5.8, 0.0, 0.0], [6.0, 4.0, 2.5]),
        box("l1", "wall", [3.0, 1.2, 0.0], [3.2, 3.8, 2.5]),
        box("l2", "wall", [3.0, 1.2, 0.0], [4.5, 1.4, 2.5]),
        box("table", "table", [1.0, 2.2, 0.0], [2.0, 3.0, 0.75]),
    ]
    grid = VoxelGrid(origin=(-0.5, -0.5, -0.5), shape=(70, 50, 35), voxel_size=0.1)
    return SemanticVoxelWorld(grid, objects)


def test_trajectory_stays_on_free_floor(world: SemanticVoxelWorld) -> None:
    config = PolicyConfig(max_step=0.5)
    poses = trajectory(world, 300, np.random.default_rng(3), config)
    assert len(poses) == 300
    xy = np.array([[p.x, p.y] for p in poses])
    assert np.all(world.is_free_floor(xy))
    for a, b in itertools.pairwise(xy):
        assert np.linalg.norm(b - a) <= config.max_step + 1e-9
        assert world.segment_is_free(a, b)
    assert all(
        p.z == pytest.approx(world.camera_z) and p.pitch == pytest.approx(math.radians(-15)) for p in poses
    )
    assert all(-math.pi <= p.yaw < math.pi for p in poses)
    # It explores: both sides of the inner wall, and some turning in place.
    assert np.any(xy[:, 0] < 2.5) and np.any(xy[:, 0] > 3.5)
    assert np.any(np.all(xy[1:] == xy[:-1], axis=1))
    assert len({(round(x, 3), round(y, 3)) for x, y in xy}) > 50


def test_trajectory_is_seeded(world: SemanticVoxelWorld) -> None:
    first = trajectory(world, 80, np.random.default_rng(11))
    assert first == trajectory(world, 80, np.random.default_rng(11))
    assert first != trajectory(world, 80, np.random.default_rng(12))
    assert first[:30] == trajectory(world, 30, np.random.default_rng(11))


def test_trajectory_start_and_errors(world: SemanticVoxelWorld) -> None:
    poses = trajectory(world, 5, np.random.default_rng(0), start=(1.0, 1.0))
    assert (poses[0].x, poses[0].y) == (1.0, 1.0)
    with pytest.raises(InvalidInput):
        trajectory(world, 5, np.random.default_rng(0), start=(1.5, 2.6))  # under the table
    closet = SemanticVoxelWorld(
        VoxelGrid(origin=(0.0, 0.0, -0.5), shape=(10, 10, 30), voxel_size=0.1),
        [
            box("f", "floor", [0.0, 0.0, -0.1], [1.0, 1.0, 0.0]),
            box("c", "cabinet", [0.0, 0.0, 0.0], [1.0, 1.0, 2.0]),
        ],
    )
    with pytest.raises(InvalidInput):
        trajectory(closet, 5, np.random.default_rng(0))
