"""The VL-Map grid and fusion equations against slow per-voxel loops on tiny grids."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import BeliefState, IncrementBatch, SensorModel, new_session
from app.errors import InvalidInput, LimitExceeded
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox
from app.scene_graph.model import SceneGraph
from app.vocabulary import class_key

GRID = VoxelGrid(origin=(0.1, -0.2, 0.3), shape=(4, 3, 2), voxel_size=0.5)


def loop_centers(grid: VoxelGrid) -> list[tuple[int, np.ndarray]]:
    """(flat index, centre) by nested loops in the documented order (z fastest)."""
    out = []
    nx, ny, nz = grid.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                flat = (i * ny + j) * nz + k
                out.append((flat, np.asarray(grid.origin) + (np.array([i, j, k]) + 0.5) * grid.voxel_size))
    return out


def random_mixture(
    rng: np.random.Generator, k: int, center: np.ndarray, spread: float, scale: float
) -> GaussianMixture:
    gaussians = []
    for _ in range(k):
        a = rng.normal(size=(3, 3)) * scale
        gaussians.append(Gaussian(center + rng.normal(size=3) * spread, a @ a.T + 0.05 * np.eye(3)))
    return GaussianMixture.from_components(rng.uniform(0.2, 1.0, k), gaussians)


def scene(objects: list[dict]) -> SceneGraph:
    return SceneGraph.model_validate({"objects": objects})


# -- grid -----------------------------------------------------------------------------------------------


def test_grid_centres_and_indices_follow_the_documented_layout() -> None:
    centres = GRID.centers()
    for flat, centre in loop_centers(GRID):
        np.testing.assert_allclose(centres[flat], centre)
        assert GRID.ijk_to_flat(GRID.flat_to_ijk(np.array([flat])))[0] == flat
    flat, inside = GRID.locate(centres)
    assert inside.all()
    np.testing.assert_array_equal(flat, np.arange(GRID.n_voxels))
    assert GRID.voxel_volume == pytest.approx(0.125)


def test_locate_marks_points_outside_the_grid() -> None:
    lo, hi = GRID.min_corner, GRID.max_corner
    points = np.array([lo, hi, lo - 1e-9, [np.nan, 0.0, 0.5], (lo + hi) / 2, [lo[0], lo[1], hi[2] - 1e-9]])
    flat, inside = GRID.locate(points)
    assert inside.tolist() == [True, False, False, False, True, True]
    assert flat[0] == 0 and flat[1] == -1 and flat[5] == GRID.ijk_to_flat(np.array([0, 0, 1]))


def test_grid_around_covers_the_scene_with_margin_on_a_voxel_aligned_lattice() -> None:
    sg = scene(
        [
            {"id": "t", "label": "table", "center": [1.03, 2.0, 0.4], "size": [1.2, 0.8, 0.8]},
            {"id": "c", "label": "chair", "center": [-0.5, 0.2, 0.45], "size": [0.5, 0.5, 0.9], "yaw": 0.7},
        ]
    )
    low, high = sg.bounds()
    grid = VoxelGrid.around(sg, voxel_size=0.1, margin=0.5)
    assert np.all(grid.min_corner <= low - 0.5 + 1e-9) and np.all(grid.max_corner >= high + 0.5 - 1e-9)
    assert np.all(grid.max_corner - grid.min_corner < high - low + 1.0 + 0.2 + 1e-9)
    np.testing.assert_allclose(
        np.asarray(grid.origin) / 0.1, np.round(np.asarray(grid.origin) / 0.1), atol=1e-9
    )
    with pytest.raises(LimitExceeded):
        VoxelGrid.around(sg, voxel_size=0.01, max_voxels=10_000)


def test_box_slices_select_exactly_the_centres_inside_the_box() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (10, 8, 6), 0.1)
    low, high = np.array([0.22, 0.15, -1.0]), np.array([0.61, 0.45, 0.33])
    sl = grid.box_slices(low, high)
    mask = np.zeros(grid.shape, dtype=bool)
    mask[sl] = True
    inside = np.all((grid.centers() >= low) & (grid.centers() <= high), axis=1)
    np.testing.assert_array_equal(mask.ravel(), inside)


def test_box_slices_of_a_box_far_beyond_the_grid_select_every_voxel() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (10, 8, 6), 0.1)
    for half in (1e3, 1e18, 1e30):
        sl = grid.box_slices(np.full(3, -half), np.full(3, half))
        assert [(s.start, s.stop) for s in sl] == [(0, 10), (0, 8), (0, 6)]
    beyond = grid.box_slices(np.full(3, 1e30), np.full(3, 2e30))
    assert all(s.start == s.stop for s in beyond)


# -- language -------------------------------------------------------------------------------------------


def loop_term(mixture: GaussianMixture) -> np.ndarray:
    """log(p(c_i) V) voxel by voxel, relative to its best voxel (what `centre_log_likelihood` returns)."""
    term = np.zeros(GRID.n_voxels)
    for flat, centre in loop_centers(GRID):
        term[flat] = float(mixture.logpdf(centre[None, :])[0]) + math.log(GRID.voxel_volume)
    return term - term.max()


def loop_mass(grid: VoxelGrid, mixture: GaussianMixture, k: int) -> np.ndarray:
    """log of each voxel's mass by the midpoint rule on k^3 sub-voxels, voxel by voxel (unnormalised)."""
    offsets = ((np.arange(k) + 0.5) / k - 0.5) * grid.voxel_size
    sub = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 3)
    term = np.zeros(grid.n_voxels)
    for flat, centre in loop_centers(grid):
        density = np.exp(mixture.logpdf(centre + sub))
        term[flat] = math.log(float(density.sum()) * grid.voxel_volume / k**3)
    return term


