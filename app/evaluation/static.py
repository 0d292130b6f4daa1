"""Static evaluation: the language sensor on a file of grounding cases, scored against the true positions.

Every case goes through the service's own path, `LanguageSensor(proposer, grounder).ground(scene_graph,
utterance, hypotheses=...)`. The hypotheses come from the proposer, run once per case and shared by every
grounder (so the methods of one table differ only in their grounding):

- `gt`: the case's true hypotheses with uniform weights (in practice one: `hypotheses[0]`);
- `builtin`: the calibrated built-in referent proposer (`app.grounding.builtin`, the service's default);
- `llm`: the LLM proposer over an OpenAI-compatible endpoint, falling back to the built-in one.

When a proposal holds no hypothesis (no anchor matched), the mixture is the sensor's broad prior. A grounder
with a `ground_mixture(scene_graph, utterance)` method (LLM-E2E) predicts the whole mixture itself and
ignores the proposer.

Metrics per method, for a case with target y and the served mixture p(x) = sum_h w_h p_h(x) (+ the
sensor's own uniform terms), p_h the density of hypothesis h (a small mixture of Gaussians and uniform boxes)
and mean(q), cov(q) the moment-matched mean and covariance of a density q:

    NLL       = -log p(y)  (nats; mean over cases)
    RMSE      = sqrt(mean_cases ||x_point - y||^2)  (metres)
    NEES      = (y - mean(p_m))^T cov(p_m)^-1 (y - mean(p_m))      ANEES = mean NEES over the matched cases
    NEES_full = (y - mean(p))^T cov(p)^-1 (y - mean(p))            ANEES_full = mean over every case
    coverage  = fraction of cases with y in the HDR of mass m: {x : p(x) >= tau_m}, P(p(X) >= tau_m) = m

- The matched hypothesis m: with `--proposer gt`, the true one (`hypotheses[0]`); with another proposer, the
  heaviest hypothesis holding the true anchors (same anchor set, relation not compared); cases where none
  does (every case without true hypotheses: Nr3D, ScanRefer) are left out of ANEES and counted
  (`unmatched`), while NLL, coverage, RMSE and ANEES_full score them on the full mixture. For a
  mixture-predicting grounder, m is the Gaussian whose mean is nearest the true anchors' centroid (how
  `LLMEndToEndGrounder` matches components to hypotheses) and NEES is that Gaussian's.
- The point x_point: mean(p_m) with `--proposer gt`; otherwise mean(p_h) of the heaviest hypothesis (the
  mixture's best single guess; mean(p) can lie between anchors, where nothing is), mean(p) when there is no
  hypothesis (the broad prior); for a mixture-predicting grounder, the matched (gt) or heaviest Gaussian's
  mean.
- Coverage: for a single Gaussian the HDR of mass m is exactly the ellipsoid NEES <= F^-1(m) (F the chi^2(3)
  CDF), so y is covered iff F(NEES) <= m; a mixture's thresholds tau_m are Monte Carlo
  (`app.evaluation.metrics.hdr_coverage`, `hdr_samples` draws per case, seeded by (seed, case index), ties
  on the plateaus of uniform boxes broken at random so that the region holds mass m exactly).
- A calibrated 3-D predictor has ANEES 3 (above: overconfident) and coverage m at every mass m.
- ANEES's 90% interval (`anees_ci90`): the percentile bootstrap of the mean NEES, resampling whole rooms
  (`meta.scene_id`; a case without one is its own room), 2,000 resamples, seed 0: whether a relation's
  ANEES of 3.5 over 300 cases in 70 rooms is out of a band or within its own sampling error.

Every NLL is read against the no-language baseline: the uniform density over the map's box U (the
axis-aligned box enclosing every object box of the case's scene graph, each side at least 0.1 m;
`app.grounding.mixture.map_box`), what one can say of the target without the utterance:

    uniform_nll               = -log U(y) = log vol(U) if y in U, else +inf
    better_than_uniform       = fraction of cases with NLL < uniform_nll
    nll_minus_uniform         = mean (NLL - uniform_nll)      over the cases with y in U
    worst_excess_over_uniform = max (NLL - uniform_nll)       over the cases with y in U

`uniform_nll` of a group is its mean over the cases with y in U, `uniform_outside` counts the others
(better than the baseline whatever the method says, since U(y) = 0 there).

With a proposer other than `gt`, the weights themselves are scored ("referent") as a distribution over
referents: the weights of the hypotheses reading the same anchor set are summed (a "near" and a "closest"
reading of one table are one referent), hypotheses with no anchor object (the target in a region) are left
out, and a referent is correct when it is the true anchor set:

    top1_accuracy       = fraction of cases whose highest-weight hypothesis is correct
    true_hypothesis_nll = mean -log max(sum of the correct hypotheses' weights, 1e-6); cases with no correct
                          hypothesis get -log 1e-6 and are counted (`absent`)
    ECE                 = sum_b (n_b / N) |acc_b - conf_b| over 10 equal-width bins of the weight, pooling
                          every (weight, correct) pair of every case; conf_b the bins' mean weight, acc_b
                          their fraction correct

and `uniform_weights_nll` is the same pipeline's mixture NLL with the proposer's weights replaced by
uniform weights over the same hypotheses' densities (the sensor's own uniform terms keeping their weight):
the proposer's weights earn their keep when the NLL is lower than this.

Everything is reported overall, per relation (of the true hypothesis) and per ambiguity level (the number
of objects sharing the true anchor's label, the most over the anchors of "between": `meta.ambiguity` when
the case carries it), bucketed 1, 2, 3-4, 5+.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np

from app.data.cases import GroundingCase, case_room, read_cases
from app.errors import InvalidInput, ModelUnavailable
from app.evaluation.metrics import (
    DEFAULT_MASSES,
    clustered_interval,
    hdr_coverage,
    mixture_nll,
    nees,
    no_language_nll,
    rmse,
)
from app.grounding.hypotheses import Hypothesis, Proposal
from app.grounding.interfaces import Grounder, HypothesisProposer
from app.grounding.mixture import GaussianMixture
from app.grounding.relations import Relation
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.model import SceneGraph

log = logging.getLogger("vlmap.eval")

PROPOSERS = ("gt", "builtin", "llm")
GROUNDERS = ("lsm", "geometric", "fixed", "scaffolded-llm", "llm-e2e")
BASELINES = ("geometric", "fixed")
AMBIGUITY_BUCKETS = ("1", "2", "3-4", "5+")
UNKNOWN = "unknown"
ECE_BINS = 10
ABSENT_WEIGHT_FLOOR = 1e-6
DEFAULT_HDR_SAMPLES = 5000
_MAX_FAILURE_EXAMPLES = 5


# ---------------------------------------------------------------------------------------------------------
# Proposers and grounders by name


@dataclass(frozen=True)
class LLMOptions:
    """Where the LLM proposer and baselines call; from the command line, else VLMAP_LLM_* variables."""

    url: str | None = None
    model: str | None = None
    api_key: str | None = None

    @classmethod
    def from_env(
        cls, url: str | None = None, model: str | None = None, env: Mapping[str, str] = os.environ
    ) -> LLMOptions:
        return cls(
            url=url or env.get("VLMAP_LLM_URL") or None,
            model=model or env.get("VLMAP_LLM_MODEL") or None,
            api_key=env.get("VLMAP_LLM_API_KEY") or None,
        )

    def endpoint(self, needed_by: str) -> Any:
        """The `LLMEndpoint`; InvalidInput naming what needs it when no endpoint is configured."""
        if not self.url or not self.model:
            msg = (
                f"{needed_by} needs an LLM endpoint: pass --llm-url and --llm-model "
                "(or set VLMAP_LLM_URL and VLMAP_LLM_MODEL, and VLMAP_LLM_API_KEY if it wants a key)"
            )
            raise InvalidInput(msg, field="--llm-url")
        from app.llm.client import LLMEndpoint

        return LLMEndpoint(base_url=self.url, model=self.model, api_key=self.api_key)


def make_builtin_proposer(params: Path | None = None) -> HypothesisProposer:
    """The built-in proposer (its parameters from `params`, default the shipped ones), on the process's one
    MiniLM (shared with the LSM)."""
    from app.grounding.builtin import BuiltinProposer
    from app.lsm.text_encoder import default_text_encoder

    return BuiltinProposer.load(default_text_encoder(), params)


def make_proposer(
    name: str,
    llm: LLMOptions,
    stack: ExitStack,
    on_fallback: Callable[[str], None] | None = None,
    params: Path | None = None,
) -> HypothesisProposer | None:
    """None for `gt` (the cases' own hypotheses); clients opened here are closed by `stack`."""
    if name == "gt":
        return None
    if name == "builtin":
        return make_builtin_proposer(params)
    if name == "llm":
        from app.llm.client import ChatClient
        from app.llm.proposer import LLMProposer

        client = stack.enter_context(ChatClient(llm.endpoint("--proposer llm")))
        return LLMProposer(client, make_builtin_proposer(params), on_fallback=on_fallback)
    msg = f"unknown proposer {name!r}; choose from {', '.join(PROPOSERS)}"
    raise InvalidInput(msg, field="--proposer")


def make_grounder(name: str, llm: LLMOptions, stack: ExitStack, model_dir: Path | None = None) -> Grounder:
    """The grounder called `name`; `lsm` reads `model_dir` (default: the shipped models/lsm)."""
    if name == "geometric":
        from app.grounding.geometric import GeometricGrounder

        return GeometricGrounder()
    if name == "fixed":
        from app.grounding.geometric import FixedGrounder

        return FixedGrounder()
    if name == "lsm":
        from app.lsm.grounder import DEFAULT_MODEL_DIR, LSMGrounder
        from app.lsm.text_encoder import default_text_encoder

        where = model_dir or DEFAULT_MODEL_DIR
        try:
            return LSMGrounder.load(where, encoder=default_text_encoder())
        except ModelUnavailable as exc:
            msg = f"--grounder lsm cannot load the LSM: {exc}. Train one (`vlmap train`) or pass --model-dir"
            raise ModelUnavailable(msg) from exc
    if name in ("scaffolded-llm", "llm-e2e"):
        from app.llm.baselines import LLMEndToEndGrounder, ScaffoldedLLMGrounder
        from app.llm.client import ChatClient

        client = stack.enter_context(ChatClient(llm.endpoint(f"--grounder {name}")))
        return ScaffoldedLLMGrounder(client) if name == "scaffolded-llm" else LLMEndToEndGrounder(client)
    msg = f"unknown grounder {name!r}; choose from {', '.join(GROUNDERS)}"
    raise InvalidInput(msg, field="--grounder")


# ---------------------------------------------------------------------------------------------------------
# Metric pieces this module adds to app.evaluation.metrics


def chi2_3_cdf(x: float) -> float:
    """F(x) = P(chi^2(3) <= x) = erf(sqrt(x/2)) - sqrt(2x/pi) exp(-x/2)."""
    if x <= 0.0:
        return 0.0
    return math.erf(math.sqrt(0.5 * x)) - math.sqrt(2.0 * x / math.pi) * math.exp(-0.5 * x)


def mixture_coverage(
    mixture: GaussianMixture,
    target: np.ndarray,
    rng: np.random.Generator,
    masses: Sequence[float] = DEFAULT_MASSES,
    hdr_samples: int = DEFAULT_HDR_SAMPLES,
) -> np.ndarray:
    """Whether `target` lies in the mixture's HDR of each mass; bool (len(masses),).

    One Gaussian and no box: exact, y in HDR_m iff F(NEES) <= m. Otherwise Monte Carlo (`hdr_coverage`).
    """
    if len(mixture.weights) == 1 and not len(mixture.box_weights):
        level = chi2_3_cdf(float(nees(mixture.means[0], mixture.covariances[0], target)[0]))
        return np.array([level <= m for m in masses])
    covered: np.ndarray = hdr_coverage(mixture, np.asarray(target).reshape(1, 3), rng, masses, hdr_samples)[0]
    return covered


def moment_nees(density: GaussianMixture, target: np.ndarray) -> float:
    """(y - mean(q))^T cov(q)^-1 (y - mean(q)) with the moment-matched mean and covariance of q."""
    return float(nees(density.mean(), density.covariance(), target)[0])


def uniform_weights_mixture(grounding: Grounding) -> GaussianMixture:
    """The served mixture with uniform weights over the hypotheses' densities, its broad term kept:
    with p(x) = (1 - beta) sum_h w_h p_h(x) + beta b(x), the answer is (1 - beta) sum_h p_h(x) / H +
    beta b(x). Without densities (the broad prior) it is p itself."""
    if not grounding.densities:
        return grounding.mixture
    even = GaussianMixture.combine(np.ones(len(grounding.densities)), grounding.densities)
    if grounding.broad is None or grounding.background <= 0.0:
        return even
    beta = grounding.background
    return GaussianMixture.combine([1.0 - beta, beta], [even, grounding.broad])


def reliability_bins(
    weights: np.ndarray, correct: np.ndarray, n_bins: int = ECE_BINS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per equal-width bin of [0, 1]: count n_b, mean weight conf_b, fraction correct acc_b; (n_bins,) each.

    A weight of exactly 1 falls in the last bin; empty bins have conf_b = acc_b = NaN.
    """
    w = np.asarray(weights, dtype=np.float64).ravel()
    hit = np.asarray(correct, dtype=np.float64).ravel()
    index = np.minimum((w * n_bins).astype(np.int64), n_bins - 1)  # (P,)
    counts = np.bincount(index, minlength=n_bins).astype(np.float64)  # (n_bins,)
    with np.errstate(invalid="ignore", divide="ignore"):
        confidence = np.bincount(index, weights=w, minlength=n_bins) / counts
        accuracy = np.bincount(index, weights=hit, minlength=n_bins) / counts
    return counts, confidence, accuracy


def expected_calibration_error(weights: np.ndarray, correct: np.ndarray, n_bins: int = ECE_BINS) -> float:
    """ECE = sum_b (n_b / N) |acc_b - conf_b| over `n_bins` equal-width bins of the weight."""
    counts, confidence, accuracy = reliability_bins(weights, correct, n_bins)
    total = counts.sum()
    if total == 0:
        return math.nan
    filled = counts > 0
    return float(np.sum(counts[filled] / total * np.abs(accuracy[filled] - confidence[filled])))


def true_hypothesis_nll(
    weights: np.ndarray, correct: np.ndarray, floor: float = ABSENT_WEIGHT_FLOOR
) -> tuple[float, bool]:
    """(-log max(sum of the correct hypotheses' weights, floor), whether no hypothesis is correct)."""
    mass = float(np.sum(np.asarray(weights, dtype=np.float64)[np.asarray(correct, dtype=bool)]))
    return -math.log(max(mass, floor)), not bool(np.any(correct))


def ambiguity_bucket(count: int | None) -> str:
    """1, 2, 3-4 or 5+ same-label candidates ("unknown" when the case cannot tell)."""
    if count is None or count < 1:
        return UNKNOWN
    if count <= 2:
        return str(count)
    return "3-4" if count <= 4 else "5+"


def case_ambiguity(case: GroundingCase) -> int | None:
    """`meta.ambiguity`, else how many objects share the true anchor's label (most over the anchors)."""
    given = case.meta.get("ambiguity")
    if isinstance(given, int | float) and not isinstance(given, bool):
        return int(given)
    if not case.hypotheses:
        return None
    labels = Counter(o.label for o in case.scene_graph.objects)
    by_id = {o.id: o.label for o in case.scene_graph.objects}
    counts = [labels[by_id[a]] for a in case.hypotheses[0].anchor_ids if a in by_id]
    return max(counts) if counts else None


# ---------------------------------------------------------------------------------------------------------
# Per-case scores and their aggregation


@dataclass(frozen=True)
class CaseScore:
    """One method's score on one case."""

    relation: str
    ambiguity: str
    target: np.ndarray  # (3,)
    point: np.ndarray  # (3,) where the error is measured
    nll: float  # -log p(y), nats
    nees: float | None  # of the matched density; None when no hypothesis holds the true anchors
    covered: np.ndarray  # (M,) bool: y inside the HDR of each mass
    uniform_weights_nll: float | None = None  # uniform weights over the densities (proposers other than gt)
    components: int = 1
    nees_full: float | None = None  # of the whole mixture's moment-matched Gaussian
    uniform_nll: float = math.inf  # the no-language baseline, -log U(y; map box)
    room: str = ""  # cases of one room are resampled together for the ANEES interval (`case_room`)

    @property
    def better_than_uniform(self) -> bool:
        return self.nll < self.uniform_nll


@dataclass(frozen=True)
class ReferentScore:
    """The proposer's weights on one case, each hypothesis marked correct or not."""

    ambiguity: str
    weights: np.ndarray  # (K,) summing to one; empty when the proposal was not grounded
    correct: np.ndarray  # (K,) bool: the hypothesis holds the true anchors

    @property
    def top1(self) -> bool:
        return len(self.weights) > 0 and bool(self.correct[int(np.argmax(self.weights))])


def referent_score(bucket: str, hypotheses: Sequence[Hypothesis], truth: frozenset[str]) -> ReferentScore:
    """The proposal as a distribution over anchor sets: P(anchors) = sum of the weights of the hypotheses
    that read them (a "near" and a "closest" reading of one table are one referent); hypotheses with no
    anchor object (the target in a region) name no referent and stay out."""
    by_anchors: dict[frozenset[str], float] = {}
    for h in hypotheses:
        if h.anchor_ids:
            key = frozenset(h.anchor_ids)
            by_anchors[key] = by_anchors.get(key, 0.0) + h.weight
    keys = list(by_anchors)
    return ReferentScore(
        bucket,
        np.array([by_anchors[k] for k in keys], dtype=np.float64),
        np.array([k == truth for k in keys], dtype=bool),
    )


def _mean_or_none(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if len(values) else None


def summarize_scores(scores: Sequence[CaseScore], masses: Sequence[float] = DEFAULT_MASSES) -> dict[str, Any]:
    """n, RMSE, NLL (mean, median), ANEES (over `anees_n` matched cases; `unmatched` the rest) and its 90%
    interval over rooms (`anees_ci90`, `clustered_interval`; null under two rooms), coverage, ANEES_full,
    and the no-language baseline's uniform_nll, better_than_uniform, nll_minus_uniform,
    worst_excess_over_uniform and uniform_outside (the module docstring's definitions)."""
    if not scores:
        return {"n": 0}
    matched = [s.nees for s in scores if s.nees is not None]
    interval = (
        clustered_interval(matched, [s.room for s in scores if s.nees is not None]) if matched else None
    )
    full = [s.nees_full for s in scores if s.nees_full is not None]
    inside = [s for s in scores if math.isfinite(s.uniform_nll)]
    excess = [s.nll - s.uniform_nll for s in inside]
    covered = np.stack([s.covered for s in scores])  # (N, M)
    nll = np.array([s.nll for s in scores])
    out: dict[str, Any] = {
        "n": len(scores),
        "rmse": rmse(np.stack([s.point for s in scores]), np.stack([s.target for s in scores])),
        "nll": float(np.mean(nll)),
        "nll_median": float(np.median(nll)),
        "anees": _mean_or_none(matched),
        "anees_ci90": None if interval is None else list(interval),
        "anees_n": len(matched),
        "unmatched": len(scores) - len(matched),
        "coverage": {str(m): float(np.mean(covered[:, j])) for j, m in enumerate(masses)},
        "anees_full": _mean_or_none(full),
        "uniform_nll": _mean_or_none([s.uniform_nll for s in inside]),
        "uniform_outside": len(scores) - len(inside),
        "better_than_uniform": float(np.mean([s.better_than_uniform for s in scores])),
        "nll_minus_uniform": _mean_or_none(excess),
        "worst_excess_over_uniform": float(max(excess)) if excess else None,
    }
    uniform_weights = [s.uniform_weights_nll for s in scores if s.uniform_weights_nll is not None]
    if uniform_weights:
        out["uniform_weights_nll"] = float(np.mean(uniform_weights))
    return out


def summarize_referent(scores: Sequence[ReferentScore], with_bins: bool = False) -> dict[str, Any]:
    """top-1 accuracy, true-hypothesis NLL (and how many cases lack the true hypothesis), ECE."""
    if not scores:
        return {"n": 0}
    nll_absent = [true_hypothesis_nll(s.weights, s.correct) for s in scores]
    weights = np.concatenate([s.weights for s in scores])
    correct = np.concatenate([s.correct for s in scores]).astype(bool)
    ece = expected_calibration_error(weights, correct)
    out: dict[str, Any] = {
        "n": len(scores),
        "top1_accuracy": float(np.mean([s.top1 for s in scores])),
        "true_hypothesis_nll": float(np.mean([v for v, _ in nll_absent])),
        "absent": int(sum(a for _, a in nll_absent)),
        "ungrounded": int(sum(len(s.weights) == 0 for s in scores)),
        "mean_hypotheses": float(np.mean([len(s.weights) for s in scores])),
        "ece": None if math.isnan(ece) else ece,
    }
    if with_bins:
        counts, confidence, accuracy = reliability_bins(weights, correct)
        out["reliability"] = [
            {
                "low": b / ECE_BINS,
                "high": (b + 1) / ECE_BINS,
                "n": int(counts[b]),
                "mean_weight": None if counts[b] == 0 else float(confidence[b]),
                "accuracy": None if counts[b] == 0 else float(accuracy[b]),
            }
            for b in range(ECE_BINS)
        ]
    return out


def _ordered_groups(keys: Iterable[str], order: Sequence[str]) -> list[str]:
    present = set(keys)
    return [k for k in order if k in present] + sorted(present - set(order))


def group_scores(scores: Sequence[CaseScore]) -> dict[str, Any]:
    """{"overall", "per_relation", "per_ambiguity"}, each group summarised by `summarize_scores`."""
    relation_order = [r.value for r in Relation]
    return {
        "overall": summarize_scores(scores),
        "per_relation": {
            key: summarize_scores([s for s in scores if s.relation == key])
            for key in _ordered_groups((s.relation for s in scores), relation_order)
        },
        "per_ambiguity": {
            key: summarize_scores([s for s in scores if s.ambiguity == key])
            for key in _ordered_groups((s.ambiguity for s in scores), AMBIGUITY_BUCKETS)
        },
    }


def group_referent(scores: Sequence[ReferentScore]) -> dict[str, Any]:
    return {
        "overall": summarize_referent(scores, with_bins=True),
        "per_ambiguity": {
            key: summarize_referent([s for s in scores if s.ambiguity == key])
            for key in _ordered_groups((s.ambiguity for s in scores), AMBIGUITY_BUCKETS)
        },
    }


# ---------------------------------------------------------------------------------------------------------
# The evaluation loop


@dataclass
class _Failures:
    count: int = 0
    examples: list[str] = field(default_factory=list)

    def add(self, case_id: str, exc: BaseException) -> None:
        self.count += 1
        if len(self.examples) < _MAX_FAILURE_EXAMPLES:
            self.examples.append(f"{case_id}: {type(exc).__name__}: {exc}")

    def to_json(self) -> dict[str, Any]:
        return {"count": self.count, "examples": self.examples}


class _GivenHypotheses:
    """The sensor's proposer slot under `--proposer gt`: the evaluation hands the sensor its hypotheses."""

    name = "gt"

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        msg = "the gt evaluation passes the cases' hypotheses to the sensor"
        raise RuntimeError(msg)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name}


def _predicts_mixture(grounder: Grounder) -> bool:
    return callable(getattr(grounder, "ground_mixture", None))


def _nearest_component(mixture: GaussianMixture, scene_graph: SceneGraph, anchor_ids: Sequence[str]) -> int:
    centroid = np.mean([scene_graph.object(i).center for i in anchor_ids], axis=0)  # (3,)
    return int(np.argmin(np.linalg.norm(mixture.means - centroid, axis=1)))


def _score_case(
    grounder: Grounder,
    sensor: LanguageSensor,
    case: GroundingCase,
    group: tuple[str, str],
    hypotheses: tuple[Hypothesis, ...],
    proposal: Proposal | None,
    *,
    given_truth: bool,
    uniform_nll: float,
    rng: np.random.Generator,
    hdr_samples: int,
) -> CaseScore:
    """One grounder's mixture for one case, scored as the module docstring defines.

    `given_truth`: the hypotheses are the case's true ones (`--proposer gt`), the first being the truth.
    `uniform_nll`: the case's no-language baseline (`no_language_nll`).
    """
    truth = case.hypotheses[0] if case.hypotheses else None
    target = np.asarray(case.target.position, dtype=np.float64)  # (3,)
    uniform_weights_nll = None
    nees_value = None
    if _predicts_mixture(grounder):
        mixture: GaussianMixture = grounder.ground_mixture(case.scene_graph, case.utterance)  # type: ignore[attr-defined]
        matched = _nearest_component(mixture, case.scene_graph, truth.anchor_ids) if truth else None
        chosen = matched if given_truth and matched is not None else int(np.argmax(mixture.weights))
        point = mixture.means[chosen]
        if matched is not None:
            nees_value = float(nees(mixture.means[matched], mixture.covariances[matched], target)[0])
    else:
        if proposal is not None:  # the proposer's reading, served as the service serves it
            grounding = sensor.ground_proposal(case.scene_graph, case.utterance, proposal)
        elif hypotheses:
            grounding = sensor.ground(case.scene_graph, case.utterance, hypotheses=hypotheses)
        else:
            msg = "no hypotheses to ground"
            raise ValueError(msg)
        mixture, grounded, densities = grounding.mixture, grounding.hypotheses, grounding.densities
        heaviest = max(range(len(grounded)), key=lambda k: grounded[k].weight) if grounded else None
        if given_truth:
            matched = 0
        else:
            true_anchors = frozenset(truth.anchor_ids) if truth else None
            holds = [k for k, h in enumerate(grounded) if frozenset(h.anchor_ids) == true_anchors]
            matched = max(holds, key=lambda k: grounded[k].weight) if holds else None
            uniform_weights_nll = mixture_nll(uniform_weights_mixture(grounding), target)
        guess = matched if given_truth else heaviest
        point = densities[guess].mean() if guess is not None else mixture.mean()
        if matched is not None:
            nees_value = moment_nees(densities[matched], target)
    return CaseScore(
        relation=group[0],
        ambiguity=group[1],
        target=target,
        point=point,
        nll=mixture_nll(mixture, target),
        nees=nees_value,
        covered=mixture_coverage(mixture, target, rng, hdr_samples=hdr_samples),
        uniform_weights_nll=uniform_weights_nll,
        components=len(mixture.weights),
        nees_full=moment_nees(mixture, target),
        uniform_nll=uniform_nll,
        room=case_room(case),
    )


@dataclass(frozen=True)
class StaticEvaluation:
    """What `evaluate_static` measured: metrics.json's content and one row per case."""

    metrics: dict[str, Any]
    per_case: list[dict[str, Any]]


def evaluate_static(
    cases: Iterable[GroundingCase],
    grounders: Sequence[Grounder],
    proposer: HypothesisProposer | None = None,
    *,
    seed: int = 0,
    hdr_samples: int = DEFAULT_HDR_SAMPLES,
    progress: bool = False,
    total: int | None = None,
) -> StaticEvaluation:
    """Score each grounder (with `proposer`'s hypotheses; None: the cases' true ones) on every case.

    metrics = {<grounder name>: {"overall", "per_relation", "per_ambiguity", "failures", "seconds"},
    "referent": {"overall", "per_ambiguity"} (with a proposer), "run": counts}. A case that fails for a
    method (an LLM error, a bad anchor id) is counted in that method's failures and skipped by it.
    per_case rows: {"case_id", "relation", "ambiguity", "uniform_nll" (null outside the map's box),
    "referent" (with a proposer and true hypotheses), <grounder name>: {"nll", "error_m", "nees",
    "covered", "components", "nees_full", "better_than_uniform"} or {"error"}}.
    """
    from tqdm import tqdm

    names = [g.name for g in grounders]
    if len(set(names)) != len(names):
        msg = f"grounders must have distinct names, got {names}"
        raise ValueError(msg)
    sensors = {g.name: LanguageSensor(proposer or _GivenHypotheses(), g) for g in grounders}
    scores: dict[str, list[CaseScore]] = {name: [] for name in names}
    failures = {name: _Failures() for name in names}
    seconds = dict.fromkeys(names, 0.0)
    referent: list[ReferentScore] = []
    proposer_failures = _Failures()
    per_case: list[dict[str, Any]] = []
    read = skipped = 0

    for index, case in enumerate(tqdm(cases, total=total, disable=not progress, unit="case", desc="eval")):
        read += 1
        truth = case.hypotheses[0] if case.hypotheses else None
        if truth is None and proposer is None:
            skipped += 1  # --proposer gt needs the true hypotheses
            continue
        relation = truth.relation.value if truth is not None else UNKNOWN
        bucket = ambiguity_bucket(case_ambiguity(case))
        true_anchors = frozenset(truth.anchor_ids) if truth is not None else None
        baseline = no_language_nll(case.scene_graph, np.asarray(case.target.position, dtype=np.float64))
        row: dict[str, Any] = {
            "case_id": case.case_id,
            "relation": relation,
            "ambiguity": bucket,
            # JSON has no infinity: null when the target lies outside the map's box.
            "uniform_nll": baseline if math.isfinite(baseline) else None,
        }

        proposal: Proposal | None = None
        proposal_error: BaseException | None = None
        if proposer is None:
            given = case.hypotheses or []
            hypotheses = tuple(
                Hypothesis(tuple(h.anchor_ids), h.relation, weight=1.0 / len(given)) for h in given
            )
        else:
            try:
                proposal = proposer.propose(case.scene_graph, case.utterance)
            except Exception as exc:  # a failing proposer costs this case, not the run
                proposal_error = exc
                proposer_failures.add(case.case_id, exc)
            hypotheses = proposal.hypotheses if proposal is not None else ()
            if proposal is not None and true_anchors is not None:
                weighed = referent_score(bucket, hypotheses, true_anchors)
                referent.append(weighed)
                row["referent"] = {
                    "top1": weighed.top1,
                    "true_hypothesis_nll": true_hypothesis_nll(weighed.weights, weighed.correct)[0],
                    "hypotheses": [[list(h.anchor_ids), h.relation.value, h.weight] for h in hypotheses],
                }

        for grounder in grounders:
            started = time.perf_counter()
            try:
                if proposal_error is not None and not _predicts_mixture(grounder):
                    raise proposal_error
                score = _score_case(
                    grounder,
                    sensors[grounder.name],
                    case,
                    (relation, bucket),
                    hypotheses,
                    proposal,
                    given_truth=proposer is None,
                    uniform_nll=baseline,
                    rng=np.random.default_rng((seed, index)),
                    hdr_samples=hdr_samples,
                )
            except Exception as exc:  # counted and reported: one bad case must not end a long LLM run
                failures[grounder.name].add(case.case_id, exc)
                row[grounder.name] = {"error": f"{type(exc).__name__}: {exc}"}
                continue
            finally:
                seconds[grounder.name] += time.perf_counter() - started
            scores[grounder.name].append(score)
            row[grounder.name] = {
                "nll": score.nll,
                "error_m": float(np.linalg.norm(score.point - score.target)),
                "nees": score.nees,
                "covered": [bool(c) for c in score.covered],
                "components": score.components,
                "nees_full": score.nees_full,
                "better_than_uniform": score.better_than_uniform,
            }
        per_case.append(row)

    metrics: dict[str, Any] = {}
    for name in names:
        metrics[name] = {
            **group_scores(scores[name]),
            "failures": failures[name].to_json(),
            "seconds": round(seconds[name], 3),
        }
    if proposer is not None:
        metrics["referent"] = group_referent(referent)
    metrics["run"] = {
        "read": read,
        "evaluated": len(per_case),
        "skipped_without_truth": skipped,
        "proposer_failures": proposer_failures.to_json(),
    }
    return StaticEvaluation(metrics, per_case)


# ---------------------------------------------------------------------------------------------------------
# The command's whole run: options -> proposer, grounders, cases -> metrics


@dataclass(frozen=True)
class StaticOptions:
    """`vlmap eval static`'s options."""

    cases: Path
    proposer: str = "gt"
    grounder: str = "lsm"
    baselines: bool = False
    max_cases: int | None = None
    seed: int = 0
    hdr_samples: int = DEFAULT_HDR_SAMPLES
    model_dir: Path | None = None
    proposer_params: Path | None = None
    llm: LLMOptions = field(default_factory=LLMOptions)
    progress: bool = True


def method_names(grounder: str, baselines: bool) -> list[str]:
    """The chosen grounder first, then the baselines it is not."""
    names = [grounder]
    if baselines:
        names += [b for b in BASELINES if b != grounder]
    return names


def run_static(options: StaticOptions) -> StaticEvaluation:
    """Build the proposer and grounders (errors here are setup errors: no endpoint, no LSM) and evaluate.

    metrics["config"] records the cases file, proposer (and the implementation behind it), methods, seed,
    Monte Carlo draws, case counts and the LLM proposer's fallbacks.
    """
    if options.max_cases is not None and options.max_cases < 1:
        msg = f"--max-cases must be >= 1, got {options.max_cases}"
        raise InvalidInput(msg, field="--max-cases")
    if options.seed < 0:
        msg = f"--seed must be >= 0, got {options.seed}"
        raise InvalidInput(msg, field="--seed")
    if options.hdr_samples < 100:
        msg = f"--hdr-samples must be >= 100, got {options.hdr_samples}"
        raise InvalidInput(msg, field="--hdr-samples")
    if not options.cases.is_file():
        msg = f"no cases file at {options.cases}"
        raise InvalidInput(msg, field="--cases")
    # Read whole before anything is built or grounded: a bad line stops the run at once, with its number.
    cases = list(islice(read_cases(options.cases), options.max_cases))
    fallbacks: Counter[str] = Counter()
    with ExitStack() as stack:
        proposer = make_proposer(
            options.proposer,
            options.llm,
            stack,
            on_fallback=lambda reason: fallbacks.update([reason]),
            params=options.proposer_params,
        )
        grounders = [
            make_grounder(name, options.llm, stack, options.model_dir)
            for name in method_names(options.grounder, options.baselines)
        ]
        result = evaluate_static(
            cases,
            grounders,
            proposer,
            seed=options.seed,
            hdr_samples=options.hdr_samples,
            progress=options.progress,
            total=len(cases),
        )
    config: dict[str, Any] = {
        "cases": str(options.cases),
        "proposer": options.proposer,
        "proposer_impl": getattr(proposer, "name", "gt"),
        "grounder": options.grounder,
        "methods": [g.name for g in grounders],
        "seed": options.seed,
        "hdr_samples": options.hdr_samples,
        "max_cases": options.max_cases,
        "n": result.metrics["run"]["evaluated"],
        "describe": {g.name: g.describe() for g in grounders},
    }
    if options.proposer == "llm":
        config["llm_fallbacks"] = dict(fallbacks)
    return StaticEvaluation({"config": config, **result.metrics}, result.per_case)
