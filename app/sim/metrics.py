"""Closed-loop metrics of a belief over the target's voxel, following the reference's closed-loop evaluation.

Notation. The session's grid has N voxels; the target occupies the set T of n_t of them (its voxels in the
simulated world, `SemanticVoxelWorld.object_voxels`, on the service's grid). b_tau is the posterior after
tau of the episode's S steps (b_0: after the utterance, before any observation; the uniform 1/N for
vision-only).

Target mass and information gain at the target:

    m_tau  = sum_{i in T} b_tau(i)                                                                (1)
    m_unif = n_t / N                        (the uniform prior's mass on the target)               (2)
    IG_tau = log m_tau - log m_unif         (nats)                                                 (3)

IG = 0 for the uniform belief, log(N / n_t) for a belief with all its mass on the target, and negative when
the belief holds less mass at the target than knowing nothing would (the overconfident failure mode). The
service clamps its layers (`app.belief.fusion`), so no voxel's posterior falls below about e^-55 / N and m_tau
never underflows to 0 in float32; m_tau is still floored at `MASS_FLOOR` so that a log is always finite.

Argmax distance: from the centre c* of the MAP voxel argmax_i b_tau(i) to the target's axis-aligned box
[lo, hi] (0 when the centre lies inside the box, so a MAP voxel anywhere on a large target is no error):

    d_tau = || max(lo - c*, 0, c* - hi) ||_2   (metres, elementwise max)                          (4)

Episode outcomes, from the terminal belief b_S:

    success:  m_S >= SUCCESS_MASS (0.1)                                                             (5)
    miss:     m_S <  m_unif         (IG_S < 0: worse than the uniform prior)                       (6)

The reference defines success as "significant terminal target mass" without a number; 0.1 means one in ten
of the belief's mass sits on the target, about 200 times the uniform prior's share in these rooms (n_t / N
~ 5e-4) and 16 times the reference's mean terminal mass for vision-only (0.006, 0% success), while its LSM
averages 0.22 (52% success), so the threshold separates "the robot knows where to look" from "it does not".
Episodes neither successes nor misses are the unresolved ambiguity in between.

Splits: an episode's target was *observed* when any of its voxels was in any frame's observed voxels (a
camera ray stopped on it), else *never observed*; metrics are reported per split and method.

Aggregates over the n episodes of a split: mean and its standard error SE = s / sqrt(n), s the sample
standard deviation (ddof = 1); SE is undefined (None) for n < 2. Curves: mean +- SE of IG_tau and m_tau at
each checkpoint, against normalised progress tau / S.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Terminal target mass counted as a success (equation (5); see the module docstring for why 0.1).
SUCCESS_MASS = 0.1
#: Lower bound on a target mass before its log is taken (never reached with the service's clamped layers).
MASS_FLOOR = 1e-30


def target_mass(posterior: np.ndarray, target_flat: np.ndarray) -> float:
    """Equation (1): the posterior mass on the target's voxels (summed in float64)."""
    return float(np.sum(np.asarray(posterior)[np.asarray(target_flat)], dtype=np.float64))


def uniform_mass(n_target: int, n_voxels: int) -> float:
    """Equation (2): n_t / N."""
    if not 0 < n_target <= n_voxels:
        msg = f"need 0 < n_target <= n_voxels, got {n_target} and {n_voxels}"
        raise ValueError(msg)
    return n_target / n_voxels


def information_gain(mass: float | np.ndarray, n_target: int, n_voxels: int) -> float | np.ndarray:
    """Equation (3): log m - log(n_t / N), nats; elementwise for an array of masses."""
    floored = np.maximum(np.asarray(mass, dtype=np.float64), MASS_FLOOR)
    gain = np.log(floored) - math.log(uniform_mass(n_target, n_voxels))
    return float(gain) if gain.ndim == 0 else gain


