"""The realistic segmenter (`app.sim.perception`): each effect's statistic over many frames matches its
parameter, within a tolerance of 4 standard errors of the sampling (fixed seeds), and the labels of one
object in one frame agree."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.errors import InvalidInput
from app.scene_graph.model import SceneObject
from app.sim.camera import Camera, CameraConfig, Observation, Pose
from app.sim.perception import (
    PerceptionConfig,
    RateCounts,
    Segmenter,
    lookalike_weights,
    misspecify,
    pixels_per_ray,
    propensities,
    recall,
    shape_similarity,
    unmapped_propensity,
)
from app.sim.world import FREE, SemanticVoxelWorld

GRID = VoxelGrid(origin=(-5.0, -5.0, -0.5), shape=(100, 100, 35), voxel_size=0.1)
EYE = Pose(0.0, 0.0, 1.0, yaw=0.0)
BACKPACK = np.array([0.4, 0.3, 0.2])


def box(
    object_id: str, label: str, center: tuple[float, float, float], size: tuple[float, ...]
) -> SceneObject:
    return SceneObject(id=object_id, label=label, center=list(center), size=list(size))


def scene(
    objects: list[SceneObject], config: CameraConfig | None = None
) -> tuple[SemanticVoxelWorld, Observation]:
    world = SemanticVoxelWorld(GRID, objects, floor_z=0.0)
    return world, Camera(config).observe(world, EYE)


def segmenter(
    world: SemanticVoxelWorld, target_label: str = "backpack", seed: int = 0, **params: float
) -> Segmenter:
    config = PerceptionConfig(**params)  # type: ignore[arg-type]
    return Segmenter(config, world, target_label, BACKPACK, CameraConfig(), np.random.default_rng(seed))


def says_t_per_frame(
    seg: Segmenter, observation: Observation, object_index: int, n: int, seed: int
) -> np.ndarray:
    """(n,) whether the object's voxels read the target class, over n frames of the same view."""
    rng = np.random.default_rng(seed)
    mine = observation.owner == object_index
    out = np.empty(n, dtype=bool)
    for k in range(n):
        codes = seg.label_codes(observation, rng)
        out[k] = bool(np.all(seg.names[codes[mine]] == seg.target_label))
    return out


def within(estimate: float, expected: float, n: int) -> bool:
    """|estimate - expected| within 4 binomial standard errors (and 1e-9 for degenerate p)."""
    return abs(estimate - expected) <= 4.0 * math.sqrt(expected * (1 - expected) / n) + 1e-9


# --- the pure parts ----------------------------------------------------------------------------------------


def test_recall_curve() -> None:
    config = PerceptionConfig()
    assert recall(0.0, config) == 0.0
    assert recall(config.half_recall_area_px, config) == pytest.approx(config.max_recall / 2)
    assert recall(96.0**2, config) == pytest.approx(0.9 * config.max_recall)
    # A 10 cm object at 4 m: f = 320 px for 640 px over 90 degrees, 8 x 8 px, found about 1 time in 20.
    assert recall((320 * 0.1 / 4) ** 2, config) == pytest.approx(0.9 * 64 / (64 + 1024))
    areas = np.geomspace(1, 1e6, 50)
    assert np.all(np.diff(recall(areas, config)) > 0)
    steeper = PerceptionConfig(recall_slope=2.0)
    assert recall(256.0, steeper) < recall(256.0, config)


def test_pixels_per_ray() -> None:
    # 640 px over 64 rays across; 2 f tan(30 deg) / 48 = 7.70 px down with f = 320 px.
    assert pixels_per_ray(CameraConfig(), 640) == pytest.approx(
        10 * 2 * 320 * math.tan(math.radians(30)) / 48
    )
    assert pixels_per_ray(CameraConfig(width=128, height=96), 640) == pytest.approx(
        pixels_per_ray(CameraConfig(), 640) / 4
    )


