"""Accuracy and calibration of predicted Gaussians and mixtures over a 3-D target position.

Pure functions over arrays, one equation each:

    error_i = ||mu_i - y_i||_2                                   RMSE = sqrt(mean_i error_i^2)
    NLL_i   = 1/2 (log|Sigma_i| + NEES_i + 3 log 2 pi)           (nats)
    NEES_i  = (y_i - mu_i)^T Sigma_i^-1 (y_i - mu_i)             ANEES = mean_i NEES_i
    mixture NLL = -log [ sum_k w_k N(y; mu_k, Sigma_k) + sum_b v_b U(y; box_b) ]

For a calibrated 3-D Gaussian, NEES ~ chi^2(3), so ANEES = 3; above 3 is overconfident, below 3 is
underconfident. A mean over a few hundred cases of a few dozen rooms is uncertain itself, and cases of one
room err together: `clustered_interval` gives its interval by a bootstrap over rooms.

Highest-density-region coverage checks a whole mixture: the HDR of mass m is
{x : p(x) >= tau_m} with P(p(X) >= tau_m) = m, and a calibrated predictor covers its targets at rate m
(on a uniform box's plateau the level set is split at random to hold exactly m: `hdr_coverage`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from app.grounding.mixture import GaussianMixture, map_box
from app.scene_graph.model import SceneGraph

_LOG_2PI = math.log(2.0 * math.pi)
DEFAULT_MASSES = (0.5, 0.9, 0.95)
#: Log densities closer than this (nats) are one level: a plateau's points agree only to rounding.
_TIE_NATS = 1e-9


def _as_batch(means: np.ndarray, covariances: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, ...]:
    mu = np.asarray(means, dtype=np.float64).reshape(-1, 3)  # (N, 3)
    cov = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)  # (N, 3, 3)
    y = np.asarray(targets, dtype=np.float64).reshape(-1, 3)  # (N, 3)
    if not (len(mu) == len(cov) == len(y)):
        msg = (
            f"means, covariances and targets disagree on the number of cases: {len(mu)}, {len(cov)}, {len(y)}"
        )
        raise ValueError(msg)
    return mu, cov, y


def euclidean_errors(means: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """||mu_i - y_i||_2 per case, metres; shape (N,)."""
    diff = np.asarray(means, dtype=np.float64).reshape(-1, 3) - np.asarray(targets, dtype=np.float64).reshape(
        -1, 3
    )
    errors: np.ndarray = np.linalg.norm(diff, axis=1)
    return errors


def rmse(means: np.ndarray, targets: np.ndarray) -> float:
    """sqrt(mean_i ||mu_i - y_i||^2), metres."""
    errors = euclidean_errors(means, targets)
    return float(np.sqrt(np.mean(errors**2)))


def nees(means: np.ndarray, covariances: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(y_i - mu_i)^T Sigma_i^-1 (y_i - mu_i) per case; shape (N,). Sigma_i must be positive definite."""
    mu, cov, y = _as_batch(means, covariances, targets)
    chol = np.linalg.cholesky(cov)  # (N, 3, 3)
    z = np.linalg.solve(chol, (y - mu)[..., None])[..., 0]  # (N, 3): L^-1 (y - mu)
    squared: np.ndarray = np.sum(z * z, axis=1)
    return squared


def anees(means: np.ndarray, covariances: np.ndarray, targets: np.ndarray) -> float:
    """Mean NEES over the cases; 3 for a calibrated 3-D predictor."""
    return float(np.mean(nees(means, covariances, targets)))


def gaussian_nll(means: np.ndarray, covariances: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """-log N(y_i; mu_i, Sigma_i) = 1/2 (log|Sigma_i| + NEES_i + 3 log 2 pi) per case, nats; shape (N,)."""
    mu, cov, y = _as_batch(means, covariances, targets)
    chol = np.linalg.cholesky(cov)
    log_det = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)  # (N,)
    nll: np.ndarray = 0.5 * (log_det + nees(mu, cov, y) + 3 * _LOG_2PI)
    return nll


def mixture_nll(mixture: GaussianMixture, target: np.ndarray) -> float:
    """-log p(y) of the whole mixture, Gaussians and uniform boxes, nats (+inf where p(y) = 0)."""
    return float(-mixture.logpdf(np.asarray(target, dtype=np.float64).reshape(1, 3))[0])


def hdr_thresholds(
    mixture: GaussianMixture, masses: Sequence[float], rng: np.random.Generator, n_samples: int = 20_000
) -> np.ndarray:
    """Monte Carlo density levels tau_m of the highest-density regions of mass m; shape (len(masses),).

    With x_1..x_S ~ p, tau_m is the (1 - m)-quantile of log p(x_s): a fraction m of the samples (so of the
    probability mass) has density at or above it (more, where p is constant on a set of positive mass: see
    `hdr_coverage`). Returned as log densities.
    """
    return _sampled_levels(mixture, masses, rng, n_samples)[1]


