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

Language layer. Each utterance L_j contributes the probability mass its mixture puts in voxel i,

    lang_i  +=  log( p_j(c_i) V ),   p_j(x) = sum_h w_h N(x; mu_h, Sigma_h) + sum_b v_b U(x; box_b),  (3)

the density at the voxel centre c_i times the voxel volume V: the mass, to the midpoint rule's accuracy,
while the voxel side s is at most twice the mixture's narrowest scale (the smallest standard deviation of
a Gaussian, half the shortest side of a box). On a coarser grid the centre's density no longer tracks the
mass (a reading whose mean lies on a voxel corner would lose nearly all its weight to one on a centre), so
each voxel is cut into k^3 sub-voxels, k = ceil(s / (2 * narrowest scale)), and its mass is the sum of
theirs: (3) on the finer grid, summed per voxel (`SUBSAMPLED_VOXELS` bounds the finer grid's size).

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
from dataclasses import dataclass, field

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
#: Largest share of the density at a voxel that `language_log_likelihood` may leave out, wherever the voxel
#: can matter to the layer (its log-density is then exact to this many nats).
LANGUAGE_TOLERANCE = 1e-5
#: x-slabs of one Gaussian's support evaluated together (a few hundred kB of temporaries, in cache).
_SLAB_GROUP = 8
#: Most voxels of the finer grid on which a coarse grid's voxel masses are summed (module docstring, (3)):
#: k is lowered to stay within it, trading accuracy for memory (4 bytes a voxel).
SUBSAMPLED_VOXELS = 8_000_000

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
    grid: VoxelGrid, mixture: GaussianMixture, span: float = LANG_LOG_SPAN
) -> np.ndarray:
    """Equation (3)'s increment relative to its best voxel, shape (N,) float32: `centre_log_likelihood`,
    or on a grid coarse against the mixture, the voxels' masses summed over k^3 sub-voxels each (module
    docstring)."""
    k = subsamples(grid, mixture)
    if k == 1:
        return centre_log_likelihood(grid, mixture, span)
    fine = VoxelGrid(
        grid.origin, (grid.shape[0] * k, grid.shape[1] * k, grid.shape[2] * k), grid.voxel_size / k
    )
    sub = centre_log_likelihood(fine, mixture, span).reshape(
        grid.shape[0], k, grid.shape[1], k, grid.shape[2], k
    )
    out = np.empty(grid.shape, dtype=np.float64)
    for start in range(0, grid.shape[0], _SLAB_GROUP):  # (g, k, ny, k, nz, k) in float64 at a time
        block = np.exp(sub[start : start + _SLAB_GROUP].astype(np.float64))  # <= 1: shifted to a maximum of 0
        with np.errstate(divide="ignore"):
            out[start : start + _SLAB_GROUP] = np.log(block.sum(axis=(1, 3, 5)))
    flat = out.reshape(-1)
    peak = float(flat.max())
    if math.isfinite(peak):
        flat -= peak
    return flat.astype(LAYER_DTYPE)


def subsamples(grid: VoxelGrid, mixture: GaussianMixture) -> int:
    """k of equation (3): sub-voxels per axis so that their side is at most twice the mixture's narrowest
    scale, lowered to keep the finer grid within SUBSAMPLED_VOXELS (at least 1)."""
    scales = [math.inf]
    keep = mixture.weights > 0
    if keep.any():
        scales.append(math.sqrt(max(float(np.linalg.eigvalsh(mixture.covariances[keep]).min()), 0.0)))
    sides = (mixture.box_highs - mixture.box_lows)[mixture.box_weights > 0]
    if len(sides):
        scales.append(0.5 * float(sides.min()))
    narrowest = min(scales)
    if not narrowest > 0 or grid.voxel_size <= 2.0 * narrowest:
        return 1
    wanted = math.ceil(grid.voxel_size / (2.0 * narrowest))
    room = int((SUBSAMPLED_VOXELS / grid.n_voxels) ** (1.0 / 3.0))
    return max(1, min(wanted, room))