def test_lookalike_weights() -> None:
    assert shape_similarity(np.array([BACKPACK[::-1]]), BACKPACK, math.log(2))[0] == pytest.approx(1.0)
    twice = shape_similarity(np.array([[0.8, 0.3, 0.2]]), BACKPACK, math.log(2))[0]
    assert twice == pytest.approx(math.exp(-1.0))
    labels = ["towel", "wardrobe", "backpacks", "coffee table"]
    sizes = np.array([[0.45, 0.3, 0.2], [1.0, 0.6, 2.0], [0.4, 0.3, 0.2], [1.0, 0.6, 0.4]])
    w = lookalike_weights(labels, sizes, "backpack", BACKPACK, math.log(2))
    assert w[0] > 0.9 and w[1] < 1e-3 and w[2] == 1.0
    # A looser naming of the target's class is a full look-alike whatever its shape.
    assert lookalike_weights(labels, sizes, "table", np.array([2.0, 1.0, 0.8]), math.log(2))[3] == 1.0


def test_misspecification() -> None:
    tp, fp = misspecify(0.5, 0.01, 2.0)
    assert (1 - tp, fp) == pytest.approx((0.25, 0.005))
    assert misspecify(0.5, 0.01, 1.0) == (0.5, 0.01)
    assert PerceptionConfig(true_rates=(0.6, 0.02), misspecification=1.5).sensor_model == pytest.approx(
        (1 - 0.4 / 1.5, 0.02 / 1.5)
    )
    with pytest.raises(InvalidInput, match="need 0 < fp_s < tp_s < 1"):
        misspecify(0.1, 0.5, 1.0)
    with pytest.raises(InvalidInput, match="positive"):
        misspecify(0.5, 0.01, 0.0)
    with pytest.raises(InvalidInput, match="accuracy"):
        PerceptionConfig(accuracy=1.5)


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.8, 1.0])
def test_frame_correlation_matches_its_parameter(rho: float) -> None:
    """Beta-Bernoulli: the intra-class correlation of one object's frames, estimated from the variance of
    per-object frame means, Var = mu (1 - mu) (rho + (1 - rho) / F), is rho."""
    rng = np.random.default_rng(7)
    n_objects, n_frames, mu = 4000, 20, 0.3
    theta = propensities(np.full(n_objects, mu), rho, rng)
    assert theta.mean() == pytest.approx(mu, abs=4 * math.sqrt(mu * (1 - mu) / n_objects))
    frames = rng.random((n_objects, n_frames)) < theta[:, None]
    variance = frames.mean(axis=1).var(ddof=1)
    estimate = (variance / (mu * (1 - mu)) - 1 / n_frames) / (1 - 1 / n_frames)
    # Standard error of the variance of n draws, about sqrt(2 / n) relative, here <= 0.03 in rho.
    assert estimate == pytest.approx(rho, abs=0.05)


# --- effects in a camera frame ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("near", "far", "side_near", "side_far"), [(1.5, 3.0, 0.3, 0.3), (2.0, 2.0, 0.6, 0.2)]
)
def test_recall_falls_with_distance_and_apparent_size(
    near: float, far: float, side_near: float, side_far: float
) -> None:
    """The share of frames in which the target is segmented matches r(A), A its rays x pixels per ray."""
    rates = []
    for distance, side in ((near, side_near), (far, side_far)):
        target = box("t", "backpack", (distance + side / 2, 0.0, 1.0), (side, side, side))
        world, observation = scene([target])
        seg = segmenter(world, accuracy=1.0)  # detected => called T
        index = world.index_of("t")
        codes, areas = seg.frame_objects(observation)
        area = float(areas[list(codes).index(index)])
        assert area == pytest.approx(np.count_nonzero(observation.ray_owner == index) * seg.pixels_per_ray)
        expected = float(recall(area, seg.config))
        n = 1500
        got = says_t_per_frame(seg, observation, index, n, seed=1).mean()
        assert within(got, expected, n), (distance, side, area, got, expected)
        rates.append(got)
    assert rates[0] > rates[1] + 0.1


