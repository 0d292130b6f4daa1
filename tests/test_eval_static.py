"""`vlmap eval static`: metric aggregation on hand-made cases with known Gaussians, and the CLI end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.stats import chi2, multivariate_normal

from app.cli import build_parser, main
from app.data.cases import CaseHypothesis, CaseTarget, GroundingCase, read_cases
from app.evaluation import cli as eval_cli
from app.evaluation.metrics import DEFAULT_MASSES, hdr_coverage, nees, no_language_nll
from app.evaluation.static import (
    DEFAULT_HDR_SAMPLES,
    GROUNDERS,
    PROPOSERS,
    StaticEvaluation,
    ambiguity_bucket,
    case_ambiguity,
    chi2_3_cdf,
    evaluate_static,
    expected_calibration_error,
    mixture_coverage,
    reliability_bins,
    run_static,
    true_hypothesis_nll,
    uniform_weights_mixture,
)
from app.grounding.geometric import FixedGrounder
from app.grounding.hypotheses import Hypothesis, Proposal, UtteranceParse
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox, map_box
from app.grounding.relations import Relation
from app.grounding.sensor import Grounding, broad_term
from app.scene_graph.model import SceneGraph
from tests.fake_llm_server import FakeLLMServer, Reply

CASES = Path(__file__).parent / "resources" / "eval" / "cases.jsonl"
N_FIXTURE_CASES = 25
COVARIANCE = np.array([[0.20, 0.05, 0.0], [0.05, 0.10, -0.02], [0.0, -0.02, 0.05]])

ROOM = SceneGraph.model_validate(
    {
        "regions": [{"id": "r0", "name": "kitchen", "center": [0, 0, 1.5], "size": [10, 10, 3]}],
        "objects": [
            {
                "id": "t1",
                "label": "table",
                "center": [1.0, 0.0, 0.4],
                "size": [1.0, 0.6, 0.8],
                "region_id": "r0",
            },
            {
                "id": "t2",
                "label": "table",
                "center": [-3.0, 2.0, 0.4],
                "size": [1.2, 0.8, 0.8],
                "region_id": "r0",
            },
            {
                "id": "s1",
                "label": "sofa",
                "center": [3.0, -2.0, 0.4],
                "size": [2.0, 0.9, 0.8],
                "region_id": "r0",
            },
        ],
    }
)


def make_case(
    index: int, target: np.ndarray, anchors: list[str], relation: str, ambiguity: int | None = None
) -> GroundingCase:
    meta: dict[str, Any] = {} if ambiguity is None else {"ambiguity": ambiguity}
    return GroundingCase(
        case_id=f"case-{index}",
        scene_graph=ROOM,
        utterance=f"case {index}: the cup {relation} the {ROOM.object(anchors[0]).label}",
        target=CaseTarget(label="cup", position=[float(v) for v in target]),
        hypotheses=[CaseHypothesis(anchor_ids=anchors, relation=Relation(relation))],
        meta=meta,
    )


class KnownGaussianGrounder:
    """Answers N(mean_i, COVARIANCE) for case i, with the means chosen by the test."""

    name = "known"
    version = "1"

    def __init__(self, means: dict[str, np.ndarray]) -> None:
        self.means = means

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {}, "checksum": None}

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        return [GaussianMixture.of(Gaussian(self.means[utterance], COVARIANCE)) for _ in hypotheses]


# --- metric pieces --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("count", "bucket"),
    [(1, "1"), (2, "2"), (3, "3-4"), (4, "3-4"), (5, "5+"), (27, "5+"), (0, "unknown"), (None, "unknown")],
)
def test_ambiguity_buckets(count: int | None, bucket: str) -> None:
    assert ambiguity_bucket(count) == bucket


def test_ambiguity_computed_from_the_scene_graph_matches_the_builder() -> None:
    cases = list(read_cases(CASES))
    for case in cases:
        given = case.meta["ambiguity"]
        computed = case_ambiguity(case.model_copy(update={"meta": {}}))
        assert computed == given, case.case_id
    # "between" takes the most over its two anchors: the table is one of two, the sofa alone.
    between = make_case(0, np.zeros(3), ["t1", "s1"], "between")
    assert case_ambiguity(between) == 2
    assert case_ambiguity(make_case(1, np.zeros(3), ["s1"], "on")) == 1


def test_chi2_3_cdf_matches_scipy() -> None:
    xs = np.array([0.0, 0.1, 1.0, 2.366, 3.0, 7.815, 20.0])
    np.testing.assert_allclose([chi2_3_cdf(x) for x in xs], chi2.cdf(xs, 3), atol=1e-12)


def test_single_gaussian_coverage_is_the_chi2_ellipsoid_and_agrees_with_monte_carlo() -> None:
    mixture = GaussianMixture.from_components([1.0], [Gaussian(np.zeros(3), COVARIANCE)])
    chol = np.linalg.cholesky(COVARIANCE)
    rng = np.random.default_rng(3)
    for m in DEFAULT_MASSES:
        radius = math.sqrt(chi2.ppf(m, 3))
        inside = chol @ np.array([0.0, 0.0, 0.97 * radius])  # NEES just below the mass-m quantile
        outside = chol @ np.array([0.0, 1.03 * radius, 0.0])
        for point, expected in ((inside, True), (outside, False)):
            exact = mixture_coverage(mixture, point, rng)
            assert exact[DEFAULT_MASSES.index(m)] == expected
            sampled = hdr_coverage(mixture, point.reshape(1, 3), rng, DEFAULT_MASSES, 50_000)[0]
            np.testing.assert_array_equal(exact, sampled)


def test_ece_by_hand() -> None:
    # Bin [0.9, 1.0]: weights 0.9, 1.0 (mean 0.95), one correct (0.5). Bin [0.2, 0.3): weight 0.2, correct.
    weights = np.array([0.9, 1.0, 0.2])
    correct = np.array([True, False, True])
    counts, confidence, accuracy = reliability_bins(weights, correct)
    assert counts[9] == 2 and counts[2] == 1 and counts.sum() == 3
    assert confidence[9] == pytest.approx(0.95) and accuracy[9] == pytest.approx(0.5)
    expected = (2 / 3) * abs(0.5 - 0.95) + (1 / 3) * abs(1.0 - 0.2)
    assert expected_calibration_error(weights, correct) == pytest.approx(expected)
    assert math.isnan(expected_calibration_error(np.array([]), np.array([], dtype=bool)))


def test_ece_of_calibrated_weights_is_near_zero_and_of_overconfident_ones_large() -> None:
    rng = np.random.default_rng(0)
    weights = rng.uniform(size=50_000)
    calibrated = rng.uniform(size=weights.size) < weights
    assert expected_calibration_error(weights, calibrated) < 0.01
    # Overconfident: the weights are pushed towards 0 and 1 beyond what the outcomes bear out.
    sharpened = np.where(weights > 0.5, 1.0 - 0.3 * (1.0 - weights), 0.3 * weights)
    assert expected_calibration_error(sharpened, calibrated) > 0.1


def test_true_hypothesis_nll() -> None:
    weights = np.array([0.7, 0.2, 0.1])
    assert true_hypothesis_nll(weights, np.array([False, True, False])) == (
        pytest.approx(-math.log(0.2)),
        False,
    )
    # Two hypotheses with the true anchors (e.g. under two relations): their mass adds up.
    assert true_hypothesis_nll(weights, np.array([True, False, True]))[0] == pytest.approx(-math.log(0.8))
    nll, absent = true_hypothesis_nll(weights, np.array([False, False, False]))
    assert absent and nll == pytest.approx(-math.log(1e-6))
    assert true_hypothesis_nll(np.array([]), np.array([], dtype=bool)) == (
        pytest.approx(-math.log(1e-6)),
        True,
    )


# --- aggregation through evaluate_static -------------------------------------------------------------


def test_a_calibrated_grounder_scores_anees_three_nominal_coverage_and_the_reference_nll() -> None:
    rng = np.random.default_rng(7)
    n = 2000
    targets = rng.uniform(-3, 3, size=(n, 3))
    # y - mu ~ N(0, COVARIANCE): the grounder's Gaussian is exactly as uncertain as it claims.
    means = targets - rng.multivariate_normal(np.zeros(3), COVARIANCE, size=n)
    cases = [make_case(i, targets[i], ["t1"], "near", ambiguity=1) for i in range(n)]
    grounder = KnownGaussianGrounder({c.utterance: means[i] for i, c in enumerate(cases)})

    metrics = evaluate_static(cases, [grounder]).metrics["known"]
    overall = metrics["overall"]
    assert overall["n"] == n and overall["anees_n"] == n and overall["unmatched"] == 0
    assert overall["anees"] == pytest.approx(3.0, abs=0.25)  # std of the mean of chi^2(3): sqrt(6/n) = 0.055
    low, high = overall["anees_ci90"]  # every case its own room: the normal interval, +- 1.645 x 0.055
    assert low < overall["anees"] < high and (high - low) / 2 == pytest.approx(
        1.645 * math.sqrt(6 / n), rel=0.2
    )
    for m in DEFAULT_MASSES:
        assert overall["coverage"][str(m)] == pytest.approx(m, abs=0.035)
    reference_nll = -np.mean(
        [multivariate_normal(mu, COVARIANCE).logpdf(y) for mu, y in zip(means, targets, strict=True)]
    )
    assert overall["nll"] == pytest.approx(reference_nll, rel=1e-9)
    assert overall["rmse"] == pytest.approx(math.sqrt(np.mean(np.sum((means - targets) ** 2, axis=1))))
    assert metrics["failures"]["count"] == 0
    assert "uniform_weights_nll" not in overall  # only with a proposer


def test_the_anees_interval_resamples_the_rooms_a_case_file_names() -> None:
    rng = np.random.default_rng(2)
    offsets = {"scene_a": 0.2, "scene_b": 2.0}  # every case of a room errs by its room's offset
    cases, means = [], {}
    for i in range(40):
        room = "scene_a" if i % 2 else "scene_b"
        target = rng.uniform(-3, 3, size=3)
        case = make_case(i, target, ["t1"], "near").model_copy(update={"meta": {"scene_id": room}})
        cases.append(case)
        means[case.utterance] = target - offsets[room] * np.array([1.0, 0.0, 0.0])
    per_case = [float(nees(means[c.utterance], COVARIANCE, np.asarray(c.target.position))[0]) for c in cases]
    room_means = sorted(
        np.mean([v for v, c in zip(per_case, cases, strict=True) if c.meta["scene_id"] == r]) for r in offsets
    )
    overall = evaluate_static(cases, [KnownGaussianGrounder(means)]).metrics["known"]["overall"]
    # Two rooms: resamples aa, ab, bb, so the 5% and 95% points are the two rooms' own ANEES.
    assert overall["anees_ci90"] == pytest.approx(room_means)


def test_fixed_grounder_groups_by_relation_with_hand_computed_errors() -> None:
    specs = [
        (np.array([1.0, 0.0, 1.0]), ["t1"], "on"),  # 0.6 m above t1's centre
        (np.array([1.0, 0.3, 0.8]), ["t1"], "on"),  # 0.5 m
        (np.array([3.0, -1.0, 0.4]), ["s1"], "near"),  # 1.0 m
        (np.array([-1.0, 1.0, 0.4]), ["t1", "t2"], "between"),  # at the midpoint
    ]
    cases = [make_case(i, y, a, r, ambiguity=1) for i, (y, a, r) in enumerate(specs)]
    metrics = evaluate_static(cases, [FixedGrounder()]).metrics["fixed"]
    per_relation = metrics["per_relation"]
    assert list(per_relation) == ["on", "near", "between"]  # the Relation enum's order
    assert [per_relation[r]["n"] for r in per_relation] == [2, 1, 1]
    assert per_relation["on"]["rmse"] == pytest.approx(math.sqrt((0.6**2 + 0.5**2) / 2))
    assert per_relation["near"]["rmse"] == pytest.approx(1.0)
    assert per_relation["between"]["rmse"] == pytest.approx(0.0, abs=1e-12)
    # sigma = 0.1 m: NEES = d^2 / 0.01.
    assert per_relation["on"]["anees"] == pytest.approx((0.36 + 0.25) / 2 / 0.01)
    assert per_relation["near"]["coverage"] == {"0.5": 0.0, "0.9": 0.0, "0.95": 0.0}
    assert per_relation["between"]["coverage"] == {"0.5": 1.0, "0.9": 1.0, "0.95": 1.0}
    assert metrics["overall"]["n"] == 4 and list(metrics["per_ambiguity"]) == ["1"]


class ScriptedProposer:
    """The true anchor with weight `true_weight`, the other table with the rest; nothing for "sofa" cases."""

    name = "scripted"

    def __init__(self, true_weight: float) -> None:
        self.true_weight = true_weight

    parse = UtteranceParse(target="cup", relation=Relation.ON, anchor_phrases=("table",))

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        parse = self.parse
        if "sofa" in utterance:
            return Proposal(parse, (), grounded=False, reason="no sofa")
        return Proposal(
            parse,
            (
                Hypothesis(("t1",), Relation.ON, weight=self.true_weight),
                Hypothesis(("t2",), Relation.ON, weight=1.0 - self.true_weight),
            ),
            background=0.0,  # the scoring is under test here, not the broad term
        )


def test_referent_metrics_and_uniform_weights_nll_with_a_proposer() -> None:
    targets = [np.array([1.0, 0.1, 0.9]), np.array([0.9, -0.1, 0.85]), np.array([3.0, -2.0, 0.9])]
    cases = [
        make_case(0, targets[0], ["t1"], "on", ambiguity=2),
        make_case(1, targets[1], ["t1"], "on", ambiguity=2),
        make_case(2, targets[2], ["s1"], "on", ambiguity=1),  # the proposer finds no anchor
    ]
    result = evaluate_static(cases, [FixedGrounder()], ScriptedProposer(true_weight=0.8), seed=1)
    referent = result.metrics["referent"]
    assert referent["overall"]["n"] == 3 and referent["overall"]["ungrounded"] == 1
    assert referent["overall"]["absent"] == 1
    assert referent["overall"]["top1_accuracy"] == pytest.approx(2 / 3)
    floor = -math.log(1e-6)
    assert referent["overall"]["true_hypothesis_nll"] == pytest.approx((2 * -math.log(0.8) + floor) / 3)
    # Pairs (0.8, correct) x2 and (0.2, wrong) x2: ECE = 0.5 * |1 - 0.8| + 0.5 * |0 - 0.2|.
    assert referent["overall"]["ece"] == pytest.approx(0.2)
    assert referent["per_ambiguity"]["2"]["top1_accuracy"] == 1.0
    assert referent["per_ambiguity"]["1"]["top1_accuracy"] == 0.0

    fixed = result.metrics["fixed"]["overall"]
    assert fixed["anees_n"] == 2 and fixed["unmatched"] == 1  # the broad prior holds no true anchor
    centres = [np.array([1.0, 0.0, 0.4]), np.array([-3.0, 2.0, 0.4])]
    cov = np.eye(3) * 0.01

    def mixture_nll(y: np.ndarray, weights: tuple[float, float]) -> float:
        return -math.log(
            sum(w * multivariate_normal(c, cov).pdf(y) for w, c in zip(weights, centres, strict=True))
        )

    nll = [
        mixture_nll(targets[0], (0.8, 0.2)),
        mixture_nll(targets[1], (0.8, 0.2)),
        float(
            -broad_term(1.0, ROOM, Proposal(ScriptedProposer.parse, ()), map_box(ROOM)).logpdf(
                targets[2][None]
            )[0]
        ),  # no anchor
    ]
    uniform = [mixture_nll(targets[0], (0.5, 0.5)), mixture_nll(targets[1], (0.5, 0.5)), nll[2]]
    assert fixed["nll"] == pytest.approx(np.mean(nll), rel=1e-6)
    assert fixed["uniform_weights_nll"] == pytest.approx(np.mean(uniform), rel=1e-6)
    assert fixed["uniform_weights_nll"] > fixed["nll"]
    rows = {row["case_id"]: row for row in result.per_case}
    assert rows["case-0"]["referent"]["top1"] is True
    assert rows["case-2"]["fixed"]["components"] == 1  # the broad prior: uniform boxes and its wide Gaussian


class MixtureGrounder:
    """Predicts a whole mixture itself (like LLM-E2E): two components, the heavier one far from the truth."""

    name = "mixture"
    version = "1"

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {}, "checksum": None}

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        msg = "a mixture-predicting grounder is asked for its mixture, not per hypothesis"
        raise AssertionError(msg)

    def ground_mixture(self, scene_graph: SceneGraph, utterance: str) -> GaussianMixture:
        return GaussianMixture.from_components(
            [0.3, 0.7],
            [
                Gaussian(np.array([1.0, 0.0, 1.0]), np.eye(3) * 0.04),
                Gaussian(np.array([-3.0, 2.0, 1.0]), np.eye(3)),
            ],
        )


def test_a_mixture_predicting_grounder_is_matched_by_the_nearest_component() -> None:
    target = np.array([1.2, 0.0, 1.0])
    case = make_case(0, target, ["t1"], "on", ambiguity=2)
    gt = evaluate_static([case], [MixtureGrounder()]).metrics["mixture"]["overall"]
    assert gt["anees"] == pytest.approx(0.2**2 / 0.04)  # the component nearest t1
    assert gt["rmse"] == pytest.approx(0.2)  # with the true hypothesis given: the matched component
    builtin = evaluate_static([case], [MixtureGrounder()], ScriptedProposer(0.5)).metrics["mixture"][
        "overall"
    ]
    assert builtin["rmse"] == pytest.approx(float(np.linalg.norm(target - [-3.0, 2.0, 1.0])))  # heaviest
    assert "uniform_weights_nll" not in builtin


class FlakyGrounder(FixedGrounder):
    name = "flaky"

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        if "case 1:" in utterance:
            msg = "endpoint hiccup"
            raise RuntimeError(msg)
        return super().ground(scene_graph, utterance, hypotheses)


def test_per_case_failures_are_counted_not_fatal() -> None:
    cases = [make_case(i, np.array([1.0, 0.0, 0.9]), ["t1"], "on", ambiguity=1) for i in range(3)]
    metrics = evaluate_static(cases, [FlakyGrounder(), FixedGrounder()]).metrics
    assert metrics["flaky"]["overall"]["n"] == 2
    assert metrics["flaky"]["failures"]["count"] == 1
    assert "case-1: RuntimeError: endpoint hiccup" in metrics["flaky"]["failures"]["examples"][0]
    assert metrics["fixed"]["overall"]["n"] == 3 and metrics["fixed"]["failures"]["count"] == 0


# --- the no-language baseline and the served densities -------------------------------------------------

# ROOM's object boxes: t1 x [0.5, 1.5], y [-0.3, 0.3]; t2 x [-3.6, -2.4], y [1.6, 2.4]; s1 x [2, 4],
# y [-2.45, -1.55]; all z [0, 0.8]. The region (10 x 10 x 3) does not count.
ROOM_BOX_VOLUME = (4.0 + 3.6) * (2.4 + 2.45) * 0.8


def test_map_box_encloses_the_yawed_object_boxes_and_not_the_regions() -> None:
    half = 1.5 / math.sqrt(2.0)  # a 2 x 1 box turned by 45 degrees: half extent (2 + 1) / 2 cos 45 per axis
    scene = SceneGraph.model_validate(
        {
            "regions": [{"id": "r0", "name": "hall", "center": [0, 0, 2], "size": [20, 20, 5]}],
            "objects": [
                {"id": "a", "label": "desk", "center": [0, 0, 0.5], "size": [2, 1, 1], "yaw": math.pi / 4},
                {"id": "b", "label": "box", "center": [4, 0, 0.25], "size": [1, 1, 0.5], "region_id": "r0"},
            ],
        }
    )
    box = map_box(scene)
    np.testing.assert_allclose(box.low, [-half, -half, 0.0])
    np.testing.assert_allclose(box.high, [4.5, half, 1.0])
    volume = (4.5 + half) * (2 * half) * 1.0
    assert box.volume == pytest.approx(volume)
    assert no_language_nll(scene, np.array([1.0, 0.0, 0.5])) == pytest.approx(math.log(volume))
    assert map_box(ROOM).volume == pytest.approx(ROOM_BOX_VOLUME)


def test_map_box_of_a_flat_scene_is_grown_to_a_tenth_of_a_metre() -> None:
    scene = SceneGraph.model_validate(
        {
            "objects": [
                {"id": "a", "label": "rug", "center": [0, 0, 0.01], "size": [2, 1, 0.02]},
                {"id": "b", "label": "mat", "center": [3, 0, 0.01], "size": [1, 1, 0.02]},
            ]
        }
    )
    box = map_box(scene)
    np.testing.assert_allclose(box.low, [-1.0, -0.5, -0.04])  # z [0, 0.02] grown about its centre 0.01
    np.testing.assert_allclose(box.high, [3.5, 0.5, 0.06])
    assert box.volume == pytest.approx(4.5 * 1.0 * 0.1)
    assert no_language_nll(scene, np.array([0.0, 0.0, 0.05])) == pytest.approx(math.log(0.45))
    assert no_language_nll(scene, np.array([0.0, 0.0, 0.07])) == math.inf  # above the grown box
    assert map_box(SceneGraph()).volume == pytest.approx(1.0)  # no object: the unit box


def test_better_than_uniform_counts_and_a_target_outside_the_map_box() -> None:
    near = np.array([0.0, 0.0, 0.0])
    far = np.array([0.0, 0.0, 3.0])  # 3 m off along z (variance 0.05): NLL about 90 nats
    specs = [  # (target, the grounder's mean minus the target, relation)
        (np.array([1.0, 0.0, 0.4]), near, "on"),
        (np.array([-3.0, 2.0, 0.7]), near, "on"),
        (np.array([3.0, -2.0, 0.2]), far, "near"),
        (np.array([3.0, -2.0, 0.5]), near, "near"),
        (np.array([1.0, 0.0, 0.9]), near, "on"),  # above every object box: U(y) = 0
    ]
    cases = [make_case(i, y, ["t1"], r, ambiguity=1) for i, (y, _, r) in enumerate(specs)]
    means = {c.utterance: y + d for c, (y, d, _) in zip(cases, specs, strict=True)}
    result = evaluate_static(cases, [KnownGaussianGrounder(means)])
    log_volume = math.log(ROOM_BOX_VOLUME)
    nll = [-multivariate_normal(y + d, COVARIANCE).logpdf(y) for y, d, _ in specs]
    assert nll[0] < log_volume < nll[2]  # the near guesses beat no language, the far one does not
    overall = result.metrics["known"]["overall"]
    assert overall["better_than_uniform"] == pytest.approx(4 / 5)  # the outside case counts as better
    assert overall["uniform_outside"] == 1
    assert overall["uniform_nll"] == pytest.approx(log_volume)  # the mean over the four inside the box
    excess = [v - log_volume for v in nll[:4]]
    assert overall["nll_minus_uniform"] == pytest.approx(np.mean(excess))
    assert overall["worst_excess_over_uniform"] == pytest.approx(nll[2] - log_volume)
    per_relation = result.metrics["known"]["per_relation"]
    on, by_near = per_relation["on"], per_relation["near"]
    assert on["better_than_uniform"] == 1.0 and on["uniform_outside"] == 1
    assert on["worst_excess_over_uniform"] == pytest.approx(max(excess[:2]))
    assert by_near["better_than_uniform"] == 0.5 and by_near["uniform_outside"] == 0
    assert result.metrics["known"]["per_ambiguity"]["1"]["better_than_uniform"] == pytest.approx(4 / 5)
    rows = result.per_case
    assert rows[0]["uniform_nll"] == pytest.approx(log_volume) and rows[4]["uniform_nll"] is None
    assert [r["known"]["better_than_uniform"] for r in rows] == [True, True, False, True, True]


def moment_matched(
    weights: list[float], means: list[np.ndarray], covs: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """mu = sum w_k mu_k, Sigma = sum w_k (Sigma_k + mu_k mu_k^T) - mu mu^T, written out."""
    mu = sum(w * m for w, m in zip(weights, means, strict=True))
    second = sum(w * (c + np.outer(m, m)) for w, m, c in zip(weights, means, covs, strict=True))
    return mu, second - np.outer(mu, mu)


class CoreAndTailGrounder:
    """Each hypothesis's density: a tight core at the anchor's centre + 0.3 m and a wide tail below it."""

    name = "core-tail"
    version = "1"
    core, tail = np.eye(3) * 0.01, np.eye(3) * 0.5
    offset, drop = np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, -0.5])

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {}, "checksum": None}

    def density(self, scene_graph: SceneGraph, h: Hypothesis) -> GaussianMixture:
        centre = np.asarray(scene_graph.object(h.anchor_ids[0]).center) + self.offset
        return GaussianMixture.from_components(
            [0.7, 0.3], [Gaussian(centre, self.core), Gaussian(centre + self.drop, self.tail)]
        )

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        return [self.density(scene_graph, h) for h in hypotheses]


def test_nees_and_point_of_a_two_component_density_are_its_moment_matched_ones() -> None:
    target = np.array([1.1, 0.2, 0.5])
    case = make_case(0, target, ["t1"], "on", ambiguity=2)
    g = CoreAndTailGrounder()
    centre = np.array([1.0, 0.0, 0.4]) + g.offset
    mu, sigma = moment_matched([0.7, 0.3], [centre, centre + g.drop], [g.core, g.tail])
    expected = float((target - mu) @ np.linalg.inv(sigma) @ (target - mu))
    core_only = float((target - centre) @ np.linalg.inv(g.core) @ (target - centre))
    assert abs(expected - core_only) > 1.0  # one component's NEES (the old score) would be far off

    gt = evaluate_static([case], [g]).metrics["core-tail"]["overall"]
    assert gt["anees"] == pytest.approx(expected, rel=1e-9)
    assert gt["anees_full"] == pytest.approx(expected, rel=1e-9)  # one hypothesis: the whole mixture
    assert gt["rmse"] == pytest.approx(float(np.linalg.norm(mu - target)))

    # With a proposer (t1 at 0.8, t2 at 0.2): NEES of t1's density, the point its mean (the heavier one),
    # NEES_full of the whole two-hypothesis mixture.
    result = evaluate_static([case], [g], ScriptedProposer(true_weight=0.8))
    scored = result.metrics["core-tail"]["overall"]
    assert scored["anees"] == pytest.approx(expected, rel=1e-9)
    assert scored["rmse"] == pytest.approx(float(np.linalg.norm(mu - target)))
    other = np.array([-3.0, 2.0, 0.4]) + g.offset
    full_mu, full_sigma = moment_matched(
        [0.56, 0.24, 0.14, 0.06],
        [centre, centre + g.drop, other, other + g.drop],
        [g.core, g.tail, g.core, g.tail],
    )
    full = float((target - full_mu) @ np.linalg.inv(full_sigma) @ (target - full_mu))
    assert scored["anees_full"] == pytest.approx(full, rel=1e-9)
    assert result.per_case[0]["core-tail"]["nees_full"] == pytest.approx(full, rel=1e-9)
    assert result.per_case[0]["core-tail"]["components"] == 4


def test_uniform_weights_keep_the_sensors_broad_term_and_spread_the_rest_evenly() -> None:
    g = CoreAndTailGrounder()
    densities = [g.density(ROOM, Hypothesis((a,), Relation.ON)) for a in ("t1", "t2")]
    broad = GaussianMixture.from_components([], [], boxes=[map_box(ROOM)], box_weights=[1.0])
    served = GaussianMixture.combine([0.9, 0.1], [GaussianMixture.combine([0.8, 0.2], densities), broad])
    parse = UtteranceParse(target="cup", relation=Relation.ON, anchor_phrases=("table",))
    grounding = Grounding(Proposal(parse, ()), (), served, {}, tuple(densities), 0.1, broad)
    even = uniform_weights_mixture(grounding)
    points = np.array([[1.3, 0.0, 0.4], [-2.7, 2.0, 0.0], [3.0, -2.0, 0.5], [0.0, 0.0, 2.0]])
    p = [np.exp(d.logpdf(points)) for d in densities]
    expected = 0.9 * (0.5 * p[0] + 0.5 * p[1]) + 0.1 * np.exp(map_box(ROOM).logpdf(points))
    np.testing.assert_allclose(np.exp(even.logpdf(points)), expected, rtol=1e-12)
    bare = Grounding(Proposal(parse, ()), (), broad, {}, (), 1.0, broad)
    assert uniform_weights_mixture(bare) is broad


class ProposerOnly:
    """Any utterance: t1 at 0.6 and t2 at 0.4 (the case itself names no anchor, like Nr3D's)."""

    name = "proposer-only"

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        parse = UtteranceParse(target="cup", relation=Relation.NEAR, anchor_phrases=("table",))
        return Proposal(
            parse,
            (Hypothesis(("t1",), Relation.NEAR, 0.6), Hypothesis(("t2",), Relation.NEAR, 0.4)),
            background=0.0,
        )


def test_a_case_without_true_hypotheses_is_scored_on_the_full_mixture() -> None:
    target = np.array([1.2, 0.1, 0.3])
    case = make_case(0, target, ["t1"], "near").model_copy(update={"hypotheses": []})
    g = CoreAndTailGrounder()
    skipped = evaluate_static([case], [g])  # --proposer gt needs true hypotheses
    assert skipped.metrics["run"]["skipped_without_truth"] == 1 and skipped.per_case == []

    result = evaluate_static([case], [g], ProposerOnly())
    overall = result.metrics["core-tail"]["overall"]
    densities = [g.density(ROOM, Hypothesis((a,), Relation.NEAR)) for a in ("t1", "t2")]
    served = GaussianMixture.combine([0.6, 0.4], densities)
    assert overall["n"] == 1 and overall["anees"] is None and overall["unmatched"] == 1
    assert overall["nll"] == pytest.approx(float(-served.logpdf(target)[0]))
    assert overall["rmse"] == pytest.approx(float(np.linalg.norm(densities[0].mean() - target)))
    mu, sigma = served.mean(), served.covariance()
    assert overall["anees_full"] == pytest.approx(float((target - mu) @ np.linalg.inv(sigma) @ (target - mu)))
    assert overall["better_than_uniform"] == 1.0
    assert result.metrics["core-tail"]["per_relation"].keys() == {"unknown"}
    assert result.metrics["referent"]["overall"]["n"] == 0  # no truth to score the weights against


class CoreUnderBoxGrounder:
    """Answers, for case i, a Gaussian core at the case's mean under a broad box holding 40% of the mass."""

    name = "core-box"
    version = "1"
    box = UniformBox(np.array([-4.0, -3.0, 0.0]), np.array([4.0, 3.0, 2.0]))

    def __init__(self, means: dict[str, np.ndarray]) -> None:
        self.means = means

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {}, "checksum": None}

    def density(self, mean: np.ndarray) -> GaussianMixture:
        return GaussianMixture.of(Gaussian(mean, COVARIANCE)).with_background(0.4, self.box)

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        return [self.density(self.means[utterance]) for _ in hypotheses]


