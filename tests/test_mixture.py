import numpy as np
import pytest
from scipy.stats import multivariate_normal

from app.grounding.mixture import Gaussian, GaussianMixture, project_to_pd


def test_mixture_logpdf_matches_scipy_sum_of_weighted_densities() -> None:
    rng = np.random.default_rng(0)
    means = rng.normal(size=(3, 3))
    covs = []
    for _ in range(3):
        a = rng.normal(size=(3, 3))
        covs.append(a @ a.T + 0.1 * np.eye(3))
    weights = np.array([0.2, 0.5, 0.3])
    mix = GaussianMixture.from_components(weights, [Gaussian(m, c) for m, c in zip(means, covs, strict=True)])
    points = rng.normal(size=(20, 3)) * 2
    expected = np.log(
        sum(w * multivariate_normal(m, c).pdf(points) for w, m, c in zip(weights, means, covs, strict=True))
    )
    np.testing.assert_allclose(mix.logpdf(points), expected, rtol=1e-10)


def test_far_points_stay_finite_thanks_to_log_sum_exp() -> None:
    mix = GaussianMixture.from_components([1.0], [Gaussian(np.zeros(3), np.eye(3) * 1e-4)])
    value = mix.logpdf(np.array([[100.0, 0.0, 0.0]]))
    assert np.isfinite(value).all()
    assert value[0] < -1e7


def test_weights_are_normalised() -> None:
    mix = GaussianMixture.from_components([2.0, 6.0], [Gaussian(np.zeros(3), np.eye(3))] * 2)
    np.testing.assert_allclose(mix.weights, [0.25, 0.75])


def test_project_to_pd_floors_eigenvalues_and_symmetrises() -> None:
    bad = np.array([[1.0, 2.0, 0.0], [1.5, 1.0, 0.0], [0.0, 0.0, -0.5]])
    fixed = project_to_pd(bad, 1e-2)
    np.testing.assert_allclose(fixed, fixed.T)
    assert np.linalg.eigvalsh(fixed).min() >= 1e-2 - 1e-12
    np.linalg.cholesky(fixed)


def test_project_to_pd_keeps_a_valid_covariance() -> None:
    good = np.diag([0.3, 0.2, 0.1])
    np.testing.assert_allclose(project_to_pd(good), good)


@pytest.mark.parametrize("weights", [[-1.0, 2.0], [0.0, 0.0], [np.nan, 1.0]])
def test_invalid_weights_are_rejected(weights: list[float]) -> None:
    with pytest.raises(ValueError, match="weights"):
        GaussianMixture.from_components(weights, [Gaussian(np.zeros(3), np.eye(3))] * 2)