def test_partial_view_counts_the_visible_area_only() -> None:
    target = box("t", "backpack", (2.2, 0.0, 1.0), (0.4, 0.4, 0.4))
    screen = box("s", "screen", (1.5, 0.15, 1.0), (0.05, 0.3, 1.0))  # hides the target's left half
    _, whole = scene([target])
    world, partial = scene([target, screen])
    index = world.index_of("t")
    rays_whole = np.count_nonzero(
        whole.ray_owner == SemanticVoxelWorld(GRID, [target], floor_z=0.0).index_of("t")
    )
    rays_partial = np.count_nonzero(partial.ray_owner == index)
    assert 0.3 * rays_whole < rays_partial < 0.7 * rays_whole
    seg = segmenter(world, accuracy=1.0)
    expected = float(recall(rays_partial * seg.pixels_per_ray, seg.config))
    got = says_t_per_frame(seg, partial, index, 1500, seed=2).mean()
    assert within(got, expected, 1500)
    assert expected < float(recall(rays_whole * seg.pixels_per_ray, seg.config)) - 0.05


def test_labels_of_one_object_in_one_frame_agree() -> None:
    objects = [
        box("t", "backpack", (2.0, 0.0, 0.6), (0.4, 0.3, 0.2)),
        box("p", "pillow", (2.0, 0.8, 0.6), (0.5, 0.4, 0.2)),
        box("c", "chair", (2.5, -0.8, 0.45), (0.5, 0.5, 0.9)),
        box("w", "wall", (3.4, 0.0, 1.25), (0.1, 4.0, 2.5)),
    ]
    world, observation = scene(objects)
    seg = segmenter(world, speckle=0.0, frame_correlation=0.0)
    rng = np.random.default_rng(3)
    owners = np.unique(observation.owner[observation.owner != FREE])
    assert len(owners) >= 5  # the four boxes and the floor
    mixed = 0
    for _ in range(200):
        labels = seg.labels(observation, rng)
        mixed += sum(len(set(labels[observation.owner == o])) > 1 for o in owners)
        assert set(labels[observation.owner == FREE]) == {"free"}
    assert mixed == 0
    # With speckle, an object's voxels disagree only by the scattered voxels: their share is the rate.
    speckled = segmenter(world, speckle=0.05, max_recall=0.0)  # nothing detected: all "unknown" but speckle
    other = (observation.owner != FREE) & (observation.owner != world.index_of("t"))
    n_other, n_frames = int(other.sum()), 100
    flips = sum(int((speckled.labels(observation, rng)[other] == "backpack").sum()) for _ in range(n_frames))
    assert within(flips / (n_other * n_frames), 0.05, n_other * n_frames)


def test_false_positives_are_whole_lookalike_objects() -> None:
    """A towel (a look-alike of the backpack) is called a backpack whole, in r(A) (1 - a) s w of the frames;
    a wardrobe (nothing like it) almost never, and its voxels mostly by speckle."""
    towel = box("towel", "towel", (2.0, 0.5, 0.6), (0.45, 0.3, 0.2))
    wardrobe = box("wardrobe", "wardrobe", (2.8, -0.6, 1.0), (0.6, 1.0, 2.0))
    world, observation = scene([towel, wardrobe])
    seg = segmenter(world, frame_correlation=0.0)  # theta = mu: frames independent, at the mean rate
    codes, areas = seg.frame_objects(observation)
    config = seg.config
    for name, lookalike in (("towel", True), ("wardrobe", False)):
        index = world.index_of(name)
        area = float(areas[list(codes).index(index)])
        w = float(seg.weights[index])
        assert (w > 0.8) is lookalike and (w < 1e-3) is not lookalike
        expected = float(recall(area, config)) * (1 - config.accuracy) * config.lookalike_share * w
        n = 3000
        got = says_t_per_frame(seg, observation, index, n, seed=4).mean()
        assert within(got, expected, n), (name, got, expected)
    # Per voxel: the towel's false-positive voxels outnumber the (larger) wardrobe's by far.
    rng = np.random.default_rng(5)
    fp = {name: 0 for name in ("towel", "wardrobe")}
    for _ in range(300):
        labels = seg.labels(observation, rng)
        for name in fp:
            fp[name] += int((labels[observation.owner == world.index_of(name)] == "backpack").sum())
    n_towel = np.count_nonzero(observation.owner == world.index_of("towel"))
    n_wardrobe = np.count_nonzero(observation.owner == world.index_of("wardrobe"))
    assert n_wardrobe > n_towel
    assert fp["towel"] / n_towel > 5 * fp["wardrobe"] / n_wardrobe