def centre_log_likelihood(
    grid: VoxelGrid, mixture: GaussianMixture, span: float = LANG_LOG_SPAN
) -> np.ndarray:
    """log(p(c_i) V) - max_j log(p(c_j) V) at every voxel centre, shape (N,) float32, evaluated on the support
    of each term only.

    The language layer is defined up to an additive constant (`apply_language` shifts it), so the term is
    returned with its maximum at 0 and in the layers' float32: values that matter lie within a few times
    `span` of 0, where float32 resolves about 4e-6 nats.

    Which voxels matter. After `apply_language` a voxel is above the floor only if lang_i + ll_i >
    max(lang + ll) - span. The layer holds lang in [-span, 0], so that needs ll_i > max(ll) - 2 span: a voxel
    the prior favours by up to `span` can survive a term up to 2 span below the term's best voxel (an
    utterance that contradicts the earlier ones). Everywhere ll_i >= max(ll) - 2 span the density a term
    leaves out is below LANGUAGE_TOLERANCE of the density kept, so the log-density is exact to 1e-5 there;
    elsewhere the value is -inf or any value below max(ll) - 2 span, all of which the floor clamps alike.

    The support (k-sigma box). With Sigma_h = L_h L_h^T and r the Mahalanobis radius, component h's term is
    w_h N(x) V = exp(log_norm_h - r^2 / 2). Outside the ellipsoid r <= k_h it is below exp(log_norm_h - k_h^2
    / 2), so choosing k_h^2 = 2 (log_norm_h - floor), floor = max(ll) - 2 span - log(n_terms / tolerance),
    bounds everything left out at a voxel by tolerance * exp(max(ll) - 2 span). For the dominant component
    (log_norm_h = max(ll)) with span 25, 5 terms and tolerance 1e-5 that is k = sqrt(2 (50 + 13.1)) = 11.2;
    a component e^d weaker than the best gets k = sqrt(2 (63.1 - d)), none if d >= 63.1. (The mass left
    out, P(chi^2_3 > 126) ~ 1e-26, is not what matters: the per-voxel density is.) max(ll) is bounded from
    below before evaluating anything by each term at the voxel nearest its mean, which can only widen the
    boxes. Each k-sigma box is cut into groups of x-slabs, each evaluated on the (y, z) rectangle bounding
    the ellipsoid's sections there. The uniform boxes are constants on their voxel ranges (closed form).

    Evaluation: with B_h = L_h^-1 / sqrt(2) and z = B_h (c - mu_h), z_0 depends on x only, z_1 on (x, y)
    and z_2 = c_h(x, y) + b_h * (z - mu_z) on all three, so the term is exp(p0 + p1 u + p2 u^2) with
    u = b_h (z - mu_z), p0 = log_norm_h - z_0^2 - z_1^2 - c_h^2 - R, p1 = -2 c_h, p2 = -1: one float64
    matrix product (rows (x, y), columns z, inner dimension 3) per slab group (no cancellation: float64
    keeps 1e-12 where c_h and u are large and opposite, as in strongly correlated covariances), then exp
    in float32 and the sum of all terms as exp(term - R), R the lower bound of max(ll) above, chunk of
    x-slabs by chunk in a float32 buffer that stays in cache (float64 or the log domain for spans beyond ~36
    or ~340 nats), and the chunk's log. Cost: about 9 passes over the evaluated voxels (for the bench's
    5-component mixture on 1M voxels, 0.66M of them) and 3 over the grid, where the dense evaluation made
    about 8 passes over the whole grid per term.
    """
    if not (math.isfinite(span) and span > 0):
        msg = f"the language span must be a positive number of nats, got {span}"
        raise InvalidInput(msg, "limits.lang_span")
    axes = tuple(grid.axis_centers(a) for a in range(3))
    keep = mixture.weights > 0
    weights, means, covs = mixture.weights[keep], mixture.means[keep], mixture.covariances[keep]
    log_voxel = math.log(grid.voxel_volume)
    box_terms: list[
        tuple[tuple[slice, ...], float]
    ] = []  # (voxel ranges, log-term) of each uniform box holding a voxel centre
    for v, low, high in zip(mixture.box_weights, mixture.box_lows, mixture.box_highs, strict=True):
        ranges = tuple(_centre_range(axes[a], low[a], high[a]) for a in range(3))
        if v > 0 and all(r.stop > r.start for r in ranges):
            box_terms.append((ranges, math.log(v) - math.log(float(np.prod(high - low))) + log_voxel))
    n_terms = len(weights) + len(box_terms)
    if n_terms == 0:
        return np.full(grid.n_voxels, -np.inf, dtype=LAYER_DTYPE)
    margin = 2.0 * span + math.log(n_terms / LANGUAGE_TOLERANCE)
    chol = np.linalg.cholesky(covs) if len(weights) else np.zeros((0, 3, 3))  # (K, 3, 3)
    scaled = (np.linalg.inv(chol) if len(weights) else chol) / math.sqrt(2.0)  # B_h, lower triangular
    log_norm = (
        np.log(weights)
        - np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)
        - 1.5 * _LOG_2PI
        + log_voxel
    )  # (K,): log w_h - 1/2 log|Sigma_h| - 3/2 log 2pi + log V
    # A lower bound of max(ll): every term at the voxel nearest its mean, every box's value.
    origin, shape = np.asarray(grid.origin), np.asarray(grid.shape)
    nearest = (
        origin + (np.clip(np.floor((means - origin) / grid.voxel_size), 0, shape - 1) + 0.5) * grid.voxel_size
    )
    z = np.einsum("hij,hj->hi", scaled, nearest - means)
    lower = max([*(log_norm - np.sum(z * z, axis=1)).tolist(), *(value for _, value in box_terms)])
    supports = [
        s
        for h in range(len(weights))
        if (
            s := _component_support(
                grid, axes, means[h], covs[h], scaled[h], float(log_norm[h]), lower - margin
            )
        )
    ]
    # Terms relative to R are summed as exp(term - R): exp(-margin), the smallest that counts, is a normal
    # float32 up to margin ~87 and a normal float64 up to ~708; beyond (spans over ~340 nats) the sum is
    # taken in the log domain.
    mode = "float32" if margin <= 80.0 else "float64" if margin <= 700.0 else "log"
    # R = `lower` first: nothing that counts underflows, and nothing overflows unless `lower` is more than
    # ~88 nats below some evaluated voxel (a needle-thin covariance between voxel centres); then R is the
    # terms' exact maximum on their supports and the sum is made again.
    with np.errstate(over="ignore"):
        flat = _sum_of_terms(grid, supports, box_terms, lower, margin, mode).reshape(-1)
    peak = float(flat.max())
    if not math.isfinite(peak):
        exact = max([s.peak() for s in supports] + [value for _, value in box_terms])
        flat = _sum_of_terms(grid, supports, box_terms, exact, margin, mode).reshape(-1)
        peak = float(flat.max())
    if math.isfinite(peak):
        flat -= flat.dtype.type(peak)
    return flat.astype(LAYER_DTYPE, copy=False)


