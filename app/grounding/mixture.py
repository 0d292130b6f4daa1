"""Mixtures over the target's 3-D position: Gaussians plus uniform boxes, densities and covariance repair.

The language sensor's output is the reference's language mixture with a broad term added,

    p(x | L, map) = sum_h w_h N(x; mu_h, Sigma_h) + sum_b v_b U(x; box_b),   sum_h w_h + sum_b v_b = 1,

every Sigma_h symmetric positive definite and U(x; box) = 1[x in box] / vol(box) the uniform density over
an axis-aligned box. The uniform terms carry "I may have misunderstood" and broad priors (a region, the
whole map) exactly: a density that keeps v_b U(x; map box) is never below v_b / vol(map box) inside the map,
which a Gaussian stand-in for the uniform cannot promise at the box's corners.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from app.scene_graph.model import object_corners

if TYPE_CHECKING:
    from app.scene_graph.model import SceneGraph

#: Smallest eigenvalue (m^2) any covariance leaves the service with: a 1 cm standard deviation.
MIN_EIGENVALUE_M2 = 1e-4
#: Largest ratio of a covariance's eigenvalues `project_to_pd` leaves: one Cholesky factors reliably.
MAX_CONDITION = 1e12
#: Smallest side (m) of a uniform box: a flat or empty extent is grown to this about its centre.
MIN_BOX_SIDE = 0.1

_LOG_2PI = math.log(2.0 * math.pi)


def project_to_pd(cov: np.ndarray, min_eigenvalue: float = MIN_EIGENVALUE_M2) -> np.ndarray:
    """Nearest symmetric matrix with eigenvalues >= `min_eigenvalue`.

    Sigma' = V diag(max(lambda_i, floor)) V^T with (lambda, V) the eigen-decomposition of (Sigma + Sigma^T)/2.
    The reference repairs foundation-model covariances this way with floor 1e-2 m^2 before Cholesky. The
    floor is at least MAX_CONDITION-th of the largest eigenvalue: float64 rounding could leave a matrix
    conditioned worse than that (a kilometre-wide map's Gaussian, 1 cm thin) without a Cholesky factor.
    A stack of matrices (..., 3, 3) is projected matrix by matrix.
    """
    cov = np.asarray(cov, dtype=np.float64)
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    if not np.all(np.isfinite(sym)):
        msg = "covariance holds NaN or infinity"
        raise ValueError(msg)
    eigvals, eigvecs = np.linalg.eigh(sym)
    floor = np.maximum(min_eigenvalue, eigvals[..., -1:] / MAX_CONDITION)  # eigh sorts ascending
    clipped = np.maximum(eigvals, floor)
    out = (eigvecs * clipped[..., None, :]) @ np.swapaxes(eigvecs, -1, -2)
    symmetric: np.ndarray = 0.5 * (out + np.swapaxes(out, -1, -2))
    return symmetric


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
        log_density: np.ndarray = -0.5 * (maha + log_det + 3 * _LOG_2PI)
        return log_density


@dataclass(frozen=True)
class UniformBox:
    """U(low, high): the uniform density over an axis-aligned box (metres), 1 / vol inside, 0 outside."""

    low: np.ndarray  # (3,)
    high: np.ndarray  # (3,)

    @classmethod
    def around(cls, low: np.ndarray, high: np.ndarray, min_side: float = MIN_BOX_SIDE) -> UniformBox:
        """The box [low, high] with every side grown to at least `min_side` about its centre."""
        lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        centre, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5 * min_side)
        return cls(centre - half, centre + half)

    @property
    def size(self) -> np.ndarray:
        size: np.ndarray = self.high - self.low  # (3,)
        return size

    @property
    def volume(self) -> float:
        return float(np.prod(self.size))

    @property
    def center(self) -> np.ndarray:
        center: np.ndarray = 0.5 * (self.low + self.high)  # (3,)
        return center

    @property
    def covariance(self) -> np.ndarray:
        """diag(w^2 / 12), the covariance of a uniform over sides w."""
        return np.diag(self.size**2 / 12.0)  # (3, 3)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each row lies in the closed box, (N,)."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        inside: np.ndarray = np.all((pts >= self.low) & (pts <= self.high), axis=1)
        return inside

    def logpdf(self, points: np.ndarray) -> np.ndarray:
        """-log vol inside the box, -inf outside, (N,)."""
        return np.where(self.contains(points), -math.log(self.volume), -np.inf)


def map_box(scene_graph: SceneGraph) -> UniformBox:
    """The map's box: the axis-aligned box enclosing every object's box, each side at least MIN_BOX_SIDE.

    low = min_o min_corner(o), high = max_o max_corner(o) over the objects (the axis-aligned boxes that bound
    their yawed boxes; regions do not count), grown by `UniformBox.around`: the evaluation's no-language
    baseline, and the box meant for the sensor's broad term. A map without objects gets `SceneGraph.bounds`:
    its regions' box (where a session's grid lies), or the unit box at the origin if it has none either.
    """
    if not scene_graph.objects:
        return UniformBox.around(*scene_graph.bounds())
    lows, highs = object_corners(scene_graph.objects)
    return UniformBox.around(lows.min(axis=0), highs.max(axis=0))


def _empty(*shape: int) -> np.ndarray:
    return np.zeros((0, *shape), dtype=np.float64)


@dataclass(frozen=True)
class GaussianMixture:
    """sum_k w_k N(mu_k, Sigma_k) + sum_b v_b U(box_b), with all weights together summing to one.

    Without boxes (`box_weights` empty) it is the plain Gaussian mixture; a mixture may also hold boxes only
    (a broad prior). `weights` are the Gaussians' and `box_weights` the boxes' shares of the mass.
    """

    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, 3)
    covariances: np.ndarray  # (K, 3, 3)
    box_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (B,)
    box_lows: np.ndarray = field(default_factory=lambda: _empty(3))  # (B, 3)
    box_highs: np.ndarray = field(default_factory=lambda: _empty(3))  # (B, 3)

    @classmethod
    def from_components(
        cls,
        weights: list[float] | np.ndarray,
        gaussians: list[Gaussian],
        min_eigenvalue: float = MIN_EIGENVALUE_M2,
        boxes: Sequence[UniformBox] = (),
        box_weights: Sequence[float] | np.ndarray = (),
    ) -> GaussianMixture:
        """Normalise all weights together and repair every covariance onto the PD cone."""
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        v = np.asarray(box_weights, dtype=np.float64).reshape(-1)
        if w.shape != (len(gaussians),) or v.shape != (len(boxes),) or len(gaussians) + len(boxes) == 0:
            msg = "a mixture needs one non-negative weight per component and at least one component"
            raise ValueError(msg)
        every = np.concatenate([w, v])
        if not np.all(np.isfinite(every)) or np.any(every < 0) or every.sum() <= 0:
            msg = f"mixture weights must be finite, non-negative and not all zero, got {every.tolist()}"
            raise ValueError(msg)
        for box in boxes:
            if not (
                np.all(np.isfinite(box.low)) and np.all(np.isfinite(box.high)) and np.all(box.high > box.low)
            ):
                msg = f"a uniform box needs finite corners with high > low, got {box.low} and {box.high}"
                raise ValueError(msg)
        total = every.sum()
        means = (
            np.stack([np.asarray(g.mean, dtype=np.float64) for g in gaussians]) if gaussians else _empty(3)
        )
        covs = (
            project_to_pd(
                np.stack([np.asarray(g.covariance, dtype=np.float64) for g in gaussians]), min_eigenvalue
            )
            if gaussians
            else _empty(3, 3)
        )
        lows = np.stack([np.asarray(b.low, dtype=np.float64) for b in boxes]) if boxes else _empty(3)
        highs = np.stack([np.asarray(b.high, dtype=np.float64) for b in boxes]) if boxes else _empty(3)
        return cls(w / total, means, covs, v / total, lows, highs)

    @classmethod
    def of(cls, gaussian: Gaussian, min_eigenvalue: float = MIN_EIGENVALUE_M2) -> GaussianMixture:
        """The one-component mixture N(mu, Sigma)."""
        return cls.from_components([1.0], [gaussian], min_eigenvalue)

    @classmethod
    def combine(
        cls, weights: Sequence[float] | np.ndarray, parts: Sequence[GaussianMixture]
    ) -> GaussianMixture:
        """sum_h w_h p_h(x) with the w_h normalised: the mixture of mixtures, flattened (no PD repair)."""
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(parts),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            msg = f"mixture weights must be finite, non-negative and not all zero, got {w.tolist()}"
            raise ValueError(msg)
        w = w / w.sum()
        return cls(
            np.concatenate([wh * p.weights for wh, p in zip(w, parts, strict=True)]),
            np.concatenate([p.means for p in parts]),
            np.concatenate([p.covariances for p in parts]),
            np.concatenate([wh * p.box_weights for wh, p in zip(w, parts, strict=True)]),
            np.concatenate([p.box_lows for p in parts]),
            np.concatenate([p.box_highs for p in parts]),
        )

    @property
    def components(self) -> list[Gaussian]:
        return [Gaussian(m, c) for m, c in zip(self.means, self.covariances, strict=True)]

    @property
    def boxes(self) -> list[UniformBox]:
        return [UniformBox(lo, hi) for lo, hi in zip(self.box_lows, self.box_highs, strict=True)]

    @property
    def gaussian_mass(self) -> float:
        """The Gaussians' share of the mass, sum_k w_k (one without boxes)."""
        return float(np.sum(self.weights))

    def with_background(self, weight: float, box: UniformBox) -> GaussianMixture:
        """(1 - weight) p(x) + weight U(x; box): the same mixture with a broad term added."""
        if not 0.0 <= weight < 1.0:
            msg = f"a background weight lies in [0, 1), got {weight}"
            raise ValueError(msg)
        keep = 1.0 - weight
        return GaussianMixture(
            self.weights * keep,
            self.means,
            self.covariances,
            np.append(self.box_weights * keep, weight),
            np.concatenate([self.box_lows, box.low[None]]),
            np.concatenate([self.box_highs, box.high[None]]),
        )

    def component_logpdf(self, points: np.ndarray) -> np.ndarray:
        """log N(x; mu_k, Sigma_k) for each point and Gaussian, shape (N, K)."""
        n = len(np.atleast_2d(points))
        if not len(self.weights):
            return np.zeros((n, 0))
        return np.stack([g.logpdf(points) for g in self.components], axis=1)

    def box_logpdf(self, points: np.ndarray) -> np.ndarray:
        """log U(x; box_b) for each point and box, shape (N, B): -log vol inside, -inf outside."""
        n = len(np.atleast_2d(points))
        if not len(self.box_weights):
            return np.zeros((n, 0))
        return np.stack([b.logpdf(points) for b in self.boxes], axis=1)

    def logpdf(self, points: np.ndarray) -> np.ndarray:
        """log p(x) of the whole mixture, with log-sum-exp over its terms, for each row x; shape (N,)."""
        with np.errstate(divide="ignore"):
            log_w = np.log(np.concatenate([self.weights, self.box_weights]))  # (K + B,)
        terms = np.concatenate([self.component_logpdf(points), self.box_logpdf(points)], axis=1) + log_w
        peak = np.max(terms, axis=1, keepdims=True)  # (N, 1)
        finite = np.where(np.isfinite(peak), peak, 0.0)
        with np.errstate(divide="ignore"):
            log_density: np.ndarray = (
                finite + np.log(np.sum(np.exp(terms - finite), axis=1, keepdims=True))
            )[:, 0]
            return log_density

    def mean(self) -> np.ndarray:
        """E[x] = sum_k w_k mu_k + sum_b v_b c_b (c_b the boxes' centres)."""
        centres = 0.5 * (self.box_lows + self.box_highs)
        mean: np.ndarray = self.weights @ self.means + self.box_weights @ centres
        return mean

    def covariance(self) -> np.ndarray:
        """The moment-matched covariance, E[x x^T] - E[x] E[x]^T over every term, (3, 3)."""
        centres = 0.5 * (self.box_lows + self.box_highs)  # (B, 3)
        box_covs = (
            np.stack([np.diag(s) for s in (self.box_highs - self.box_lows) ** 2 / 12.0])
            if len(self.box_weights)
            else _empty(3, 3)
        )
        second = np.einsum(
            "k,kij->ij", self.weights, self.covariances + np.einsum("ki,kj->kij", self.means, self.means)
        )
        second += np.einsum(
            "b,bij->ij", self.box_weights, box_covs + np.einsum("bi,bj->bij", centres, centres)
        )
        mu = self.mean()
        covariance: np.ndarray = second - np.outer(mu, mu)
        return covariance

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n draws, shape (n, 3)."""
        every = np.concatenate([self.weights, self.box_weights])
        counts = rng.multinomial(n, every / every.sum())
        k = len(self.weights)
        draws = [
            rng.multivariate_normal(m, c, size=c_k)
            for m, c, c_k in zip(self.means, self.covariances, counts[:k], strict=True)
            if c_k
        ]
        draws += [
            rng.uniform(lo, hi, size=(c_b, 3))
            for lo, hi, c_b in zip(self.box_lows, self.box_highs, counts[k:], strict=True)
            if c_b
        ]
        return np.concatenate(draws, axis=0) if draws else np.empty((0, 3))
