import numpy as np
import pytest
from scipy.stats import multivariate_normal

from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox, map_box, project_to_pd
from app.scene_graph.model import SceneGraph


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


def test_a_covariance_kilometres_wide_and_centimetres_thin_keeps_a_cholesky_factor() -> None:
    """The LSM's region hypothesis in a map 100 km wide: eigenvalues 2e16 and 1e-4 m^2 cannot both stand."""
    turn = np.array([[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]])
    cov = turn @ np.diag([2e16, 1e-6, 1e-6]) @ turn.T
    fixed = project_to_pd(cov)
    np.linalg.cholesky(fixed)
    eigenvalues = np.linalg.eigvalsh(fixed)
    assert eigenvalues[-1] == pytest.approx(2e16) and eigenvalues[0] == pytest.approx(2e16 / 1e12, rel=1e-3)
    # Ordinary covariances keep the absolute floor alone.
    np.testing.assert_allclose(np.linalg.eigvalsh(project_to_pd(np.diag([4.0, 1.0, 1e-6]))), [1e-4, 1.0, 4.0])


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


def test_uniform_boxes_enter_the_density_the_moments_and_the_draws() -> None:
    box = UniformBox(np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.0, 0.5]))
    gaussian = Gaussian(np.array([5.0, 0.0, 0.0]), np.eye(3) * 0.01)
    mix = GaussianMixture.from_components([3.0], [gaussian], boxes=[box], box_weights=[1.0])
    np.testing.assert_allclose([mix.gaussian_mass, mix.box_weights[0]], [0.75, 0.25])
    inside, outside = np.array([[1.0, 0.5, 0.25]]), np.array([[3.0, 0.5, 0.25]])
    np.testing.assert_allclose(
        mix.logpdf(inside), np.log(0.25 / box.volume + 0.75 * np.exp(gaussian.logpdf(inside))), rtol=1e-12
    )
    np.testing.assert_allclose(mix.logpdf(outside), np.log(0.75) + gaussian.logpdf(outside), rtol=1e-12)
    draws = mix.sample(200_000, np.random.default_rng(0))
    np.testing.assert_allclose(draws.mean(axis=0), mix.mean(), atol=0.01)
    np.testing.assert_allclose(np.cov(draws.T), mix.covariance(), atol=0.02)


def test_a_background_keeps_the_density_above_its_share_of_the_uniform_everywhere_in_the_box() -> None:
    box = UniformBox.around(np.array([0.0, 0.0, 0.0]), np.array([4.0, 3.0, 0.0]))
    assert box.size[2] == 0.1  # a flat extent is grown to the minimum side
    sharp = GaussianMixture.from_components([1.0], [Gaussian(np.ones(3), np.eye(3) * 1e-4)])
    served = sharp.with_background(0.02, box)
    corners = np.array(
        [[x, y, z] for x in box.low[:1] for y in box.high[1:2] for z in (box.low[2], box.high[2])]
    )
    assert np.all(served.logpdf(corners) >= np.log(0.02 / box.volume) - 1e-12)
    np.testing.assert_allclose(served.weights.sum() + served.box_weights.sum(), 1.0)
    with pytest.raises(ValueError, match="background"):
        sharp.with_background(1.0, box)


def test_the_map_box_of_a_map_without_objects_is_its_regions() -> None:
    """Where a session's grid lies (`SceneGraph.bounds`), not the unit box at the origin."""
    kitchen = {"id": "k", "name": "kitchen", "center": [10.0, 10.0, 1.25], "size": [4.0, 4.0, 2.5]}
    box = map_box(SceneGraph.model_validate({"regions": [kitchen], "objects": []}))
    assert np.allclose(box.low, [8.0, 8.0, 0.0]) and np.allclose(box.high, [12.0, 12.0, 2.5])
    empty = map_box(SceneGraph.model_validate({"regions": [], "objects": []}))
    assert np.allclose(empty.low, -0.5) and np.allclose(empty.high, 0.5)