def test_a_box_holding_density_is_covered_at_the_nominal_rate_through_the_evaluation() -> None:
    """Targets drawn from the served density itself: coverage m at every mass m (one Gaussian and a box
    must not take the single Gaussian's exact chi^2 path, nor count the whole plateau in)."""
    rng = np.random.default_rng(11)
    n = 1500
    means = rng.uniform([-1, -1, 0.5], [1, 1, 1.5], size=(n, 3))
    grounder = CoreUnderBoxGrounder({})
    targets = np.stack([grounder.density(m).sample(1, rng)[0] for m in means])
    cases = [make_case(i, targets[i], ["t1"], "near", ambiguity=1) for i in range(n)]
    grounder.means = {c.utterance: means[i] for i, c in enumerate(cases)}
    overall = evaluate_static(cases, [grounder], hdr_samples=2000).metrics["core-box"]["overall"]
    for m in DEFAULT_MASSES:  # binomial std error <= 0.013 at n = 1500, plus the thresholds' own wobble
        assert overall["coverage"][str(m)] == pytest.approx(m, abs=0.05)


# --- the CLI ------------------------------------------------------------------------------------------


def test_cli_choices_match_the_evaluation() -> None:
    assert eval_cli.PROPOSER_CHOICES == PROPOSERS
    assert eval_cli.GROUNDER_CHOICES == GROUNDERS
    args = build_parser().parse_args(["eval", "static", "--cases", "c.jsonl", "--out", "out"])
    assert args.hdr_samples == DEFAULT_HDR_SAMPLES and args.grounder == "lsm" and args.proposer == "gt"


