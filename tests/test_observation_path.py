"""The observation path (label ids -> increments -> look-alike filter -> apply) against references, exactly.

Two references: the path as it was before the one-lookup fast case (`reference_batch`: class of each id,
equation (4) by `fusion.vision_increments`, look-alikes dropped by a boolean mask), and a per-voxel Python
loop that says what the path means (`loop_batch`, `loop_apply`). Increments, indices and the clamped layer
must be bitwise equal; bad batches must raise the same errors with the same messages.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import IncrementBatch, ObservationModel, SensorModel
from app.errors import Conflict, InvalidInput, LimitExceeded
from app.vocabulary import class_key

GRID = VoxelGrid((0.0, 0.0, 0.0), (20, 15, 10), 0.1)
NAMES = ["floor", "backpack", "table", "Back_Pack", "chair", "wall", "rucksack", "sofa"]


def reference_batch(
    model: ObservationModel,
    labels: np.ndarray,
    flat_idx: np.ndarray,
    tp: float | None = None,
    fp: float | None = None,
    max_voxels: int | None = None,
) -> IncrementBatch:
    """`ObservationModel.observation_batch` by its general path, as it was."""
    is_target = model.is_target(labels)
    idx, kept = model.voxel_indices(len(is_target), None, flat_idx, max_voxels)
    tp = model.sensor_model.tp if tp is None else tp
    fp = model.sensor_model.fp if fp is None else fp
    increments = fusion.vision_increments(is_target[kept], tp, fp)
    if model._look_alike_mask is not None:
        explained = model._look_alike_mask[idx]
        if explained.any():
            idx, increments = idx[~explained], increments[~explained]
    return IncrementBatch(idx, increments, int(len(kept) - kept.sum()))


def loop_batch(
    label_map: dict[int, str],
    target: str,
    look_alikes: set[int],
    labels: np.ndarray,
    idx: np.ndarray,
    tp: float,
    fp: float,
) -> tuple[list[int], list[float]]:
    """Equation (4) voxel by voxel."""
    hit, miss = float(np.float32(math.log(tp / fp))), float(np.float32(math.log((1 - tp) / (1 - fp))))
    out_idx: list[int] = []
    out_inc: list[float] = []
    for label, voxel in zip(labels.tolist(), idx.tolist(), strict=True):
        if voxel in look_alikes:
            continue
        out_idx.append(voxel)
        out_inc.append(hit if class_key(label_map[label]) == class_key(target) else miss)
    return out_idx, out_inc


def loop_apply(layer: np.ndarray, idx: list[int], inc: list[float], lo: float, hi: float) -> np.ndarray:
    """Each increment added in float32 in batch order, then the clamp."""
    out = layer.copy()
    for i, v in zip(idx, inc, strict=True):
        out[i] = np.float32(out[i] + np.float32(v))
    clamped: np.ndarray = np.clip(out, np.float32(lo), np.float32(hi))
    return clamped


LABEL_MAPS: dict[int, dict[int, str]] = {}  # id(model) -> the label map it was made from


def random_model(rng: np.random.Generator, n_look_alikes: int, sparse: bool = False) -> ObservationModel:
    ids = rng.choice(70_000 if sparse else 40, size=6, replace=False)
    label_map = {int(i): str(rng.choice(NAMES)) for i in ids}
    label_map[int(rng.choice(ids))] = "backpack"
    look_alikes = rng.choice(GRID.n_voxels, size=n_look_alikes, replace=False) if n_look_alikes else None
    model = ObservationModel(GRID, "backpack", label_map, SensorModel(0.85, 0.1), look_alikes)
    LABEL_MAPS[id(model)] = label_map
    return model


def labels_of(rng: np.random.Generator, model: ObservationModel, m: int, dtype: str) -> np.ndarray:
    ids = np.array(sorted(model._ids.tolist()))
    return ids[rng.integers(0, len(ids), m)].astype(dtype)


def assert_same(got: IncrementBatch, expected: IncrementBatch) -> None:
    assert got.flat_idx.dtype == expected.flat_idx.dtype == np.int64
    assert got.increments.dtype == expected.increments.dtype == fusion.LAYER_DTYPE
    np.testing.assert_array_equal(got.flat_idx, expected.flat_idx)
    np.testing.assert_array_equal(got.increments, expected.increments)
    assert got.n_outside == expected.n_outside


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("n_look_alikes", [0, 1, 5, 300])
def test_random_batches_equal_both_references(seed: int, n_look_alikes: int) -> None:
    rng = np.random.default_rng(seed)
    model = random_model(rng, n_look_alikes)
    dtype = str(rng.choice(["int64", "int32", "uint8", "uint16", "uint32", "uint64"]))
    m = int(rng.integers(1, 3000))
    labels = labels_of(rng, model, m, dtype)
    # Repeated voxels, and look-alike voxels hit several times.
    idx = rng.integers(0, GRID.n_voxels, m) if seed % 2 else rng.integers(0, 50, m)
    if n_look_alikes:
        idx[rng.random(m) < 0.05] = int(model._look_alikes[0])  # type: ignore[index]
    tp, fp = (None, None) if seed % 3 else (0.7, 0.2)
    got = model.observation_batch(labels, flat_idx=idx, tp=tp, fp=fp)
    assert_same(got, reference_batch(model, labels, idx, tp, fp))
    rates = (tp or model.sensor_model.tp, fp or model.sensor_model.fp)
    look_alikes = set() if model._look_alikes is None else set(model._look_alikes.tolist())
    loop_idx, loop_inc = loop_batch(
        LABEL_MAPS[id(model)], "backpack", look_alikes, labels.astype(np.int64), idx, *rates
    )
    assert got.flat_idx.tolist() == loop_idx
    np.testing.assert_array_equal(got.increments, np.array(loop_inc, dtype=np.float32))
    layer = rng.uniform(-9.5, 19.5, GRID.n_voxels).astype(np.float32)
    expected = loop_apply(layer, loop_idx, loop_inc, fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX)
    fusion.apply_increments(layer, got.flat_idx, got.increments, fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX)
    np.testing.assert_array_equal(layer, expected)


def test_a_large_saturating_batch_clamps_the_whole_layer_as_before() -> None:
    """32 M >= N: the whole layer is clamped; repeated hits saturate at VIS_LOG_MAX, misses at VIS_LOG_MIN."""
    rng = np.random.default_rng(5)
    model = random_model(rng, 3)
    m = 4 * GRID.n_voxels
    labels, idx = labels_of(rng, model, m, "uint32"), rng.integers(0, 40, m)
    got = model.observation_batch(labels, flat_idx=idx)
    assert_same(got, reference_batch(model, labels, idx))
    a, b = np.zeros(GRID.n_voxels, np.float32), np.zeros(GRID.n_voxels, np.float32)
    fusion.apply_increments(a, got.flat_idx, got.increments, fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX)
    ref = reference_batch(model, labels, idx)
    np.add.at(b, ref.flat_idx, ref.increments)
    np.testing.assert_array_equal(a, np.clip(b, fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX))
    assert a.max() == fusion.VIS_LOG_MAX or a.min() == fusion.VIS_LOG_MIN


def error_of(call: object) -> tuple[type[Exception], str]:
    try:
        call()  # type: ignore[operator]
    except (InvalidInput, Conflict, LimitExceeded) as exc:
        return type(exc), str(exc)
    msg = "no error"
    raise AssertionError(msg)


@pytest.mark.parametrize(
    "bad",
    [
        np.array([1, 2, 99]),  # above the map's largest id
        np.array([1, 2, 3]),  # a gap inside the dense table
        np.array([1, -1, 2]),  # negative
        np.array([1, 70_000, 2]),  # above the dense table
        np.array([1, 2**64 - 1], dtype=np.uint64),  # -1 as an int64
        np.array([1, 2**63 + 1], dtype=np.uint64),
        np.array([[1, 2]]),  # not flat
        np.array([1.0, 2.0]),  # not integers
    ],
)
def test_ids_outside_the_label_map_raise_as_before(bad: np.ndarray) -> None:
    model = ObservationModel(GRID, "backpack", {1: "backpack", 2: "table", 5: "floor"}, SensorModel())
    idx = np.arange(bad.size)
    got = error_of(lambda: model.observation_batch(bad, flat_idx=idx))
    assert got == error_of(lambda: reference_batch(model, bad, idx))
    assert got[0] is InvalidInput


def test_other_errors_keep_their_order() -> None:
    model = ObservationModel(GRID, "backpack", {1: "backpack", 2: "table"}, SensorModel())
    labels = np.array([1, 2, 1])
    cases: list[tuple[np.ndarray, float | None, float | None, int | None]] = [
        (np.array([0, 1, GRID.n_voxels]), None, None, None),  # a voxel outside the grid
        (np.array([0, 1]), None, None, None),  # lengths differ
        (np.arange(3), None, None, 2),  # over the batch limit
        (np.arange(3), 0.2, 0.3, None),  # rates inverted
        (np.arange(3), 1.0, 0.3, None),
    ]
    for idx, tp, fp, limit in cases:
        got = error_of(
            lambda: model.observation_batch(labels, flat_idx=idx, tp=tp, fp=fp, max_voxels=limit)  # noqa: B023
        )
        assert got == error_of(lambda: reference_batch(model, labels, idx, tp, fp, limit))  # noqa: B023
    bad_labels_and_rates = error_of(
        lambda: model.observation_batch(np.array([7]), flat_idx=np.arange(1), tp=2.0)
    )
    assert "label ids [7]" in bad_labels_and_rates[1]  # labels are checked first, as before
    unknown = ObservationModel(GRID, "", {1: "backpack"}, SensorModel())
    assert error_of(lambda: unknown.observation_batch(np.array([1]), flat_idx=np.arange(1)))[0] is Conflict


@pytest.mark.parametrize("dtype", ["int64", "uint16"])
def test_points_and_voxels_outside_the_grid_are_counted_and_dropped(dtype: str) -> None:
    rng = np.random.default_rng(9)
    model = random_model(rng, 4)
    m = 500
    labels = labels_of(rng, model, m, dtype)
    points = rng.uniform(-0.3, 2.3, (m, 3))
    voxels = rng.integers(-2, 22, (m, 3))
    for where in ({"points": points}, {"voxels": voxels}):
        got = model.observation_batch(labels, **where)
        is_target = model.is_target(labels)
        idx, kept = model.voxel_indices(m, where.get("points"), None, None, where.get("voxels"))
        inc = fusion.vision_increments(is_target[kept], model.sensor_model.tp, model.sensor_model.fp)
        explained = model._look_alike_mask[idx]  # type: ignore[index]
        assert_same(got, IncrementBatch(idx[~explained], inc[~explained], int(m - kept.sum())))
        assert 0 < got.n_outside < m


def test_string_labels_sparse_maps_and_empty_batches_take_the_general_path() -> None:
    rng = np.random.default_rng(4)
    sparse = random_model(rng, 2, sparse=True)
    labels = labels_of(rng, sparse, 800, "int64")
    idx = rng.integers(0, GRID.n_voxels, 800)
    assert_same(sparse.observation_batch(labels, flat_idx=idx), reference_batch(sparse, labels, idx))
    names = ObservationModel(GRID, "backpack", {}, SensorModel())
    got = names.observation_batch(["backpacks", "table"], flat_idx=np.array([3, 4]))
    np.testing.assert_array_equal(
        got.increments, fusion.vision_increments(np.array([True, False]), 0.9, 0.05)
    )
    empty = sparse.observation_batch(np.zeros(0, dtype=np.int64), flat_idx=np.zeros(0, dtype=np.int64))
    assert len(empty.flat_idx) == 0 and len(empty.increments) == 0


def test_rate_overrides_each_get_their_table() -> None:
    model = ObservationModel(GRID, "backpack", {0: "floor", 1: "backpack"}, SensorModel())
    labels, idx = np.array([0, 1, 1]), np.array([5, 6, 7])
    for tp, fp in [(0.9, 0.05), (0.6, 0.4), (0.9, 0.05), *((0.5 + i / 100, 0.1) for i in range(12))]:
        assert_same(
            model.observation_batch(labels, flat_idx=idx, tp=tp, fp=fp),
            reference_batch(model, labels, idx, tp, fp),
        )
    assert len(model._increment_tables) <= 8


def test_label_ids_of_a_dense_map_take_the_one_lookup_path() -> None:
    model = ObservationModel(GRID, "backpack", {0: "floor", 1: "backpack", 4: "table"}, SensorModel())
    for dtype in ("int64", "uint32", "uint8"):
        got = model._id_increments(np.array([0, 1, 4, 1], dtype=dtype), 0.9, 0.05)
        assert got is not None and got.dtype == fusion.LAYER_DTYPE
    for bad in ([0, 2], [0, 5], [-1, 0]):
        assert model._id_increments(np.array(bad), 0.9, 0.05) is None
    assert model._id_increments(np.array([0, 1]), 0.05, 0.9) is None  # invalid rates: the general path raises


@pytest.mark.parametrize("dtype", ["<i8", ">i8", ">i4", "<i2", ">u4", "|u1", "|i1"])
def test_bounds_in_any_byte_order(dtype: str) -> None:
    """Ids and flat indices are bounds-checked in one pass as unsigned integers of their own byte order."""
    model = ObservationModel(GRID, "backpack", {0: "floor", 1: "backpack", 2: "table"}, SensorModel())
    labels, idx = np.array([0, 1, 2, 1], dtype=dtype), np.array([3, 7, 100, 7], dtype=dtype)
    assert_same(model.observation_batch(labels, flat_idx=idx), reference_batch(model, labels, idx))
    cases = [([0, 3, 1, 1], [3, 7, 100, 7])]  # an id not in the map
    if np.iinfo(np.dtype(dtype)).max >= GRID.n_voxels:
        cases.append(([0, 1, 2, 1], [3, 7, GRID.n_voxels, 7]))  # a voxel past the grid
    for bad_labels, bad_idx in cases:
        labels, idx = np.array(bad_labels, dtype=dtype), np.array(bad_idx, dtype=dtype)
        got = error_of(lambda: model.observation_batch(labels, flat_idx=idx))  # noqa: B023
        assert got == error_of(lambda: reference_batch(model, labels, idx))  # noqa: B023
    if np.dtype(dtype).kind == "i":
        for labels, idx in (
            (np.array([0, -1], dtype=dtype), np.array([1, 2], dtype=dtype)),
            (np.array([0, 1], dtype=dtype), np.array([1, -2], dtype=dtype)),
        ):
            got = error_of(lambda: model.observation_batch(labels, flat_idx=idx))  # noqa: B023
            assert got == error_of(lambda: reference_batch(model, labels, idx))  # noqa: B023
