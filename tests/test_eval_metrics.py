"""Metric functions against hand-computed values and slow, obviously-correct references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2, multivariate_normal

from app.evaluation.metrics import (
    anees,
    clustered_interval,
    clustered_mean_draws,
    euclidean_errors,
    gaussian_nll,
    gaussian_summary,
    hdr_coverage,
    hdr_thresholds,
    mixture_nll,
    nees,
    rmse,
)
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox

CORRELATED = np.array([[0.5, 0.1, 0.0], [0.1, 0.3, -0.05], [0.0, -0.05, 0.2]])


def test_rmse_and_errors_by_hand():
    means = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    targets = np.array([[3.0, 4.0, 0.0], [1.0, 1.0, 2.0]])
    np.testing.assert_allclose(euclidean_errors(means, targets), [5.0, 1.0])
    assert rmse(means, targets) == pytest.approx(math.sqrt((25.0 + 1.0) / 2.0))


def test_nees_of_a_known_case():
    # Sigma = diag(1, 4, 9), y - mu = (1, 2, 3): each axis contributes one standard deviation squared.
    value = nees(np.zeros(3), np.diag([1.0, 4.0, 9.0]), np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(value, [3.0])


def test_nees_and_nll_match_the_explicit_formulas():
    rng = np.random.default_rng(0)
    means = rng.normal(size=(5, 3))
    covs = np.stack([CORRELATED * (1 + k) for k in range(5)])
    targets = rng.normal(size=(5, 3))
    expected_nees = [
        (y - m) @ np.linalg.inv(c) @ (y - m) for m, c, y in zip(means, covs, targets, strict=True)
    ]
    expected_nll = [
        -multivariate_normal(m, c).logpdf(y) for m, c, y in zip(means, covs, targets, strict=True)
    ]
    np.testing.assert_allclose(nees(means, covs, targets), expected_nees, rtol=1e-10)
    np.testing.assert_allclose(gaussian_nll(means, covs, targets), expected_nll, rtol=1e-10)


def test_anees_of_samples_from_the_predicted_gaussian_is_three():
    rng = np.random.default_rng(1)
    mean = np.array([1.0, -2.0, 0.5])
    targets = rng.multivariate_normal(mean, CORRELATED, size=20_000)
    n = len(targets)
    value = anees(np.tile(mean, (n, 1)), np.tile(CORRELATED, (n, 1, 1)), targets)
    assert value == pytest.approx(3.0, abs=0.1)  # chi^2(3) mean; its std error here is sqrt(6 / n) ~ 0.02
    # An overconfident predictor (covariance 4x too small) reads 4x too high.
    assert anees(np.tile(mean, (n, 1)), np.tile(CORRELATED / 4, (n, 1, 1)), targets) == pytest.approx(
        12.0, abs=0.4
    )


def test_mismatched_lengths_raise():
    with pytest.raises(ValueError, match="number of cases"):
        nees(np.zeros((2, 3)), np.tile(np.eye(3), (3, 1, 1)), np.zeros((2, 3)))


def _mixture() -> GaussianMixture:
    return GaussianMixture.from_components(
        [0.6, 0.4],
        [
            Gaussian(np.array([0.0, 0.0, 0.0]), CORRELATED),
            Gaussian(np.array([2.0, 1.0, 0.5]), 0.5 * np.eye(3)),
        ],
    )


def test_mixture_nll_matches_the_sum_of_component_densities():
    target = np.array([1.0, 0.5, 0.2])
    density = 0.6 * multivariate_normal(np.zeros(3), CORRELATED).pdf(target) + 0.4 * multivariate_normal(
        [2.0, 1.0, 0.5], 0.5 * np.eye(3)
    ).pdf(target)
    assert mixture_nll(_mixture(), target) == pytest.approx(-math.log(density), rel=1e-10)


def test_hdr_coverage_of_samples_from_the_mixture_is_the_nominal_mass():
    rng = np.random.default_rng(2)
    mixture = _mixture()
    targets = mixture.sample(4000, rng)
    covered = hdr_coverage(mixture, targets, rng, masses=(0.5, 0.9, 0.95), n_samples=40_000)
    assert covered.shape == (4000, 3)
    # Binomial std error at n = 4000 is <= 0.008; allow ~4 of them.
    np.testing.assert_allclose(covered.mean(axis=0), [0.5, 0.9, 0.95], atol=0.03)


def test_hdr_of_a_single_gaussian_is_the_chi_square_ellipsoid():
    """For one Gaussian the HDR of mass m is {NEES <= chi2_3.ppf(m)}; compare away from the edge."""
    rng = np.random.default_rng(3)
    gaussian = Gaussian(np.array([0.5, 0.0, 1.0]), CORRELATED)
    mixture = GaussianMixture.from_components([1.0], [gaussian])
    targets = rng.multivariate_normal(gaussian.mean, CORRELATED, size=500)
    per_target_nees = nees(np.tile(gaussian.mean, (500, 1)), np.tile(CORRELATED, (500, 1, 1)), targets)
    masses = (0.5, 0.9)
    covered = hdr_coverage(mixture, targets, rng, masses=masses, n_samples=100_000)
    for k, m in enumerate(masses):
        edge = chi2.ppf(m, df=3)
        clear = np.abs(per_target_nees - edge) > 0.15 * edge  # Monte Carlo thresholds wobble near the edge
        np.testing.assert_array_equal(covered[clear, k], per_target_nees[clear] <= edge)


def test_hdr_thresholds_decrease_with_mass():
    thresholds = hdr_thresholds(_mixture(), (0.5, 0.9, 0.95), np.random.default_rng(4), n_samples=10_000)
    assert thresholds[0] > thresholds[1] > thresholds[2]


def test_gaussian_summary_collects_the_metrics():
    means = np.zeros((2, 3))
    covs = np.tile(np.eye(3), (2, 1, 1))
    targets = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    summary = gaussian_summary(means, covs, targets)
    assert summary["n"] == 2
    assert summary["rmse"] == pytest.approx(math.sqrt(2.5))
    assert summary["anees"] == pytest.approx(2.5)
    assert summary["nll_mean"] == pytest.approx(0.5 * (2.5 + 3 * math.log(2 * math.pi)))


def _with_boxes() -> tuple[GaussianMixture, GaussianMixture]:
    """A Gaussian core under a broad box (30% of the mass, most of it on a plateau), and a box-only prior."""
    box = UniformBox(np.array([-3.0, -3.0, 0.0]), np.array([3.0, 3.0, 2.0]))
    core = GaussianMixture.of(Gaussian(np.array([0.5, 0.0, 1.0]), 0.05 * np.eye(3)))
    only = GaussianMixture.from_components([], [], boxes=[box], box_weights=[1.0])
    return core.with_background(0.3, box), only


@pytest.mark.parametrize("which", [0, 1], ids=["gaussian-and-box", "box-only"])
def test_hdr_coverage_of_a_mixture_with_uniform_boxes_is_the_nominal_mass(which: int) -> None:
    """On a plateau p(X) has an atom: the level set {p >= tau_m} alone would hold more than m."""
    rng = np.random.default_rng(5)
    mixture = _with_boxes()[which]
    masses = (0.5, 0.9, 0.95)
    draws = mixture.logpdf(mixture.sample(20_000, rng))
    assert np.mean(draws == draws.min()) > 0.15  # exact ties beyond the 0.9 and 0.95 levels
    targets = mixture.sample(4000, rng)
    covered = hdr_coverage(mixture, targets, rng, masses=masses, n_samples=40_000)
    # Binomial std error at n = 4000 is <= 0.008 (plus the thresholds' own Monte Carlo error); ~4 of them.
    np.testing.assert_allclose(covered.mean(axis=0), masses, atol=0.035)
    # One uniform draw per target: the regions stay nested, the 0.5 region inside the 0.9 one and so on.
    assert np.all(covered[:, 0] <= covered[:, 1]) and np.all(covered[:, 1] <= covered[:, 2])


def test_hdr_coverage_outside_every_box_and_at_the_peak() -> None:
    mixture, only = _with_boxes()
    rng = np.random.default_rng(6)
    outside = np.array([[10.0, 0.0, 1.0]])  # p(y) = 0
    assert not hdr_coverage(only, outside, rng).any()
    assert not hdr_coverage(mixture, outside, rng).any()
    # The core's mean is the mode, inside the HDR of every mass whatever the plateau does.
    assert hdr_coverage(mixture, np.array([[0.5, 0.0, 1.0]]), rng).all()


# --- the interval of a mean over rooms ------------------------------------------------------------------


def test_clustered_mean_draws_match_concatenating_the_drawn_rooms() -> None:
    rng = np.random.default_rng(3)
    clusters = rng.choice(["r0", "r1", "r2", "r3", "r4"], size=60)
    values = rng.gamma(1.5, 2.0, size=60)
    labels = np.unique(clusters)
    draws = rng.integers(0, len(labels), size=(40, len(labels)))
    slow = [np.mean(np.concatenate([values[clusters == labels[c]] for c in row])) for row in draws]
    np.testing.assert_allclose(clustered_mean_draws(values, clusters, draws), slow, rtol=1e-12)


def test_clustered_interval_of_independent_cases_is_the_normal_one() -> None:
    rng = np.random.default_rng(11)
    values = rng.normal(3.0, 2.0, size=4000)
    low, high = clustered_interval(values, np.arange(len(values)).astype(str))  # type: ignore[misc]
    half = 1.645 * np.std(values) / math.sqrt(len(values))
    assert low < np.mean(values) < high
    assert (high - low) / 2 == pytest.approx(half, rel=0.1)


def test_cases_of_one_room_count_once_and_two_rooms_span_their_means() -> None:
    rng = np.random.default_rng(5)
    rooms = np.repeat([f"room{i}" for i in range(30)], 4)
    values = rng.gamma(1.5, 2.0, size=30)[np.repeat(np.arange(30), 4)]  # every room's cases err alike
    by_room = clustered_interval(values, rooms)
    # Four copies of each room: the same resampled means as one case per room.
    assert by_room == clustered_interval(values[::4], rooms[::4])
    as_cases = clustered_interval(values, np.arange(len(values)).astype(str))
    assert by_room is not None and as_cases is not None
    assert by_room[1] - by_room[0] > 1.5 * (as_cases[1] - as_cases[0])  # about sqrt(4) wider
    two = clustered_interval([1.0, 1.0, 5.0, 5.0, 5.0], ["a", "a", "b", "b", "b"])
    assert two == pytest.approx((1.0, 5.0))  # resamples aa, ab, bb: the 5% and 95% points are the rooms
    assert clustered_interval([1.0, 2.0], ["a", "a"]) is None