def test_propensities_are_per_episode() -> None:
    """With rho = 1 an object gets one answer for the whole episode: every frame of it agrees."""
    towel = box("towel", "towel", (2.0, 0.0, 0.6), (0.45, 0.3, 0.2))
    world, observation = scene([towel])
    index = world.index_of("towel")
    per_episode = []
    for seed in range(60):
        seg = segmenter(
            world, seed=seed, frame_correlation=1.0, accuracy=0.0, lookalike_share=1.0, max_recall=1.0
        )
        frames = says_t_per_frame(seg, observation, index, 20, seed=seed)
        detected_and_t = frames.any()
        per_episode.append(detected_and_t)
        if seg.theta[index] == 0.0:
            assert not frames.any()
    # theta ~ Bernoulli(w): some episodes call the towel a backpack, others never do.
    assert 0 < sum(per_episode) < 60


def test_rate_counts() -> None:
    counts = RateCounts()
    counts.count(
        np.array([True, True, False, False]),
        np.array([True, False, True, False]),
        np.array([True, False, False, False]),
    )
    counts.count(np.array([False]), np.array([False]), np.array([False]))
    summary = counts.summary()
    assert summary["tp"] == 0.5 and summary["fp"] == pytest.approx(1 / 3)
    assert summary["precision"] == 0.5 and summary["iou"] == pytest.approx(1 / 3)
    assert summary["target_frames"] == 1 and summary["target_frames_labelled_t_pct"] == 100.0
    assert RateCounts().summary()["tp"] is None


# --- the target the map lacks (1') --------------------------------------------------------------------------


def posterior_by_weighting(mu: float, rho: float, recalls: list[float], n: int = 2_000_000) -> np.ndarray:
    """Slow reference for (1'): prior draws of (1) and their weights prod (1 - r_f theta)."""
    theta = propensities(np.full(n, mu), rho, np.random.default_rng(123))
    weight = np.ones(n)
    for r in recalls:
        weight *= 1.0 - r * theta
    return np.stack([theta, weight])


@pytest.mark.parametrize(
    ("mu", "rho", "recalls"),
    [(0.8, 0.5, [0.9, 0.9, 0.9]), (0.8, 0.2, [0.9] * 4), (0.6, 0.5, [0.3, 0.7, 0.1, 0.8] * 5)],
)
def test_unmapped_propensity_is_the_posterior_given_the_misses(
    mu: float, rho: float, recalls: list[float]
) -> None:
    """The draws' mean and P(theta > 0.5) match the importance-weighted prior's within 4 standard errors."""
    rng = np.random.default_rng(5)
    n = 3000
    draws = np.array([unmapped_propensity(mu, rho, np.array(recalls), rng) for _ in range(n)])
    theta, weight = posterior_by_weighting(mu, rho, recalls)
    mean = float((theta * weight).sum() / weight.sum())
    assert mean < mu - 0.1  # the misses lower it
    sd = math.sqrt(float((weight * (theta - mean) ** 2).sum() / weight.sum()))
    assert abs(draws.mean() - mean) <= 4 * sd / math.sqrt(n) + 1e-3
    high = float((weight * (theta > 0.5)).sum() / weight.sum())
    assert within(float((draws > 0.5).mean()), high, n)