def _sum_of_terms(
    grid: VoxelGrid,
    supports: list[_Support],
    box_terms: list[tuple[tuple[slice, ...], float]],
    reference: float,
    margin: float,
    mode: str,
) -> np.ndarray:
    """log sum_h exp(term_h - reference) over the terms, each on its support, grid-shaped (-inf where no
    term reaches). The sum is made x-chunk by x-chunk (_SLAB_GROUP slabs, a few hundred kB) in a buffer
    that stays in cache while every term adds its part; "float32" and "float64" sum exp(term - reference)
    and take the log per chunk, "log" sums by logaddexp."""
    log = mode == "log"
    dtype = LAYER_DTYPE if mode == "float32" else np.float64
    nx = grid.shape[0]
    out = np.empty(grid.shape, dtype=dtype)
    chunk = np.empty((_SLAB_GROUP, *grid.shape[1:]), dtype=dtype)
    size = max((s.largest_group for s in supports), default=0)
    work64, work = np.empty(size), np.empty(size, dtype=dtype)
    parts: dict[int, list[tuple[_Support, tuple[slice, slice, slice]]]] = {}
    for s in supports:
        s.prepare(reference)
        for group in s.groups:
            parts.setdefault((s.box[0].start + group[0].start) // _SLAB_GROUP, []).append((s, group))
    for c, x0 in enumerate(range(0, nx, _SLAB_GROUP)):
        x1 = min(nx, x0 + _SLAB_GROUP)
        boxes = [
            (r, v)
            for r, v in box_terms
            if r[0].start < x1 and r[0].stop > x0 and (log or v - reference > -margin)
        ]
        if c not in parts and not boxes:
            out[x0:x1] = -np.inf
            continue
        acc = chunk[: x1 - x0]
        acc.fill(-np.inf if log else 0.0)
        for s, group in parts.get(c, ()):
            s.accumulate(acc, x0, group, work64, work, log)
        for r, v in boxes:
            ranges = (slice(max(r[0].start, x0) - x0, min(r[0].stop, x1) - x0), r[1], r[2])
            if log:
                np.logaddexp(acc[ranges], v - reference, out=acc[ranges])
            else:
                acc[ranges] += math.exp(v - reference)
        if log:
            out[x0:x1] = acc
        else:
            with np.errstate(divide="ignore"):
                np.log(acc, out=out[x0:x1])
    return out


def _centre_range(axis: np.ndarray, low: float, high: float) -> slice:
    """The indices of the (sorted) voxel centres in the closed interval [low, high]."""
    return slice(int(np.searchsorted(axis, low, "left")), int(np.searchsorted(axis, high, "right")))


@dataclass
class _Support:
    """One Gaussian's k-sigma box as groups of x-slabs, each with the (y, z) ranges bounding its ellipsoid
    sections, and what the matrix products need: over the box's (x, y) rows log_norm - z_0^2 - z_1^2 and
    c = z_2 - u, and u along z."""

    box: tuple[slice, ...]
    groups: list[tuple[slice, slice, slice]]  # ranges inside the box
    head: np.ndarray  # (bx, by): log_norm - z_0^2 - z_1^2
    c: np.ndarray  # (bx, by)
    u: np.ndarray  # (bz,), increasing
    rows: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))  # `prepare`
    columns: np.ndarray = field(default_factory=lambda: np.zeros((3, 0)))

    def peak(self) -> float:
        """The term's exact maximum over the box's voxels: along a column, -(c + u)^2 is largest at the
        voxel centre nearest its vertex u = -c."""
        c, u = self.c, self.u
        if len(u) == 1:
            return float(np.max(self.head - (c + u[0]) ** 2))
        j = np.clip(np.searchsorted(u, -c), 1, len(u) - 1)
        return float(np.max(self.head - np.minimum((c + u[j - 1]) ** 2, (c + u[j]) ** 2)))

    @property
    def largest_group(self) -> int:
        return max(int(np.prod([r.stop - r.start for r in g])) for g in self.groups)

    def prepare(self, reference: float) -> None:
        """The matrix products' operands for terms relative to `reference`."""
        c, u = self.c, self.u
        self.rows = np.stack([self.head - c * c - reference, -2.0 * c, np.full_like(c, -1.0)], axis=-1)
        self.columns = np.stack([np.ones_like(u), u, u * u])  # (3, bz)

    def accumulate(
        self,
        acc: np.ndarray,
        x0: int,
        group: tuple[slice, slice, slice],
        work64: np.ndarray,
        work: np.ndarray,
        log: bool,
    ) -> None:
        """acc += exp(term - reference) on one group (log: acc = logaddexp(acc, term - reference)); acc
        holds the x-slabs from x0 on; `work64` and `work` (acc's dtype) hold the largest group."""
        gx, gy, gz = group
        shape = (gx.stop - gx.start, gy.stop - gy.start, gz.stop - gz.start)
        n = shape[0] * shape[1] * shape[2]
        out64 = work64[:n].reshape(shape[0] * shape[1], shape[2])
        np.matmul(self.rows[gx, gy].reshape(-1, 3), self.columns[:, gz], out=out64)  # term - reference
        bx, by, bz = self.box
        start = bx.start + gx.start - x0
        target = acc[
            start : start + shape[0],
            by.start + gy.start : by.start + gy.stop,
            bz.start + gz.start : bz.start + gz.stop,
        ]
        if log:
            np.logaddexp(target, out64.reshape(shape), out=target)
            return
        out = out64 if work.dtype == np.float64 else work[:n].reshape(out64.shape)
        if out is not out64:
            np.copyto(out, out64, casting="same_kind")
        np.exp(out, out=out)
        target += out.reshape(shape)