def test_language_log_likelihood_matches_the_mixture_logpdf_at_each_centre() -> None:
    """Up to the constant the layer ignores, within float32 (tests/test_fusion_support.py: larger grids)."""
    rng = np.random.default_rng(0)
    mixture = random_mixture(rng, 3, np.array([1.0, 0.5, 0.8]), 0.5, 0.3)
    got = fusion.centre_log_likelihood(GRID, mixture)
    np.testing.assert_allclose(got, loop_term(mixture), rtol=0, atol=1e-5)


def test_language_with_one_live_component_matches_the_logpdf() -> None:
    """A zero-weight component is dropped, which leaves the single-component path (no log-sum-exp)."""
    g1, g2 = (
        Gaussian(np.array([0.5, 0.3, 0.9]), np.diag([0.3, 0.2, 0.4])),
        Gaussian(np.ones(3), 0.1 * np.eye(3)),
    )
    mixture = GaussianMixture(
        np.array([1.0, 0.0]), np.stack([g1.mean, g2.mean]), np.stack([g1.covariance, g2.covariance])
    )
    got = fusion.centre_log_likelihood(GRID, mixture)
    np.testing.assert_allclose(got, loop_term(GaussianMixture.of(g1)), rtol=0, atol=1e-5)


def test_utterances_add_up_and_the_posterior_is_their_softmax() -> None:
    rng = np.random.default_rng(1)
    belief = BeliefState(GRID)
    mixtures = [random_mixture(rng, 2, np.array([1.0, 0.5, 0.8]), 0.3, 0.6) for _ in range(3)]
    total = np.zeros(GRID.n_voxels)
    for version, mixture in enumerate(mixtures, start=1):
        assert belief.apply_utterance(mixture) == version
        total += loop_mass(GRID, mixture, fusion.subsamples(GRID, mixture))
    assert total.max() - total.min() < fusion.LANG_LOG_SPAN  # no clamping in this test
    np.testing.assert_allclose(belief.lang, total - total.max(), atol=1e-5)
    assert belief.lang.max() == 0.0
    weights = [math.exp(v) for v in total]
    expected = [w / sum(weights) for w in weights]
    np.testing.assert_allclose(belief.posterior(), expected, rtol=1e-5)


