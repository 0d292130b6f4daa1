"""The VL-Map fusion equations, one pure function each.

The target sits in exactly one voxel; its position is a categorical variable t in [N]. Under the
reference's conditional-independence assumption (utterances L_1..L_M and observations Z_1..Z_T are
independent given the target's position) and a uniform prior over voxels,

    bel(t = i)  ∝  P(Z_1:T | t = i) * prod_j p_lang(c_i | L_j)                                       (1)

so the belief is a sum of per-voxel log-weights in two layers,

    bel(t = i) = softmax(lang + vis)_i = exp(lang_i + vis_i) / sum_n exp(lang_n + vis_n).          (2)

The reference writes the same sum per voxel as log-odds l_i = l_i^vis + l_i^lang and reads each voxel
through a sigmoid; here exactly one voxel holds the target, so the two additive layers are normalised
jointly by the softmax (2), and "uniform prior" means 1/N per voxel.

Language layer. Each utterance L_j contributes the language sensor's Gaussian mixture evaluated at the
voxel centre c_i, times the voxel volume V (so p V approximates the probability mass the utterance puts
in voxel i):

    lang_i  +=  log( p_j(c_i) V ),   p_j(x) = sum_h w_h N(x; mu_h, Sigma_h) + sum_b v_b U(x; box_b).  (3)

The uniform boxes are the sensor's broad terms (`app.grounding.mixture`): exactly the density the
sensor serves, so the belief's update is the served mixture's log-likelihood voxel for voxel.

Vision layer. The robot labels voxel i with y (ray-cast semantic labels, the reference's y_{i,tau}). With
the sensor model tp = P(y = target | t = i) and fp = P(y = target | t != i), the likelihood of all labels
given t = i is prod_n P(y_n | t != n) * [P(y_i | t = i) / P(y_i | t != i)]; the product does not depend
on i, so only the ratio at the labelled voxel matters:

    vis_i  +=  log tp/fp                 if y = target class,                                       (4)
    vis_i  +=  log (1 - tp)/(1 - fp)     otherwise;  unobserved voxels are unchanged.

Inside the box of a mapped object of the target's class (a look-alike the scene graph already holds), the
label is explained by that object whether or not the target is there: P(y | t = i) = P(y | t != i), so (4)
adds nothing (`app.belief.session.mapped_look_alikes`).

A detector that outputs p = P(target at i | image) under its own prior pi0 enters through its likelihood
ratio: dividing the posterior odds by the prior odds gives P(image | t = i) / P(image | t != i), so

    vis_i  +=  logit(p) - logit(pi0),   logit(p) = log p/(1 - p)   (pi0 = 1/2: the raw log-odds).   (5)

Clamping (as OctoMap clamps occupancy log-odds) keeps every voxel able to change again:
- vis holds log-likelihood ratios against "not here", so 0 means "no evidence" and the layer is clamped
  to absolute bounds [VIS_LOG_MIN, VIS_LOG_MAX] after each batch (the increments of one batch are summed
  first, because their order inside a batch is arbitrary).
- lang is defined only up to an additive constant (adding c to every voxel leaves (2) unchanged), so
  absolute bounds would mean nothing. After each utterance the layer is shifted so that its maximum is 0
  and clamped below at -LANG_LOG_SPAN: no voxel is ever more than e^LANG_LOG_SPAN times less likely than
  the language's best voxel. The shift also keeps the values small, which is what makes float32 exact
  enough (resolution about 2e-6 nats on [-25, 0]).
- The defaults satisfy VIS_LOG_MAX - VIS_LOG_MIN > LANG_LOG_SPAN: saturated visual evidence (target seen
  here, seen absent at the language's favourite) always overturns the language, however wrong it was.

Layers are float32: the vision kernel is memory bound (random scatter into the layer), so half the bytes
is nearly twice the speed, and a 1 M-voxel session holds 8 MB instead of 16 MB. The clamping above bounds
every value, so float32 keeps about 1e-6 relative precision; sums that span the grid (the posterior's
normaliser, moments, entropy) are taken in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.belief.grid import VoxelGrid
from app.errors import InvalidInput
from app.grounding.mixture import GaussianMixture

#: Data type of both layers (see the module docstring for why float32).
LAYER_DTYPE = np.float32
#: Lower bound of the vision layer (nats): a voxel seen as "not the target" ~5 times with the default
#: sensor model is ruled out by a factor e^-10 ~ 5e-5, and ~4 sightings of the target bring it back to even.
VIS_LOG_MIN = -10.0
#: Upper bound of the vision layer (nats): log(1e6) + 6, so one voxel can still hold >99% of the mass of a
#: 1 M-voxel grid on vision alone, while a later "not here" can pull it down again.
VIS_LOG_MAX = 20.0
#: Largest gap (nats) between the language layer's best voxel and any other voxel.
LANG_LOG_SPAN = 25.0
#: Probabilities from a detector are clipped to [eps, 1 - eps] so that p = 0 or 1 gives a finite increment.
DETECTOR_EPS = 1e-6
#: Voxels evaluated together by `language_log_likelihood` (bounds its temporaries to a few MB).
LANGUAGE_BLOCK_VOXELS = 1 << 16
#: The "energy" (minus the log-term) of a uniform box at a voxel outside it: log 0 as a finite number, so
#: that sums and differences of energies stay free of inf - inf.
_OUTSIDE = 1e30

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class LayerLimits:
    """Clamping bounds of the two layers (nats); see the module docstring."""

    vis_min: float = VIS_LOG_MIN
    vis_max: float = VIS_LOG_MAX
    lang_span: float = LANG_LOG_SPAN

    def __post_init__(self) -> None:
        if not (
            math.isfinite(self.vis_min) and math.isfinite(self.vis_max) and self.vis_min < 0 < self.vis_max
        ):
            msg = f"vision bounds need finite vis_min < 0 < vis_max, got [{self.vis_min}, {self.vis_max}]"
            raise InvalidInput(msg, "limits")
        if not (math.isfinite(self.lang_span) and self.lang_span > 0):
            msg = f"lang_span must be a positive number of nats, got {self.lang_span}"
            raise InvalidInput(msg, "limits.lang_span")


def check_sensor_model(tp: float, fp: float) -> None:
    """Reject rates that make (4) infinite or uninformative-to-inverted: need 0 < fp < tp < 1."""
    if not (0.0 < fp < tp < 1.0):
        msg = f"sensor model needs 0 < fp < tp < 1 (true- and false-positive rates), got tp={tp}, fp={fp}"
        raise InvalidInput(msg, "sensor_model")


def language_log_likelihood(
    grid: VoxelGrid, mixture: GaussianMixture, block_voxels: int = LANGUAGE_BLOCK_VOXELS
) -> np.ndarray:
    """Equation (3)'s increment log(p(c_i) V) at every voxel centre, shape (N,), float64.

    Equal to `mixture.logpdf(grid.centers()) + log V`, computed slab by slab along x without building the
    (N, 3) centre array: with Sigma_h = L_h L_h^T and A_h = L_h^-1 (lower triangular), z = A_h (c - mu_h)
    has z_0 depending on x only, z_1 on (x, y) and only z_2 on all three, so the Mahalanobis term costs
    three full-size operations per component; the log-sum-exp over components is skipped for a single
    term. A uniform box b adds v_b / vol_b on the voxel centres inside it (a separable x, y, z test) and
    nothing elsewhere; a voxel no term reaches gets a finite stand-in for log 0 (`_OUTSIDE`), which the
    language layer's span clamps.
    """
    nx, ny, nz = grid.shape
    xs, ys, zs = (grid.axis_centers(a) for a in range(3))
    keep = mixture.weights > 0
    weights, means, covs = mixture.weights[keep], mixture.means[keep], mixture.covariances[keep]
    box_keep = mixture.box_weights > 0
    box_weights = mixture.box_weights[box_keep]
    lows, highs = mixture.box_lows[box_keep], mixture.box_highs[box_keep]
    log_voxel = math.log(grid.voxel_volume)
    chol = np.linalg.cholesky(covs) if len(weights) else np.zeros((0, 3, 3))  # (K, 3, 3)
    inv_chol = np.linalg.inv(chol) if len(weights) else chol  # (K, 3, 3), lower triangular
    log_norm = (
        np.log(weights)
        - np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)
        - 1.5 * _LOG_2PI
        + log_voxel
    )  # (K,): log w_h - 1/2 log|Sigma_h| - 3/2 log 2pi + log V
    box_log = np.log(box_weights) - np.log(np.prod(highs - lows, axis=1)) + log_voxel  # (B,)
    inside = [
        [(axis >= lows[b, a]) & (axis <= highs[b, a]) for a, axis in enumerate((xs, ys, zs))]
        for b in range(len(box_weights))
    ]
    # With B_h = A_h / sqrt(2), the "energy" e_h = |B_h (c - mu_h)|^2 - log_norm_h is -(log-term of h).
    scaled = inv_chol / math.sqrt(2.0)
    n_terms = len(weights) + len(box_weights)
    out = np.empty(grid.n_voxels)
    slab = max(1, block_voxels // (ny * nz))
    for start in range(0, nx, slab):
        stop = min(nx, start + slab)
        energy = np.empty((n_terms, stop - start, ny, nz))  # (K + B, bx, ny, nz)
        for h, (b, mu) in enumerate(zip(scaled, means, strict=True)):
            dx = (xs[start:stop] - mu[0])[:, None, None]  # (bx, 1, 1)
            dy = (ys - mu[1])[None, :, None]  # (1, ny, 1)
            dz = (zs - mu[2])[None, None, :]  # (1, 1, nz)
            z0 = b[0, 0] * dx
            z1 = b[1, 0] * dx + b[1, 1] * dy  # (bx, ny, 1)
            e = energy[h]
            np.add(b[2, 0] * dx + b[2, 1] * dy, b[2, 2] * dz, out=e)  # z2, (bx, ny, nz)
            np.square(e, out=e)
            e += z0 * z0 + z1 * z1 - log_norm[h]
        for j, (in_x, in_y, in_z) in enumerate(inside):
            mask = in_x[start:stop, None, None] & in_y[None, :, None] & in_z[None, None, :]  # (bx, ny, nz)
            energy[len(weights) + j] = np.where(mask, -box_log[j], _OUTSIDE)
        block = out[start * ny * nz : stop * ny * nz].reshape(stop - start, ny, nz)
        if n_terms == 1:
            np.negative(energy[0], out=block)
            continue
        # log sum_h exp(-e_h) = -e_min + log sum_h exp(e_min - e_h)
        lowest = energy.min(axis=0)  # (bx, ny, nz)
        np.subtract(lowest, energy, out=energy)
        # Terms below e^-50 of the largest change nothing in float64, and exp is ~10x slower where it
        # underflows (arguments below about -745), which far-away voxels reach easily.
        np.maximum(energy, -50.0, out=energy)
        np.exp(energy, out=energy)
        np.log(energy.sum(axis=0), out=block)
        block -= lowest
    return out


def vision_increments(is_target: np.ndarray, tp: float, fp: float) -> np.ndarray:
    """Equation (4): log tp/fp where the label is the target, log (1-tp)/(1-fp) elsewhere; (M,) float32."""
    check_sensor_model(tp, fp)
    hit, miss = math.log(tp / fp), math.log((1.0 - tp) / (1.0 - fp))
    return np.where(np.asarray(is_target, dtype=bool), hit, miss).astype(LAYER_DTYPE)


def detector_increments(p_target: np.ndarray, prior: float = 0.5, eps: float = DETECTOR_EPS) -> np.ndarray:
    """Equation (5): logit(p) - logit(prior), with p clipped to [eps, 1 - eps]; (M,) float32."""
    if not 0.0 < prior < 1.0:
        msg = f"detector prior must lie in (0, 1), got {prior}"
        raise InvalidInput(msg, "prior")
    p = np.asarray(p_target, dtype=np.float64)
    if not np.all((p >= 0) & (p <= 1)):  # also rejects NaN
        msg = "detector probabilities must lie in [0, 1]"
        raise InvalidInput(msg, "p_target")
    p = np.clip(p, eps, 1.0 - eps)
    return (np.log(p / (1.0 - p)) - math.log(prior / (1.0 - prior))).astype(LAYER_DTYPE)


def apply_increments(
    layer: np.ndarray, flat_idx: np.ndarray, increments: np.ndarray, lo: float, hi: float
) -> None:
    """layer[i] = clamp(layer[i] + sum of the batch's increments at i, lo, hi), in place.

    Repeated indices in one batch all count (np.add.at, not fancy-index assignment, which would keep one).
    Clamping follows the whole batch. Untouched voxels already lie in [lo, hi], so clamping the whole layer
    is the same as clamping the touched ones, and cheaper for large batches (a sequential pass costs about
    one thirtieth of a random gather/scatter per voxel).
    """
    if len(flat_idx) == 0:
        return
    np.add.at(layer, flat_idx, increments)
    if 32 * len(flat_idx) >= layer.size:
        np.clip(layer, lo, hi, out=layer)
    else:
        layer[flat_idx] = np.clip(layer[flat_idx], lo, hi)


def apply_language(lang: np.ndarray, log_likelihood: np.ndarray, span: float) -> None:
    """lang = max(lang + log_likelihood - max(lang + log_likelihood), -span), in place (see the docstring)."""
    total = lang.astype(np.float64) + log_likelihood  # float64 so that far-away voxels do not round the mode
    peak = total.max()
    if not np.isfinite(peak):
        msg = "the language likelihood is not finite anywhere on the grid"
        raise InvalidInput(msg, "mixture")
    total -= peak
    np.maximum(total, -span, out=total)
    lang[:] = total


def posterior(lang: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Equation (2): softmax(lang + vis) over all voxels, (N,) float64."""
    s = lang.astype(np.float64) + vis
    s -= s.max()
    p: np.ndarray = np.exp(s)
    p /= p.sum()
    return p