def _component_support(
    grid: VoxelGrid,
    axes: tuple[np.ndarray, ...],
    mean: np.ndarray,
    cov: np.ndarray,
    scaled: np.ndarray,
    log_norm: float,
    floor: float,
) -> _Support | None:
    """The voxels where the component's term can exceed `floor` (`_Support`), None if there are none."""
    k2 = 2.0 * (log_norm - floor)
    if k2 <= 0:
        return None
    half = np.sqrt(k2 * np.diag(cov))
    box = tuple(_centre_range(axes[a], mean[a] - half[a], mean[a] + half[a]) for a in range(3))
    if any(r.stop <= r.start for r in box):
        return None
    dx, dy, dz = (axes[a][box[a]] - mean[a] for a in range(3))
    b = scaled
    z1 = b[1, 0] * dx[:, None] + b[1, 1] * dy[None, :]
    head = log_norm - (b[0, 0] * dx)[:, None] ** 2 - z1 * z1  # (bx, by)
    c = b[2, 0] * dx[:, None] + b[2, 1] * dy[None, :]  # (bx, by)
    u = b[2, 2] * dz  # (bz,), increasing
    # Sections of the ellipsoid r^2 <= k2 at each x: centre and half-widths of their (y, z) bounding box,
    # bounded over each group of x-slabs, as index ranges into dy and dz.
    sxx = cov[0, 0]
    r2 = np.maximum(k2 - dx * dx / sxx, 0.0)
    x0 = box[0].start  # groups end on the grid's chunk boundaries (`_sum_of_terms`)
    starts = np.concatenate(
        [[0], np.arange((x0 // _SLAB_GROUP + 1) * _SLAB_GROUP, box[0].stop, _SLAB_GROUP) - x0]
    )
    centre = (cov[0, 1:] / sxx)[:, None] * dx  # (2, bx): y and z of the sections' centres
    reach = np.sqrt((np.diag(cov)[1:] - cov[0, 1:] ** 2 / sxx)[:, None] * r2)  # (2, bx): their half-widths
    lo = np.minimum.reduceat(centre - reach, starts, axis=1)
    hi = np.maximum.reduceat(centre + reach, starts, axis=1)
    bounds = np.stack(
        [
            starts,
            np.append(starts[1:], len(dx)),
            np.searchsorted(dy, lo[0], "left"),
            np.searchsorted(dy, hi[0], "right"),
            np.searchsorted(dz, lo[1], "left"),
            np.searchsorted(dz, hi[1], "right"),
        ]
    ).T.tolist()  # per group: x0, x1, y0, y1, z0, z1
    groups = [
        (slice(x0, x1), slice(y0, y1), slice(z0, z1))
        for x0, x1, y0, y1, z0, z1 in bounds
        if y1 > y0 and z1 > z0
    ]
    if not groups:
        return None
    return _Support(box, groups, head, c, u)


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
    """lang = max(lang + log_likelihood - max(lang + log_likelihood), -span), in place (see the docstring).

    A float32 term (`language_log_likelihood`'s, 0 at its best voxel) is added in float32: both operands
    lie within a few spans of 0. Any other term is added in float64, so that a term far below 0 (an
    absolute log-density far from the mixture) does not round the mode away.
    """
    if log_likelihood.dtype == np.float32 and lang.dtype == np.float32:
        total = lang + log_likelihood
    else:
        total = lang.astype(np.float64) + log_likelihood
    peak = total.max()
    if not np.isfinite(peak):
        msg = "the language likelihood is not finite anywhere on the grid"
        raise InvalidInput(msg, "mixture")
    total -= peak
    np.maximum(total, -span, out=lang, casting="same_kind")


def posterior(lang: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """Equation (2): softmax(lang + vis) over all voxels, (N,) float64."""
    s = lang.astype(np.float64) + vis
    s -= s.max()
    p: np.ndarray = np.exp(s)
    p /= p.sum()
    return p