@pytest.mark.parametrize("voxel_size", [0.3, 0.5, 1.0, 2.0])
def test_on_a_coarse_grid_each_reading_keeps_its_mass_wherever_its_mean_lies(voxel_size: float) -> None:
    """Two readings of weight 1/2, sigma 0.12 m, one mean on a voxel centre and one on a voxel corner: the
    centre's density alone gave the first 0.63 of the mass on 0.3 m voxels and all of it on 1 m voxels."""
    n = max(6, round(6.0 / voxel_size))  # both means at least a metre inside the grid
    grid = VoxelGrid(origin=(-1.0, -1.0, -1.0), shape=(n, 3, 3), voxel_size=voxel_size)
    on_centre = grid.centers(np.array([grid.ijk_to_flat(np.array([1, 1, 1]))]))[0]
    on_centre[0] = -1.0 + voxel_size * (math.ceil(1.0 / voxel_size) + 0.5)
    on_corner = np.array(
        [-1.0 + voxel_size * (n - math.ceil(1.0 / voxel_size) - 1), -1.0 + voxel_size, -1.0 + voxel_size]
    )
    covariance = 0.12**2 * np.eye(3)
    mixture = GaussianMixture.from_components(
        [0.5, 0.5], [Gaussian(on_centre, covariance), Gaussian(on_corner, covariance)]
    )
    assert fusion.subsamples(grid, mixture) > 1
    belief = BeliefState(grid)
    belief.apply_utterance(mixture)
    posterior = belief.posterior()
    nearer_the_first = grid.centers()[:, 0] < 0.5 * (on_centre[0] + on_corner[0])
    assert posterior[nearer_the_first].sum() == pytest.approx(0.5, abs=0.01)


def test_a_coarse_grid_sums_the_mass_over_sub_voxels_and_a_fine_one_reads_the_centre() -> None:
    rng = np.random.default_rng(6)
    coarse = VoxelGrid(origin=(-0.4, -0.6, 0.0), shape=(6, 5, 3), voxel_size=0.4)
    tight = random_mixture(rng, 2, np.array([0.6, 0.3, 0.5]), 0.3, 0.05)  # sigma 0.22-0.3 m
    box = UniformBox(np.array([0.1, 0.2, 0.3]), np.array([0.2, 0.6, 0.5]))  # 0.1 m wide
    mixture = GaussianMixture.from_components(
        list(tight.weights / 2),
        [Gaussian(m, c) for m, c in zip(tight.means, tight.covariances, strict=True)],
        boxes=[box],
        box_weights=[0.5],
    )
    k = fusion.subsamples(coarse, mixture)
    assert k == 4  # 0.4 m voxels against a box 0.1 m wide: sub-voxels of 0.1 m
    expected = loop_mass(coarse, mixture, k)
    np.testing.assert_allclose(
        fusion.language_log_likelihood(coarse, mixture), expected - expected.max(), atol=1e-4
    )
    fine = VoxelGrid(origin=(-0.4, -0.6, 0.0), shape=(24, 20, 12), voxel_size=0.1)
    assert fusion.subsamples(fine, mixture) == 1
    # The finer grid is bounded: fewer sub-voxels rather than more memory.
    huge = VoxelGrid(origin=(0.0, 0.0, 0.0), shape=(200, 200, 100), voxel_size=0.4)
    assert fusion.subsamples(huge, mixture) == 1 and huge.n_voxels * 2**3 > fusion.SUBSAMPLED_VOXELS


