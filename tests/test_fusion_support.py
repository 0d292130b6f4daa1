"""The language term at voxel centres evaluated on each component's support (`fusion.centre_log_likelihood`,
equation (3) on a grid fine against the mixture) against the dense evaluation on every voxel.

The reference is the obviously-correct one: the mixture's float64 log-density at every voxel centre
(`GaussianMixture.logpdf`). The truncated term must equal it within 1e-4 nats,
up to the constant the language layer ignores, on every voxel that can matter (within 2 span of the term's
best voxel, `fusion.centre_log_likelihood`), never exceed it anywhere, and give the same language layer
after `fusion.apply_language`, whatever the prior layer, clamped voxels included.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import BeliefState
from app.errors import InvalidInput
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox

SPAN = fusion.LANG_LOG_SPAN
TOL = 1e-4


def dense_term(grid: VoxelGrid, mixture: GaussianMixture) -> np.ndarray:
    """log(p(c_i) V) at every voxel centre, float64 (-inf where no term reaches)."""
    term = np.asarray(mixture.logpdf(grid.centers()), dtype=np.float64)
    return term + math.log(grid.voxel_volume)


def dense_layer(prior: np.ndarray, term: np.ndarray, span: float) -> np.ndarray:
    """The language layer after the term, in float64 from the dense term."""
    total = prior.astype(np.float64) + term
    layer: np.ndarray = np.maximum(total - total.max(), -span)
    return layer


def random_prior(rng: np.random.Generator, term: np.ndarray, span: float, kind: str) -> np.ndarray:
    """A language layer before the term (max 0, >= -span): flat, random, or the most adversarial one (the
    prior favours exactly where the term is weakest, so that voxels far below the term's best survive)."""
    n = len(term)
    if kind == "flat":
        prior = np.zeros(n)
    elif kind == "random":
        prior = rng.uniform(-span, 0.0, n)
    else:
        finite = np.where(np.isfinite(term), term, -np.inf)
        prior = np.where(finite > finite.max() - span, -span, 0.0)
        prior[rng.random(n) < 0.3] = -span
    prior[int(rng.integers(n))] = 0.0
    return prior.astype(fusion.LAYER_DTYPE)


def check_against_dense(grid: VoxelGrid, mixture: GaussianMixture, span: float = SPAN, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    tol = TOL + 2.0 * span * 2.0**-22  # float32 resolves ~2 span * 2^-23 at the floor of what matters
    got = fusion.centre_log_likelihood(grid, mixture, span)
    assert got.shape == (grid.n_voxels,) and got.dtype == fusion.LAYER_DTYPE
    ref = dense_term(grid, mixture)
    ref = ref - ref.max()
    assert got.max() == 0.0
    matters = ref >= -2.0 * span
    np.testing.assert_allclose(got[matters], ref[matters], rtol=0, atol=tol)
    # Elsewhere (where only density is left out, and float32 sums near their underflow resolve less) the
    # term stays below every voxel that can matter.
    assert np.all(got[~matters] < -2.0 * span + tol)
    for kind in ("flat", "random", "adversarial"):
        prior = random_prior(rng, ref, span, kind)
        expected = dense_layer(prior, ref, span)
        layer = prior.copy()
        fusion.apply_language(layer, got, span)
        np.testing.assert_allclose(layer, expected, rtol=0, atol=tol, err_msg=kind)
        clamped = expected <= -span
        np.testing.assert_array_equal(layer[clamped & (expected < -span)], -span)
        assert np.all((layer == -span) <= (expected < -span + tol)), kind
        assert layer.max() == 0.0 and layer.min() >= -span


def random_grid(rng: np.random.Generator) -> VoxelGrid:
    shape = tuple(int(s) for s in rng.integers(1, 31, 3))
    return VoxelGrid(tuple(rng.uniform(-2, 2, 3)), shape, float(rng.choice([0.05, 0.1, 0.2])))  # type: ignore[arg-type]


def random_covariance(rng: np.random.Generator, scale: float) -> np.ndarray:
    a = rng.normal(size=(3, 3)) * scale
    return a @ a.T + (scale * scale / 50.0) * np.eye(3)


def random_mixture(rng: np.random.Generator, grid: VoxelGrid, n_boxes: int) -> GaussianMixture:
    low, high = grid.min_corner, grid.max_corner
    gaussians = []
    for _ in range(int(rng.integers(1, 7))):
        centre = rng.uniform(low - 0.5, high + 0.5)
        scale = float(np.exp(rng.uniform(np.log(0.02), np.log(3.0))))
        gaussians.append(Gaussian(centre, random_covariance(rng, scale)))
    boxes = []
    for _ in range(n_boxes):
        a, b = rng.uniform(low - 0.5, high + 0.5), rng.uniform(low - 0.5, high + 0.5)
        boxes.append(UniformBox.around(np.minimum(a, b), np.maximum(a, b)))
    weights = np.exp(rng.uniform(-6, 0, len(gaussians)))
    return GaussianMixture.from_components(
        weights, gaussians, boxes=boxes, box_weights=np.exp(rng.uniform(-6, 0, n_boxes))
    )


@pytest.mark.parametrize("seed", range(40))
def test_random_mixtures_on_random_grids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = random_grid(rng)
    check_against_dense(grid, random_mixture(rng, grid, n_boxes=seed % 3), seed=seed)


GRID = VoxelGrid((0.0, 0.0, 0.0), (24, 20, 16), 0.1)
INSIDE = Gaussian(np.array([1.2, 1.0, 0.8]), random_covariance(np.random.default_rng(7), 0.2))


def mix(*gaussians: Gaussian, weights: list[float] | None = None) -> GaussianMixture:
    """The mixture as given: no covariance repair (which would raise tiny eigenvalues to 1e-4 m^2)."""
    w = np.asarray(weights or [1.0] * len(gaussians), dtype=np.float64)
    means = np.stack([g.mean for g in gaussians])
    return GaussianMixture(w / w.sum(), means, np.stack([g.covariance for g in gaussians]))


@pytest.mark.parametrize(
    "mixture",
    [
        mix(Gaussian(np.array([60.0, -40.0, 30.0]), 0.3 * np.eye(3))),  # far outside, alone
        mix(Gaussian(np.array([1.2, 1.0, 40.0]), np.diag([0.1, 0.2, 0.05]))),  # far above, alone
        mix(INSIDE, Gaussian(np.array([60.0, -40.0, 30.0]), 0.3 * np.eye(3))),  # and an inside one
        mix(INSIDE, Gaussian(np.array([3.0, 1.0, 0.8]), 0.05 * np.eye(3)), weights=[1.0, 1e-30]),
        mix(Gaussian(np.array([1.23, 0.97, 0.81]), 1e-6 * np.eye(3))),  # tiny: between voxel centres
        mix(INSIDE, Gaussian(np.array([0.33, 1.51, 0.2]), 1e-5 * np.eye(3))),
        mix(Gaussian(np.array([1.2, 1.0, 0.8]), 1e4 * np.eye(3))),  # huge: nearly flat on the grid
        mix(Gaussian(np.array([100.0, 1.0, 0.8]), np.diag([1e4, 1.0, 1.0]))),  # huge and far
    ],
    ids=["far", "far-above", "far-and-inside", "negligible", "tiny", "tiny-and-inside", "huge", "huge-far"],
)
def test_far_tiny_and_huge_components(mixture: GaussianMixture) -> None:
    check_against_dense(GRID, mixture)


def needle(direction: np.ndarray, thin: float, long: float) -> np.ndarray:
    d = direction / np.linalg.norm(direction)
    return long * long * np.outer(d, d) + thin * thin * (np.eye(3) - np.outer(d, d))


def test_a_needle_between_voxel_centres_takes_the_exact_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """Thin along one diagonal, the voxel nearest the mean is hundreds of nats below the best voxel on the
    needle: the first sum overflows and is made again relative to the exact maximum."""
    calls = []
    peak = fusion._Support.peak

    def counted(self: fusion._Support) -> float:
        calls.append(1)
        return peak(self)

    monkeypatch.setattr(fusion._Support, "peak", counted)
    cov = needle(np.array([0.126, -0.132, 0.640]), thin=3.3e-4, long=0.8)
    mean = np.array([1.313, 1.413, 1.107])
    check_against_dense(GRID, mix(Gaussian(mean, cov)))
    check_against_dense(GRID, mix(Gaussian(mean, cov), INSIDE, weights=[1.0, 1e-12]))
    assert calls


def test_strongly_correlated_covariances() -> None:
    rng = np.random.default_rng(3)
    gaussians = [
        Gaussian(rng.uniform(0.3, 1.5, 3), needle(rng.normal(size=3), thin=t, long=0.8))
        for t in (0.01, 0.03, 0.1)
    ]
    check_against_dense(GRID, mix(*gaussians, weights=[0.2, 0.3, 0.5]))


def test_uniform_boxes_in_closed_form() -> None:
    edge = np.array([0.05, 0.05, 0.05])  # a box side exactly on a row of voxel centres
    boxes = [
        UniformBox(edge, np.array([1.25, 0.85, 0.45])),
        UniformBox(np.array([-5.0, -5.0, -5.0]), np.array([5.0, 5.0, 5.0])),  # wider than the grid
        UniformBox(np.array([10.0, 10.0, 10.0]), np.array([11.0, 11.0, 11.0])),  # outside it
    ]
    for gaussians, weights in (([], []), ([INSIDE], [0.5])):
        mixture = GaussianMixture.from_components(
            weights, gaussians, boxes=boxes, box_weights=[0.2, 0.05, 0.25]
        )
        check_against_dense(GRID, mixture)
    box_only = GaussianMixture.from_components([], [], boxes=boxes[:1], box_weights=[1.0])
    got = fusion.centre_log_likelihood(GRID, box_only)
    inside = boxes[0].contains(GRID.centers())
    assert np.all(got[inside] == 0.0) and np.all(got[~inside] == -np.inf)


def test_a_mixture_that_misses_the_grid_is_refused_by_the_update() -> None:
    outside = GaussianMixture.from_components(
        [], [], boxes=[UniformBox(np.full(3, 10.0), np.full(3, 11.0))], box_weights=[1.0]
    )
    got = fusion.centre_log_likelihood(GRID, outside)
    assert np.all(got == -np.inf)
    belief = BeliefState(GRID)
    with pytest.raises(InvalidInput):
        belief.apply_utterance(outside)
    assert belief.version == 0 and not belief.lang.any()


@pytest.mark.parametrize("span", [3.0, 25.0, 60.0, 300.0, 1e4])  # float32, float64 and log-domain sums
def test_other_spans(span: float) -> None:
    rng = np.random.default_rng(int(span))
    check_against_dense(GRID, random_mixture(rng, GRID, n_boxes=1), span=span, seed=int(span))


def test_spans_that_are_not_positive_numbers_are_refused() -> None:
    mixture = mix(INSIDE)
    for span in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InvalidInput):
            fusion.centre_log_likelihood(GRID, mixture, span)


def test_the_belief_uses_its_own_span() -> None:
    """A layer with a wider span needs a wider support: BeliefState passes its span to the term."""
    limits = fusion.LayerLimits(lang_span=80.0)
    belief = BeliefState(GRID, limits)
    belief.lang[:] = np.where(np.arange(GRID.n_voxels) % 7 == 0, 0.0, -80.0)
    prior = belief.lang.copy()
    mixture = mix(Gaussian(np.array([0.3, 0.3, 0.3]), 0.01 * np.eye(3)))
    belief.apply_utterance(mixture)
    ref = dense_term(GRID, mixture)
    np.testing.assert_allclose(belief.lang, dense_layer(prior, ref - ref.max(), 80.0), atol=TOL)


def test_a_bench_sized_grid() -> None:
    """The 1M-voxel case of bench.fusion_kernel at a quarter of its size per axis... in voxels, not metres:
    same mixture scale on a coarser lattice."""
    rng = np.random.default_rng(11)
    grid = VoxelGrid((0.0, 0.0, 0.0), (40, 40, 40), 0.25)
    gaussians = [Gaussian(rng.uniform(1, 9, 3), random_covariance(rng, 0.2)) for _ in range(5)]
    check_against_dense(grid, mix(*gaussians, weights=list(rng.uniform(0.2, 1.0, 5))))