def test_unmapped_propensity_edge_cases() -> None:
    """No view: one draw of (1), the same draw; rho = 0 or a point-mass prior: theta = mu; rho = 1: the
    Bernoulli posterior mu prod(1 - r) / (mu prod(1 - r) + 1 - mu)."""
    a, b = np.random.default_rng(9), np.random.default_rng(9)
    none = np.array([])
    assert unmapped_propensity(0.8, 0.5, none, a) == float(propensities(np.array([0.8]), 0.5, b)[0])
    assert unmapped_propensity(0.8, 0.0, np.array([0.9] * 5), a) == 0.8
    assert unmapped_propensity(1.0, 0.5, np.array([0.9] * 5), a) == 1.0
    rng = np.random.default_rng(3)
    ones = np.mean([unmapped_propensity(0.8, 1.0, np.array([0.5, 0.5]), rng) for _ in range(4000)])
    assert within(float(ones), 0.8 * 0.25 / (0.8 * 0.25 + 0.2), 4000)
    with pytest.raises(InvalidInput, match="mapping_pass"):
        PerceptionConfig(mapping_pass="earlier")


def test_the_target_the_map_lacks_is_labelled_as_often_as_its_posterior_says() -> None:
    """Over many episodes, after a mapping pass of 3 frames that show the target, the share of frames that
    label it T is r(A) E[theta | missed in those frames] (1'), far below r(A) a; a mapped object of its class
    keeps (1); with the mapping pass "none", or frames that do not show the target, nothing is redrawn."""
    target = box("t", "backpack", (2.0, 0.0, 1.0), (0.4, 0.4, 0.4))
    other = box("o", "backpack", (2.0, 1.2, 1.0), (0.4, 0.4, 0.4))
    world, observation = scene([target, other])
    away = Camera().observe(world, Pose(0.0, 0.0, 1.0, yaw=math.pi))  # shows neither
    t, o = world.index_of("t"), world.index_of("o")
    config = PerceptionConfig()
    frames_t, frames_o = [], []
    for seed in range(400):
        seg = Segmenter(config, world, "backpack", BACKPACK, CameraConfig(), np.random.default_rng(seed))
        old = Segmenter(config, world, "backpack", BACKPACK, CameraConfig(), np.random.default_rng(seed))
        seg.miss_while_mapping(t, [observation, away, observation, observation], np.random.default_rng(seed))
        assert seg.theta[o] == old.theta[o]  # the mapped look-alike of its class keeps (1)
        for unchanged, frames in ((PerceptionConfig(mapping_pass="none"), [observation]), (config, [away])):
            rng = np.random.default_rng(seed)
            kept = Segmenter(unchanged, world, "backpack", BACKPACK, CameraConfig(), rng)
            kept.miss_while_mapping(t, frames, np.random.default_rng(seed))
            assert np.array_equal(kept.theta, old.theta)
        frames_t.append(says_t_per_frame(seg, observation, t, 10, seed=seed))
        frames_o.append(says_t_per_frame(seg, observation, o, 10, seed=seed))
    codes, areas = seg.frame_objects(observation)
    r_t = float(recall(float(areas[list(codes).index(t)]), config))
    r_o = float(recall(float(areas[list(codes).index(o)]), config))
    assert np.allclose(seg.view_recalls([observation, away, observation], t), [r_t, r_t])
    theta, weight = posterior_by_weighting(config.accuracy, config.frame_correlation, [r_t] * 3)
    expected_t = r_t * float((theta * weight).sum() / weight.sum())
    got_t, got_o = float(np.mean(frames_t)), float(np.mean(frames_o))
    # Frames of one episode are correlated: the standard error is that of 400 episodes, not 4000 frames.
    assert abs(got_t - expected_t) <= 4 * math.sqrt(expected_t * (1 - expected_t) / 400)
    assert abs(got_o - r_o * config.accuracy) <= 4 * math.sqrt(0.25 / 400)
    assert got_t < got_o - 0.2