def test_language_layer_is_clamped_relative_to_its_best_voxel() -> None:
    tight = GaussianMixture.from_components(
        [1.0], [Gaussian(GRID.centers(np.array([0]))[0], 0.01 * np.eye(3))]
    )
    belief = BeliefState(GRID, fusion.LayerLimits(lang_span=6.0))
    belief.apply_utterance(tight)
    raw = fusion.language_log_likelihood(GRID, tight)
    expected = np.maximum(raw - raw.max(), -6.0)
    np.testing.assert_allclose(belief.lang, expected, atol=1e-6)
    assert belief.lang.min() == pytest.approx(-6.0) and belief.lang[0] == 0.0
    # A second utterance elsewhere can still lift a clamped voxel: nothing is ever ruled out for good.
    far = GRID.n_voxels - 1
    belief.apply_utterance(
        GaussianMixture.from_components([1.0], [Gaussian(GRID.centers(np.array([far]))[0], 0.01 * np.eye(3))])
    )
    assert belief.lang[far] > -6.0


def test_bad_mixtures_are_rejected_without_changing_the_belief() -> None:
    belief = BeliefState(GRID)
    nan_mean = GaussianMixture(np.array([1.0]), np.array([[np.nan, 0.0, 0.0]]), np.eye(3)[None])
    not_pd = GaussianMixture(np.array([1.0]), np.zeros((1, 3)), -np.eye(3)[None])
    for mixture in (nan_mean, not_pd):
        with pytest.raises(InvalidInput):
            belief.apply_utterance(mixture)
    assert belief.version == 0 and not belief.lang.any()


# -- vision ---------------------------------------------------------------------------------------------


def test_vision_increments_match_the_sensor_model() -> None:
    is_target = np.array([True, False, True, False, False])
    got = fusion.vision_increments(is_target, tp=0.8, fp=0.1)
    for value, hit in zip(got, is_target, strict=True):
        expected = math.log(0.8 / 0.1) if hit else math.log(0.2 / 0.9)
        assert value == pytest.approx(expected, rel=1e-6)
    for tp, fp in ((0.1, 0.2), (1.0, 0.1), (0.9, 0.0), (0.5, 0.5)):
        with pytest.raises(InvalidInput):
            fusion.vision_increments(is_target, tp=tp, fp=fp)


def test_detector_increments_are_log_likelihood_ratios() -> None:
    p = np.array([0.0, 0.2, 0.5, 0.9, 1.0])
    got = fusion.detector_increments(p, prior=0.1)
    for value, prob in zip(got, p, strict=True):
        q = min(max(prob, fusion.DETECTOR_EPS), 1 - fusion.DETECTOR_EPS)
        assert value == pytest.approx(math.log(q / (1 - q)) - math.log(0.1 / 0.9), rel=1e-6)
    assert fusion.detector_increments(np.array([0.5]))[0] == 0.0
    with pytest.raises(InvalidInput):
        fusion.detector_increments(np.array([1.2]))
    with pytest.raises(InvalidInput):
        fusion.detector_increments(np.array([np.nan]))
    with pytest.raises(InvalidInput):
        fusion.detector_increments(p, prior=1.0)


def naive_apply(layer: np.ndarray, idx: np.ndarray, inc: np.ndarray, lo: float, hi: float) -> np.ndarray:
    out = layer.astype(np.float64).copy()
    sums: dict[int, float] = {}
    for i, v in zip(idx.tolist(), inc.tolist(), strict=True):
        sums[i] = sums.get(i, 0.0) + v
    for i, v in sums.items():
        out[i] = min(max(out[i] + v, lo), hi)
    return out


@pytest.mark.parametrize(("n_voxels", "batch"), [(24, 60), (5000, 40)])  # whole-layer and per-voxel clamping
def test_apply_increments_counts_repeated_indices_and_clamps_after_the_batch(
    n_voxels: int, batch: int
) -> None:
    rng = np.random.default_rng(2)
    layer = rng.uniform(-3, 3, n_voxels).astype(np.float32)
    idx = rng.integers(0, min(n_voxels, 12), batch)  # many repeats
    inc = rng.normal(0, 2, batch).astype(np.float32)
    expected = naive_apply(layer, idx, inc, -4.0, 5.0)
    fusion.apply_increments(layer, idx, inc, -4.0, 5.0)
    np.testing.assert_allclose(layer, expected, atol=1e-5)
    assert layer.min() >= -4.0 and layer.max() <= 5.0


