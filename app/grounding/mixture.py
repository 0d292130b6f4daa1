"""Gaussian mixtures over the target's 3-D position: densities and covariance repair.

The language sensor's output is p(x | L, map) = sum_h w_h N(x; mu_h, Sigma_h)  (the reference's
language-mixture equation), with sum_h w_h = 1 and every Sigma_h symmetric positive definite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Smallest eigenvalue (m^2) any covariance leaves the service with: a 1 cm standard deviation.
MIN_EIGENVALUE_M2 = 1e-4

_LOG_2PI = math.log(2.0 * math.pi)


def project_to_pd(cov: np.ndarray, min_eigenvalue: float = MIN_EIGENVALUE_M2) -> np.ndarray:
    """Nearest symmetric matrix with eigenvalues >= `min_eigenvalue`.

    Sigma' = V diag(max(lambda_i, floor)) V^T with (lambda, V) the eigen-decomposition of (Sigma + Sigma^T)/2.
    The reference repairs foundation-model covariances this way with floor 1e-2 m^2 before Cholesky.
    A stack of matrices (..., 3, 3) is projected matrix by matrix.
    """
    cov = np.asarray(cov, dtype=np.float64)
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    if not np.all(np.isfinite(sym)):
        msg = "covariance holds NaN or infinity"
        raise ValueError(msg)
    eigvals, eigvecs = np.linalg.eigh(sym)
    clipped = np.maximum(eigvals, min_eigenvalue)
    out = (eigvecs * clipped[..., None, :]) @ np.swapaxes(eigvecs, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


@dataclass(frozen=True)
class Gaussian:
    """N(mean, covariance) in the scene graph's frame (metres)."""

    mean: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)

    def logpdf(self, points: np.ndarray) -> np.ndarray:
        """log N(x; mu, Sigma) = -1/2 [ (x-mu)^T Sigma^-1 (x-mu) + log|Sigma| + 3 log 2pi ] for each row x."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))  # (N, 3)
        chol = np.linalg.cholesky(self.covariance)  # (3, 3)
        diff = pts - self.mean  # (N, 3)
        z = np.linalg.solve(chol, diff.T)  # (3, N): L^-1 (x - mu)
        maha = np.sum(z * z, axis=0)  # (N,)
        log_det = 2.0 * np.sum(np.log(np.diag(chol)))
        return -0.5 * (maha + log_det + 3 * _LOG_2PI)


@dataclass(frozen=True)
class GaussianMixture:
    """sum_k w_k N(mu_k, Sigma_k) with weights summing to one."""

    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, 3)
    covariances: np.ndarray  # (K, 3, 3)

    @classmethod
    def from_components(
        cls,
        weights: list[float] | np.ndarray,
        gaussians: list[Gaussian],
        min_eigenvalue: float = MIN_EIGENVALUE_M2,
    ) -> GaussianMixture:
        """Normalise the weights and repair every covariance onto the PD cone."""
        w = np.asarray(weights, dtype=np.float64)
        if len(gaussians) == 0 or w.shape != (len(gaussians),):
            msg = "a mixture needs one non-negative weight per component and at least one component"
            raise ValueError(msg)
        if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            msg = f"mixture weights must be finite, non-negative and not all zero, got {w.tolist()}"
            raise ValueError(msg)
        means = np.stack([np.asarray(g.mean, dtype=np.float64) for g in gaussians])
        covs = np.stack([project_to_pd(g.covariance, min_eigenvalue) for g in gaussians])
        return cls(weights=w / w.sum(), means=means, covariances=covs)

    @property
    def components(self) -> list[Gaussian]:
        return [Gaussian(m, c) for m, c in zip(self.means, self.covariances, strict=True)]

    def component_logpdf(self, points: np.ndarray) -> np.ndarray:
        """log N(x; mu_k, Sigma_k) for each point and component, shape (N, K)."""
        return np.stack([g.logpdf(points) for g in self.components], axis=1)

    def logpdf(self, points: np.ndarray) -> np.ndarray:
        """log sum_k w_k N(x; mu_k, Sigma_k), computed with log-sum-exp for each row x; shape (N,)."""
        with np.errstate(divide="ignore"):
            log_w = np.log(self.weights)  # (K,)
        terms = self.component_logpdf(points) + log_w  # (N, K)
        peak = np.max(terms, axis=1, keepdims=True)
        return (peak + np.log(np.sum(np.exp(terms - peak), axis=1, keepdims=True)))[:, 0]

    def mean(self) -> np.ndarray:
        """E[x] = sum_k w_k mu_k."""
        return self.weights @ self.means

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n draws, shape (n, 3)."""
        counts = rng.multinomial(n, self.weights)
        draws = [
            rng.multivariate_normal(m, c, size=k)
            for m, c, k in zip(self.means, self.covariances, counts, strict=True)
            if k
        ]
        return np.concatenate(draws, axis=0) if draws else np.empty((0, 3))