def box_distance(point: Sequence[float] | np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """Equation (4): Euclidean distance from a point to an axis-aligned box, 0 inside it."""
    p = np.asarray(point, dtype=np.float64)
    gap = np.maximum(np.maximum(np.asarray(low) - p, p - np.asarray(high)), 0.0)
    return float(np.linalg.norm(gap))


def is_success(terminal_mass: float, threshold: float = SUCCESS_MASS) -> bool:
    """Equation (5)."""
    return terminal_mass >= threshold


def is_miss(terminal_mass: float, n_target: int, n_voxels: int) -> bool:
    """Equation (6): less terminal mass on the target than the uniform prior puts there."""
    return terminal_mass < uniform_mass(n_target, n_voxels)


def mean_and_se(values: Sequence[float] | np.ndarray) -> tuple[float | None, float | None]:
    """(mean, standard error s / sqrt(n) with ddof = 1) over the values; None where undefined."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(x) == 0:
        return None, None
    mean = float(np.mean(x))
    if len(x) < 2:
        return mean, None
    return mean, float(np.std(x, ddof=1) / math.sqrt(len(x)))


def curve_mean_and_se(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) mean and standard error over the episodes of (n, K) per-checkpoint values; NaN SE if n < 2."""
    x = np.asarray(rows, dtype=np.float64)
    n = x.shape[0]
    if n == 0:
        nan = np.full(x.shape[1], np.nan)
        return nan, nan.copy()
    se = np.std(x, axis=0, ddof=1) / math.sqrt(n) if n >= 2 else np.full(x.shape[1], np.nan)
    return np.mean(x, axis=0), se


@dataclass(frozen=True)
class EpisodeOutcome:
    """What one method's belief did in one episode: the target mass and MAP distance at each checkpoint."""

    episode_id: str
    method: str
    target_seen: bool
    n_target: int
    n_voxels: int
    progress: tuple[float, ...]  # (K,) tau / S at the checkpoints, 0 first, 1 last
    mass: tuple[float, ...]  # (K,) m_tau
    argmax_distance: tuple[float, ...]  # (K,) d_tau, metres

    @property
    def information_gain(self) -> np.ndarray:
        """(K,) IG_tau, nats."""
        return np.atleast_1d(information_gain(np.asarray(self.mass), self.n_target, self.n_voxels))

    @property
    def terminal_mass(self) -> float:
        return self.mass[-1]

    @property
    def terminal_information_gain(self) -> float:
        return float(self.information_gain[-1])

    @property
    def miss(self) -> bool:
        return is_miss(self.terminal_mass, self.n_target, self.n_voxels)


@dataclass(frozen=True)
class SplitMetrics:
    """The aggregates of one method over the episodes of one split (module docstring)."""

    n: int
    mean_ig: float | None
    se_ig: float | None
    mean_mass: float | None
    se_mass: float | None
    mean_argmax_distance: float | None
    se_argmax_distance: float | None
    success_pct: float | None
    miss_pct: float | None
    progress: tuple[float, ...]
    ig_curve_mean: tuple[float, ...]
    ig_curve_se: tuple[float, ...]
    mass_curve_mean: tuple[float, ...]
    mass_curve_se: tuple[float, ...]


def split_metrics(outcomes: Sequence[EpisodeOutcome], success_mass: float = SUCCESS_MASS) -> SplitMetrics:
    """Aggregate one method's outcomes (all sharing one checkpoint schedule) over one split."""
    if outcomes and len({o.progress for o in outcomes}) != 1:
        msg = "the outcomes of one split must share their checkpoint schedule"
        raise ValueError(msg)
    n = len(outcomes)
    ig, ig_se = mean_and_se([o.terminal_information_gain for o in outcomes])
    mass, mass_se = mean_and_se([o.terminal_mass for o in outcomes])
    dist, dist_se = mean_and_se([o.argmax_distance[-1] for o in outcomes])
    progress = outcomes[0].progress if outcomes else ()
    k = len(progress)
    ig_mean_curve, ig_se_curve = curve_mean_and_se(
        np.array([o.information_gain for o in outcomes]).reshape(n, k)
    )
    mass_mean_curve, mass_se_curve = curve_mean_and_se(np.array([o.mass for o in outcomes]).reshape(n, k))
    return SplitMetrics(
        n=n,
        mean_ig=ig,
        se_ig=ig_se,
        mean_mass=mass,
        se_mass=mass_se,
        mean_argmax_distance=dist,
        se_argmax_distance=dist_se,
        success_pct=100.0 * sum(is_success(o.terminal_mass, success_mass) for o in outcomes) / n
        if n
        else None,
        miss_pct=100.0 * sum(o.miss for o in outcomes) / n if n else None,
        progress=tuple(progress),
        ig_curve_mean=tuple(ig_mean_curve.tolist()),
        ig_curve_se=tuple(ig_se_curve.tolist()),
        mass_curve_mean=tuple(mass_mean_curve.tolist()),
        mass_curve_se=tuple(mass_se_curve.tolist()),
    )


#: Splits of the report, in table order: name -> which episodes belong to it.
SPLITS = ("observed", "unobserved", "all")


def in_split(outcome: EpisodeOutcome, split: str) -> bool:
    if split == "observed":
        return outcome.target_seen
    if split == "unobserved":
        return not outcome.target_seen
    if split == "all":
        return True
    msg = f"unknown split {split!r}; one of {list(SPLITS)}"
    raise ValueError(msg)


def aggregate(
    outcomes: Sequence[EpisodeOutcome], methods: Sequence[str], success_mass: float = SUCCESS_MASS
) -> dict[str, dict[str, SplitMetrics]]:
    """method -> split -> aggregates, for every method given (in order) and every split of `SPLITS`."""
    return {
        method: {
            split: split_metrics(
                [o for o in outcomes if o.method == method and in_split(o, split)], success_mass
            )
            for split in SPLITS
        }
        for method in methods
    }