def test_saturated_vision_can_change_again() -> None:
    belief = BeliefState(GRID)
    hit, miss = fusion.vision_increments(np.array([True, False]), 0.9, 0.05)
    idx = np.zeros(30, dtype=np.int64)
    belief.apply_increments(IncrementBatch(idx, np.full(30, hit, dtype=np.float32)))
    assert belief.vis[0] == pytest.approx(fusion.VIS_LOG_MAX)
    belief.apply_increments(IncrementBatch(idx[:3], np.full(3, miss, dtype=np.float32)))
    assert belief.vis[0] == pytest.approx(fusion.VIS_LOG_MAX + 3 * miss, rel=1e-6)
    belief.apply_increments(IncrementBatch(idx, np.full(30, miss, dtype=np.float32)))
    assert belief.vis[0] == pytest.approx(fusion.VIS_LOG_MIN)
    assert belief.version == 3


def test_posterior_is_the_softmax_of_both_layers() -> None:
    rng = np.random.default_rng(3)
    lang = rng.uniform(-20, 0, GRID.n_voxels).astype(np.float32)
    vis = rng.uniform(-10, 20, GRID.n_voxels).astype(np.float32)
    got = fusion.posterior(lang, vis)
    weights = [math.exp(float(a) + float(b)) for a, b in zip(lang, vis, strict=True)]
    np.testing.assert_allclose(got, [w / sum(weights) for w in weights], rtol=1e-9)


def test_the_clamp_defaults_let_vision_overturn_the_language() -> None:
    assert fusion.VIS_LOG_MAX - fusion.VIS_LOG_MIN > fusion.LANG_LOG_SPAN


# -- sessions: labels, points, evidence moving mass ------------------------------------------------------

ROOM = scene(
    [
        {"id": "1", "label": "table", "center": [1.0, 1.0, 0.4], "size": [1.0, 0.8, 0.8]},
        {"id": "2", "label": "Sofa", "center": [3.0, 1.0, 0.4], "size": [2.0, 0.9, 0.8]},
    ]
)


@pytest.mark.parametrize(
    ("a", "b", "same"),
    [
        ("backpack", "Backpacks", True),
        ("Back_Pack", "backpack", True),
        ("rucksack", "backpack", True),
        ("TrashCan", "garbage can", True),
        ("DiningTable", "dining_table", True),
        ("boxes", "box", True),
        ("shelves", "shelf", True),
        ("sofa", "couch", True),
        ("glass", "glasses", True),
        ("cup", "mug", False),
        ("table", "dining table", False),
        ("bus", "bu", False),
    ],
)
def test_class_keys(a: str, b: str, same: bool) -> None:
    assert (class_key(a) == class_key(b)) is same


def test_labels_by_id_and_by_name() -> None:
    session = new_session("r", ROOM, "Backpack", label_map={0: "floor", 3: "back_packs", 7: "table"})
    np.testing.assert_array_equal(
        session.observer.is_target(np.array([0, 3, 7, 3])), [False, True, False, True]
    )
    np.testing.assert_array_equal(
        session.observer.is_target(["backpacks", "Table", "rucksack"]), [True, False, True]
    )
    for bad in ([1], [8], [-1]):
        with pytest.raises(InvalidInput):
            session.observer.is_target(np.array(bad))
    with pytest.raises(InvalidInput):
        new_session("r", ROOM, "backpack", label_map={0: "floor", 1: "table"})
    with pytest.raises(InvalidInput):
        new_session(
            "r", ROOM, "backpack", sensor_model=SensorModel(tp=0.9, fp=0.05), label_map={-1: "backpack"}
        )