def run_cli(*args: str) -> int:
    return main(["eval", "static", "--cases", str(CASES), "--no-progress", *args])


def is_png(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_gt_with_baselines_writes_metrics_report_and_plots(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "gt"
    assert run_cli("--grounder", "geometric", "--baselines", "--proposer", "gt", "--out", str(out)) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["methods"] == ["geometric", "fixed"]
    assert metrics["config"]["n"] == N_FIXTURE_CASES and metrics["config"]["proposer"] == "gt"
    for method in ("geometric", "fixed"):
        overall = metrics[method]["overall"]
        assert overall["n"] == N_FIXTURE_CASES and metrics[method]["failures"]["count"] == 0
        assert set(overall["coverage"]) == {"0.5", "0.9", "0.95"}
        assert overall["anees_n"] == N_FIXTURE_CASES
        assert set(metrics[method]["per_relation"]) == {r.value for r in Relation}
        assert list(metrics[method]["per_ambiguity"]) == ["1", "2", "3-4", "5+"]
        assert sum(g["n"] for g in metrics[method]["per_relation"].values()) == N_FIXTURE_CASES
    assert "referent" not in metrics
    # The fixed 0.1 m baseline is the overconfident one.
    assert metrics["fixed"]["overall"]["anees"] > metrics["geometric"]["overall"]["anees"]

    report = (out / "report.md").read_text()
    assert "| geometric | 25 |" in report and "| fixed | 25 |" in report and "## Per relation" in report
    assert report in capsys.readouterr().out
    assert is_png(out / "anees_per_relation.png") and is_png(out / "coverage.png")
    assert not (out / "reliability.png").exists()
    rows = [json.loads(line) for line in (out / "per_case.jsonl").read_text().splitlines()]
    assert len(rows) == N_FIXTURE_CASES and {"geometric", "fixed"} <= set(rows[0])


def test_cli_output_that_fails_half_way_leaves_the_previous_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "fixed"
    assert run_cli("--grounder", "fixed", "--max-cases", "3", "--out", str(out)) == 0
    before = (out / "per_case.jsonl").read_bytes()

    def unwritable_first_row(options: Any) -> StaticEvaluation:
        result = run_static(options)
        return StaticEvaluation(result.metrics, [{"case_id": "x", "fixed": object()}, *result.per_case])

    monkeypatch.setattr("app.evaluation.static.run_static", unwritable_first_row)
    with pytest.raises(TypeError, match="not JSON serializable"):
        run_cli("--grounder", "fixed", "--max-cases", "3", "--out", str(out))
    assert (out / "per_case.jsonl").read_bytes() == before  # not emptied
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # nor temporary files left


def test_cli_builtin_proposer_adds_referent_metrics(tmp_path: Path) -> None:
    out = tmp_path / "builtin"
    assert (
        run_cli("--grounder", "fixed", "--proposer", "builtin", "--max-cases", "12", "--out", str(out)) == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["n"] == 12 and metrics["config"]["methods"] == ["fixed"]
    referent = metrics["referent"]
    assert referent["overall"]["n"] == 12
    assert 0.0 <= referent["overall"]["top1_accuracy"] <= 1.0
    assert 0.0 <= referent["overall"]["ece"] <= 1.0
    assert len(referent["overall"]["reliability"]) == 10
    assert sum(g["n"] for g in referent["per_ambiguity"].values()) == 12
    assert "uniform_weights_nll" in metrics["fixed"]["overall"]
    report = (out / "report.md").read_text()
    assert "## Referent" in report and "NLL, uniform w" in report
    assert is_png(out / "reliability.png")


# Keys of metrics.json and per_case.jsonl as other tools read them before the no-language baseline came
# (taken from a run of that code): they stay, new keys come beside them.
OLD_TOP_KEYS = {"config", "referent", "run"}
OLD_CONFIG_KEYS = {
    *("cases", "describe", "grounder", "hdr_samples", "max_cases", "methods", "n", "proposer"),
    *("proposer_impl", "seed"),
}
OLD_RUN_KEYS = {"evaluated", "proposer_failures", "read", "skipped_without_truth"}
OLD_METHOD_KEYS = {"failures", "overall", "per_ambiguity", "per_relation", "seconds"}
OLD_SUMMARY_KEYS = {"anees", "anees_n", "coverage", "n", "nll", "nll_median", "rmse", "unmatched"}
OLD_REFERENT_KEYS = {"absent", "ece", "mean_hypotheses", "n", "top1_accuracy", "true_hypothesis_nll"}
OLD_ROW_KEYS = {"ambiguity", "case_id", "relation"}
OLD_ROW_METHOD_KEYS = {"components", "covered", "error_m", "nees", "nll"}
NEW_SUMMARY_KEYS = {
    *("uniform_nll", "uniform_outside", "better_than_uniform", "nll_minus_uniform"),
    *("worst_excess_over_uniform", "anees_full", "anees_ci90"),
}


def strict_json(text: str) -> Any:
    """json.loads refusing NaN and Infinity, which strict readers of the contract cannot parse."""

    def refuse(name: str) -> None:
        raise ValueError(name)

    return json.loads(text, parse_constant=refuse)


def test_cli_output_keeps_every_old_key_and_adds_the_baseline(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "compat"
    args = ("--grounder", "geometric", "--baselines", "--proposer", "builtin", "--max-cases", "10")
    assert run_cli(*args, "--out", str(out)) == 0
    metrics = strict_json((out / "metrics.json").read_text())
    assert set(metrics) >= OLD_TOP_KEYS
    assert set(metrics["config"]) >= OLD_CONFIG_KEYS and set(metrics["run"]) >= OLD_RUN_KEYS
    assert OLD_REFERENT_KEYS | {"reliability", "ungrounded"} <= set(metrics["referent"]["overall"])
    for method in ("geometric", "fixed"):
        assert set(metrics[method]) >= OLD_METHOD_KEYS
        groups = [
            metrics[method]["overall"],
            *metrics[method]["per_relation"].values(),
            *metrics[method]["per_ambiguity"].values(),
        ]
        for summary in groups:
            assert OLD_SUMMARY_KEYS | {"uniform_weights_nll"} | NEW_SUMMARY_KEYS <= set(summary)
            assert set(summary["coverage"]) == {"0.5", "0.9", "0.95"}
            assert 0.0 <= summary["better_than_uniform"] <= 1.0
    rows = [strict_json(line) for line in (out / "per_case.jsonl").read_text().splitlines()]
    assert len(rows) == 10
    for row in rows:
        assert OLD_ROW_KEYS | {"referent", "uniform_nll"} <= set(row)
        for method in ("geometric", "fixed"):
            assert OLD_ROW_METHOD_KEYS | {"better_than_uniform", "nees_full"} <= set(row[method])
            assert row[method]["better_than_uniform"] == (
                row["uniform_nll"] is None or row[method]["nll"] < row["uniform_nll"]
            )
    report = (out / "report.md").read_text()
    assert "NLL U" in report and "< U" in report and "## Against no language" in report
    assert "| all | geometric | 10 |" in report and "worst excess" in report
    assert report in capsys.readouterr().out
    assert is_png(out / "nll_minus_uniform.png")


def test_cli_lsm_without_weights_fails_clearly(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        run_cli("--grounder", "lsm", "--model-dir", str(tmp_path), "--out", str(tmp_path / "out"))
    message = str(exc.value)
    assert "no LSM checkpoint" in message and str(tmp_path) in message and "--model-dir" in message
    assert not (tmp_path / "out").exists()


def test_cli_a_malformed_case_line_stops_the_run_before_any_grounding(tmp_path: Path) -> None:
    lines = CASES.read_text(encoding="utf-8").splitlines()
    broken = tmp_path / "cases.jsonl"
    broken.write_text("\n".join([*lines[:2], '{"case_id": "x"', *lines[2:]]) + "\n", encoding="utf-8")
    with pytest.raises(SystemExit) as exc:
        run_cli("--grounder", "fixed", "--cases", str(broken), "--out", str(tmp_path / "out"))
    assert f"{broken}:3: not a grounding case" in str(exc.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("option", "value"), [("--seed", "-1"), ("--hdr-samples", "10")])
def test_cli_a_bad_number_is_named(tmp_path: Path, option: str, value: str) -> None:
    with pytest.raises(SystemExit) as exc:
        run_cli("--grounder", "fixed", option, value, "--out", str(tmp_path / "out"))
    assert f"{option} must be >= " in str(exc.value) and f"got {value}" in str(exc.value)


@pytest.mark.parametrize(
    "choice", [("--proposer", "llm"), ("--grounder", "scaffolded-llm"), ("--grounder", "llm-e2e")]
)
def test_cli_llm_without_an_endpoint_fails_clearly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, choice: tuple[str, str]
) -> None:
    for name in ("VLMAP_LLM_URL", "VLMAP_LLM_MODEL", "VLMAP_LLM_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    args = ("--grounder", "geometric", *choice) if choice[0] == "--proposer" else choice
    with pytest.raises(SystemExit) as exc:
        run_cli(*args, "--out", str(tmp_path / "out"))
    assert "needs an LLM endpoint" in str(exc.value) and "--llm-url" in str(exc.value)


def test_cli_llm_proposer_against_a_local_server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cases = [c for c in read_cases(CASES) if c.hypotheses and c.hypotheses[0].relation is Relation.ON][:2]
    subset = tmp_path / "cases.jsonl"
    subset.write_text("".join(c.model_dump_json() + "\n" for c in cases))
    truth = cases[0].hypotheses[0] if cases[0].hypotheses else None
    assert truth is not None
    good = {
        "hypotheses": [
            {
                "utterance": cases[0].utterance,
                "referred_object_id": truth.anchor_ids,
                "region_id": cases[0].scene_graph.object(truth.anchor_ids[0]).region_id,
                "confidence": 0.9,
            }
        ]
    }
    monkeypatch.setenv("VLMAP_LLM_MODEL", "fake-chat-1")
    with FakeLLMServer() as server:
        server.script(Reply(content=json.dumps(good)), Reply(content="no JSON here"))
        out = tmp_path / "out"
        code = main(
            [
                *("eval", "static", "--cases", str(subset), "--proposer", "llm", "--grounder", "geometric"),
                *("--llm-url", server.base_url, "--out", str(out), "--no-progress"),
            ]
        )
        assert len(server.requests) == 2
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["llm_fallbacks"] == {"malformed_reply": 1}
    assert metrics["geometric"]["overall"]["n"] == 2
    assert metrics["referent"]["overall"]["n"] == 2
    rows = [json.loads(line) for line in (out / "per_case.jsonl").read_text().splitlines()]
    assert rows[0]["referent"]["top1"] is True
    assert rows[0]["referent"]["hypotheses"] == [[list(truth.anchor_ids), "on", 1.0]]