def _sampled_levels(
    mixture: GaussianMixture, masses: Sequence[float], rng: np.random.Generator, n_samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """(log p(x_s) of S draws x_s ~ p, their (1 - m)-quantiles tau_m); shapes (S,) and (len(masses),)."""
    log_density = mixture.logpdf(mixture.sample(n_samples, rng))
    return log_density, np.quantile(log_density, 1.0 - np.asarray(masses, dtype=np.float64))


def hdr_coverage(
    mixture: GaussianMixture,
    targets: np.ndarray,
    rng: np.random.Generator,
    masses: Sequence[float] = DEFAULT_MASSES,
    n_samples: int = 20_000,
) -> np.ndarray:
    """Whether each target lies in the mixture's HDR of mass m; bool (M, len(masses)).

    A density that is constant on a set of positive mass (a uniform box where the Gaussians have vanished)
    puts an atom in the law of p(X): {p >= tau_m} can then hold more than m, so the level set alone would
    over-cover. The HDR of mass m is made exact by randomising on the tie (the "plateau" p = tau_m):

        a_m = P(p(X) > tau_m),   t_m = P(p(X) = tau_m)      (Monte Carlo, from the same draws as tau_m)
        y covered  iff  p(y) > tau_m,  or  p(y) = tau_m and u_y < (m - a_m) / t_m,   u_y ~ U(0, 1)

    so P(covered) = a_m + t_m (m - a_m) / t_m = m for y ~ p. Without ties t_m is about 1/S and the rule is
    p(y) >= tau_m. One u_y per target serves every mass, so the regions stay nested. Densities within
    `_TIE_NATS` of each other count as equal: identical plateaus agree only to rounding. One set of draws
    per call is shared by all `targets` (rows of an (M, 3) array).
    """
    log_density, thresholds = _sampled_levels(mixture, masses, rng, n_samples)  # (S,), (K,)
    tied = np.abs(log_density[:, None] - thresholds[None, :]) <= _TIE_NATS  # (S, K)
    above = np.mean((log_density[:, None] > thresholds[None, :]) & ~tied, axis=0)  # (K,) a_m
    at = np.mean(tied, axis=0)  # (K,) t_m
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(at > 0, np.clip((np.asarray(masses) - above) / at, 0.0, 1.0), 1.0)  # (K,)
    log_p = mixture.logpdf(np.asarray(targets, dtype=np.float64).reshape(-1, 3))  # (M,)
    on_tie = np.abs(log_p[:, None] - thresholds[None, :]) <= _TIE_NATS  # (M, K)
    draw = rng.uniform(size=(len(log_p), 1))  # (M, 1): u_y
    return np.where(on_tie, draw < share[None, :], log_p[:, None] > thresholds[None, :])


def gaussian_summary(means: np.ndarray, covariances: np.ndarray, targets: np.ndarray) -> dict[str, float]:
    """n, RMSE, mean and std of the per-case error, NLL and NEES (ANEES = nees_mean) for one set of cases."""
    errors = euclidean_errors(means, targets)
    nll = gaussian_nll(means, covariances, targets)
    per_case_nees = nees(means, covariances, targets)
    return {
        "n": len(errors),
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "error_mean": float(np.mean(errors)),
        "error_std": float(np.std(errors)),
        "nll_mean": float(np.mean(nll)),
        "nll_std": float(np.std(nll)),
        "anees": float(np.mean(per_case_nees)),
        "nees_std": float(np.std(per_case_nees)),
        "nees_median": float(np.median(per_case_nees)),
    }


def clustered_mean_draws(values: np.ndarray, clusters: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """The mean of `values` over each resample of whole clusters, (R,).

    draws (R, C) holds, per resample, C indices into the C distinct clusters (in `np.unique` order), drawn
    with replacement; resample r's mean is sum_c n_rc S_c / sum_c n_rc N_c, S_c and N_c the sum and count of
    cluster c's values and n_rc the times c was drawn.
    """
    labels, inverse = np.unique(np.asarray(clusters), return_inverse=True)
    sums = np.bincount(inverse, weights=np.asarray(values, dtype=np.float64), minlength=len(labels))  # (C,)
    counts = np.bincount(inverse, minlength=len(labels)).astype(np.float64)  # (C,)
    draws = np.asarray(draws)
    rows = draws + len(labels) * np.arange(len(draws))[:, None]  # (R, C): one bincount for every resample
    picked = np.bincount(rows.ravel(), minlength=draws.size).reshape(draws.shape).astype(np.float64)  # (R, C)
    means: np.ndarray = (picked @ sums) / (picked @ counts)
    return means


def clustered_interval(
    values: Sequence[float] | np.ndarray,
    clusters: Sequence[str] | np.ndarray,
    level: float = 0.9,
    resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float] | None:
    """The percentile bootstrap interval of mean(values) at `level`, resampling whole clusters (rooms).

    Cases of one room share its layout, so their errors are correlated: resampling cases alone would
    pretend each is independent and give too narrow an interval. None with fewer than two clusters.
    Deterministic for a given `seed`.
    """
    values = np.asarray(values, dtype=np.float64)
    n_clusters = len(np.unique(np.asarray(clusters)))
    if n_clusters < 2:
        return None
    draws = np.random.default_rng(seed).integers(0, n_clusters, size=(resamples, n_clusters))
    means = clustered_mean_draws(values, np.asarray(clusters), draws)
    low, high = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(low), float(high)


def no_language_nll(scene_graph: SceneGraph, target: np.ndarray) -> float:
    """-log U(y; map box) = log vol(U) with y inside U (`map_box`), +inf outside: the no-language baseline of
    `vlmap eval static` and of the training report alike."""
    box = map_box(scene_graph)
    return math.log(box.volume) if bool(box.contains(target)[0]) else math.inf