def test_observation_batch_from_points_drops_the_outside_ones() -> None:
    session = new_session("r", ROOM, "backpack", sensor_model=SensorModel(tp=0.7, fp=0.2))
    inside = session.grid.centers(np.array([5, 9]))
    points = np.vstack([inside, [[100.0, 0.0, 0.0]]])
    batch = session.observation_batch(["backpack", "table", "backpack"], points=points, tp=0.8, fp=0.1)
    np.testing.assert_array_equal(batch.flat_idx, [5, 9])
    np.testing.assert_allclose(batch.increments, [math.log(8.0), math.log(0.2 / 0.9)], rtol=1e-6)
    assert batch.n_outside == 1
    with pytest.raises(InvalidInput):
        session.observation_batch(["backpack"], points=[[np.inf, 0.0, 0.0]])
    with pytest.raises(InvalidInput):
        session.observation_batch(["backpack"], flat_idx=np.array([session.grid.n_voxels]))
    with pytest.raises(InvalidInput):
        session.observation_batch(["backpack"])
    with pytest.raises(LimitExceeded):
        session.observation_batch(["backpack"] * 3, flat_idx=np.arange(3), max_voxels=2)


def test_vision_moves_mass_towards_a_seen_target_and_away_from_seen_other_things() -> None:
    session = new_session("r", ROOM, "backpack")
    mixture = GaussianMixture.from_components([1.0], [Gaussian(np.array([2.0, 1.0, 0.9]), np.eye(3))])
    session.belief.apply_utterance(mixture)
    before = session.belief.posterior()
    seen_target, seen_other = 17, 40
    batch = session.observation_batch(["backpack", "table"], flat_idx=np.array([seen_target, seen_other]))
    session.belief.apply_increments(batch)
    after = session.belief.posterior()
    assert after[seen_target] > 10 * before[seen_target]
    assert after[seen_other] < 0.2 * before[seen_other]
    unobserved = np.setdiff1d(np.arange(session.grid.n_voxels), [seen_target, seen_other])
    ratio = after[unobserved] / before[unobserved]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)  # unobserved voxels keep their relative odds


def test_language_likelihood_of_a_mixture_with_uniform_boxes_equals_its_logpdf() -> None:
    grid = VoxelGrid(origin=(-1.0, -0.5, 0.0), shape=(23, 17, 9), voxel_size=0.1)
    rng = np.random.default_rng(4)
    gaussians = []
    for _ in range(3):
        a = rng.normal(size=(3, 3)) * 0.3
        gaussians.append(Gaussian(rng.normal(size=3) * 0.5, a @ a.T + 0.01 * np.eye(3)))
    boxes = [
        UniformBox(np.array([-1.2, -0.6, -0.1]), np.array([1.4, 1.3, 1.0])),
        UniformBox.around(np.array([0.0, 0.0, 0.2]), np.array([0.3, 0.2, 0.5])),
    ]
    mixture = GaussianMixture.from_components(
        [0.5, 0.2, 0.1], gaussians, boxes=boxes, box_weights=[0.15, 0.05]
    )
    expected = mixture.logpdf(grid.centers()) + np.log(grid.voxel_volume)
    got = fusion.language_log_likelihood(grid, mixture)
    np.testing.assert_allclose(got, expected - expected.max(), rtol=0, atol=1e-5)


def test_a_box_only_mixture_gives_log_zero_outside_as_a_clampable_number() -> None:
    grid = VoxelGrid(origin=(0.0, 0.0, 0.0), shape=(10, 4, 3), voxel_size=0.1)
    box = UniformBox(np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.4, 0.3]))
    mixture = GaussianMixture.from_components([], [], boxes=[box], box_weights=[1.0])
    got = fusion.language_log_likelihood(grid, mixture)
    inside = box.contains(grid.centers())
    assert np.all(got[inside] == 0.0)  # log(V / vol), relative to the best voxel
    assert np.all(got[~inside] < -1e20)
    lang = np.zeros(grid.n_voxels, dtype=fusion.LAYER_DTYPE)
    fusion.apply_language(lang, got, span=25.0)
    assert np.all(lang[inside] == 0.0) and np.all(lang[~inside] == -25.0)
