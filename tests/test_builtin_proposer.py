"""The built-in referent proposer: candidates, features, calibrated weights, fitting, shipped parameters."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.data.templates import LABEL_SYNONYMS
from app.errors import ModelUnavailable
from app.grounding.builtin import (
    DEFAULT_PARAMS_PATH,
    BuiltinProposer,
    ProposerParams,
    lexical_match,
    regions_for_phrase,
)
from app.grounding.geometric import GeometricGrounder
from app.grounding.interfaces import HypothesisProposer
from app.grounding.referent_features import (
    FEATURES,
    SceneBoxes,
    attribute_scores,
    between_mask,
    related_mask,
)
from app.grounding.referent_fit import (
    CaseRows,
    fit_conditional_logit,
    fit_proposer,
    fit_temperature,
    logit_loss,
    logit_problem,
    proposal_weights,
    summary_table,
)
from app.grounding.relations import Relation
from app.grounding.sensor import LanguageSensor
from app.lsm.text_encoder import TextEncoder
from app.scene_graph.model import SceneGraph

RESOURCES = Path(__file__).parent / "resources" / "proposer"


@pytest.fixture(scope="module")
def encoder() -> TextEncoder:
    return TextEncoder()


@pytest.fixture(scope="module")
def proposer(encoder: TextEncoder) -> BuiltinProposer:
    return BuiltinProposer.load(encoder)


def obj(
    oid: str, label: str, center: list[float], size: list[float], region: str | None = None, **attrs: Any
):
    return {
        "id": oid,
        "label": label,
        "center": center,
        "size": size,
        "region_id": region,
        "attributes": attrs,
    }


def scene(objects: list[dict[str, Any]], regions: list[dict[str, Any]] | None = None) -> SceneGraph:
    return SceneGraph.model_validate({"regions": regions or [], "objects": objects})


def room(rid: str, name: str, x: float, z: float = 1.25) -> dict[str, Any]:
    return {"id": rid, "name": name, "center": [x, 0.0, z], "size": [6.0, 6.0, 2.5]}


TABLE = [1.2, 0.8, 0.75]
CHAIR = [0.5, 0.5, 0.9]


def two_rooms() -> SceneGraph:
    """The same table with two chairs in a kitchen and (mirrored) in a bedroom, plus a sofa."""
    objects = []
    for rid, x in (("k", -5.0), ("b", 5.0)):
        objects += [
            obj(f"{rid}-table", "table", [x, 0.0, 0.375], TABLE, rid),
            obj(f"{rid}-chair1", "chair", [x - 1.0, 0.0, 0.45], CHAIR, rid),
            obj(f"{rid}-chair2", "chair", [x + 1.0, 0.0, 0.45], CHAIR, rid),
        ]
    return scene(objects, [room("k", "kitchen", -5.0), room("b", "bedroom", 5.0)])


def weights_by_anchor(proposal) -> dict[tuple[str, ...], float]:
    return {h.anchor_ids: h.weight for h in proposal.hypotheses}


# --- the proposer -------------------------------------------------------------------------------------------


def test_is_a_hypothesis_proposer(proposer: BuiltinProposer) -> None:
    assert isinstance(proposer, HypothesisProposer)
    assert proposer.name == "builtin"


def test_two_identical_tables_share_the_weight(proposer: BuiltinProposer) -> None:
    proposal = proposer.propose(two_rooms(), "I left my backpack on the table")
    weights = weights_by_anchor(proposal)
    assert set(weights) == {("k-table",), ("b-table",)}
    assert weights[("k-table",)] == pytest.approx(weights[("b-table",)], abs=0.02)
    assert all(h.relation is Relation.ON for h in proposal.hypotheses)
    assert proposal.grounded and proposal.reason is None


def test_a_region_mention_picks_the_table_in_that_room(proposer: BuiltinProposer) -> None:
    proposal = proposer.propose(two_rooms(), "I left my backpack on the table in the kitchen")
    assert proposal.parse.region_phrase == "kitchen"
    assert proposal.hypotheses[0].anchor_ids == ("k-table",)
    assert proposal.hypotheses[0].weight > 0.9
    assert proposal.hypotheses[0].region_id == "k"


def test_a_region_without_the_anchor_is_ignored_and_said(proposer: BuiltinProposer) -> None:
    graph = two_rooms()
    graph.objects.append(
        graph.objects[0].model_copy(update={"id": "sofa", "label": "sofa", "region_id": "b"})
    )
    proposal = proposer.propose(graph, "the remote is on the sofa in the kitchen")
    assert [h.anchor_ids for h in proposal.hypotheses] == [("sofa",)]
    assert proposal.extra["region_ignored"] == 1.0


def test_storey_words_pick_regions_by_height() -> None:
    graph = scene(
        [], [room("up", "bedroom", 0.0, z=4.0), room("down", "bedroom", 0.0), room("k", "kitchen", 8.0)]
    )
    assert regions_for_phrase(graph, "upstairs bedroom") == {"up"}
    assert regions_for_phrase(graph, "downstairs") == {"down", "k"}
    assert regions_for_phrase(graph, "kitchen") == {"k"}
    assert regions_for_phrase(graph, "garage") is None


def test_an_attribute_picks_the_object_that_carries_it(proposer: BuiltinProposer) -> None:
    graph = scene(
        [
            obj("white", "table", [0.0, 0.0, 0.375], TABLE, color="white"),
            obj("brown", "table", [4.0, 0.0, 0.375], TABLE, color="brown"),
        ]
    )
    proposal = proposer.propose(graph, "the mug is on the white table")
    assert proposal.parse.attributes == ("white",)
    assert proposal.hypotheses[0].anchor_ids == ("white",)
    assert proposal.hypotheses[0].weight > 0.9


def test_a_size_word_ranks_by_box_size_when_no_attribute_says_it(proposer: BuiltinProposer) -> None:
    graph = scene(
        [
            obj("small", "table", [0.0, 0.0, 0.3], [0.5, 0.5, 0.6]),
            obj("big", "table", [4.0, 0.0, 0.375], [2.0, 1.0, 0.75]),
        ]
    )
    small = weights_by_anchor(proposer.propose(graph, "the mug is near the small table"))
    big = weights_by_anchor(proposer.propose(graph, "the mug is near the big table"))
    assert small[("small",)] > 0.9 and big[("big",)] > 0.9


def test_no_matching_anchor_is_not_grounded_and_the_sensor_falls_back(proposer: BuiltinProposer) -> None:
    proposal = proposer.propose(two_rooms(), "my keys are on the piano")
    assert not proposal.grounded and proposal.hypotheses == ()
    assert "piano" in (proposal.reason or "")
    grounding = LanguageSensor(proposer, GeometricGrounder()).ground(two_rooms(), "my keys are on the piano")
    assert not grounding.grounded and len(grounding.mixture.weights) == 1  # the scene-wide prior

    unanchored = proposer.propose(two_rooms(), "where is my backpack")
    assert not unanchored.grounded and "no anchor" in (unanchored.reason or "")
    empty = proposer.propose(scene([]), "the mug is on the table")
    assert not empty.grounded and "no objects" in (empty.reason or "")


def test_plural_anchor_gives_one_hypothesis_per_object(proposer: BuiltinProposer) -> None:
    proposal = proposer.propose(two_rooms(), "I put my phone on one of the chairs")
    anchors = {h.anchor_ids for h in proposal.hypotheses}
    assert anchors == {("k-chair1",), ("k-chair2",), ("b-chair1",), ("b-chair2",)}
    assert sum(h.weight for h in proposal.hypotheses) == pytest.approx(1.0)


def test_between_pairs_distinct_objects(proposer: BuiltinProposer) -> None:
    graph = two_rooms()
    proposal = proposer.propose(graph, "the lamp is between the chairs")
    pairs = [frozenset(h.anchor_ids) for h in proposal.hypotheses]
    assert all(len(p) == 2 for p in pairs) and len(set(pairs)) == len(pairs)
    assert all(h.relation is Relation.BETWEEN for h in proposal.hypotheses)
    # The two chairs of one room (2 m apart) are likelier than chairs in different rooms (8-12 m apart).
    assert pairs[0] in ({"k-chair1", "k-chair2"}, {"b-chair1", "b-chair2"})

    mixed = proposer.propose(graph, "the bag is between the table and the chair")
    for h in mixed.hypotheses:
        labels = sorted(graph.object(i).label for i in h.anchor_ids)
        assert labels == ["chair", "table"]
    same_room = [h for h in mixed.hypotheses if len({graph.object(i).region_id for i in h.anchor_ids}) == 1]
    assert len(same_room) == 4  # each table with either of its own chairs
    assert sum(h.weight for h in same_room) > 0.9


def test_at_most_five_weights_summing_to_one(encoder: TextEncoder) -> None:
    chairs = [obj(f"c{i}", "chair", [1.5 * i, 0.0, 0.45], CHAIR) for i in range(12)]
    for limit in (5, 2):
        proposal = BuiltinProposer.load(encoder, max_hypotheses=limit).propose(
            scene(chairs), "the bag is near the chair"
        )
        weights = [h.weight for h in proposal.hypotheses]
        assert len(weights) == limit
        assert sum(weights) == pytest.approx(1.0)
        assert weights == sorted(weights, reverse=True)
        assert proposal.extra["candidates"] == 12.0
        assert 0.0 < proposal.extra["dropped_weight"] < 1.0


def test_unknown_relation_words_give_near_hypotheses(proposer: BuiltinProposer) -> None:
    proposal = proposer.propose(two_rooms(), "the bag is behind the table")
    assert not proposal.parse.relation_known
    assert {h.relation for h in proposal.hypotheses} == {Relation.NEAR}


def test_alternatives_take_candidates_of_both_phrases(proposer: BuiltinProposer) -> None:
    graph = scene([obj("t", "table", [0.0, 0.0, 0.375], TABLE), obj("d", "desk", [4.0, 0.0, 0.375], TABLE)])
    proposal = proposer.propose(graph, "the keys are on the table or the desk")
    assert {h.anchor_ids for h in proposal.hypotheses} == {("t",), ("d",)}


def test_synonyms_lemmas_and_raw_labels_find_their_objects(proposer: BuiltinProposer) -> None:
    graph = scene(
        [
            obj("sofa", "sofa", [0.0, 0.0, 0.4], [2.0, 0.9, 0.8]),
            obj("cab", "kitchen_cabinets", [4.0, 0.0, 0.4], [2.0, 0.6, 0.9]),
            obj("bin", "garbage bin", [8.0, 0.0, 0.3], [0.4, 0.4, 0.6], raw_label="trash can"),
            obj("lamp", "lamp", [12.0, 0.0, 0.3], [0.4, 0.4, 0.6]),
        ]
    )
    for phrase, expected in (("couch", "sofa"), ("kitchen cabinet", "cab"), ("trash can", "bin")):
        proposal = proposer.propose(graph, f"the mug is near the {phrase}")
        assert proposal.hypotheses[0].anchor_ids == (expected,), phrase


def test_every_synonym_the_data_generator_speaks_names_its_label() -> None:
    """Lemmas, the synonym table or the head noun connect each generated phrase to its label."""
    from app.grounding.builtin import lemmas

    for label, phrases in LABEL_SYNONYMS.items():
        for phrase in phrases:
            assert lexical_match(lemmas(phrase), lemmas(label)) > 0, (phrase, label)


# --- features -----------------------------------------------------------------------------------------------


def test_relation_masks_on_hand_made_boxes() -> None:
    graph = scene(
        [
            obj("table", "table", [0.0, 0.0, 0.375], TABLE),
            obj("mug", "mug", [0.2, 0.1, 0.8], [0.1, 0.1, 0.1]),  # on the table
            obj("box", "box", [0.0, 0.0, 0.15], [0.3, 0.3, 0.3]),  # under it (and inside its box)
            obj("lamp", "lamp", [0.0, 0.0, 1.8], [0.3, 0.3, 0.3]),  # above it
            obj("chair", "chair", [1.0, 0.0, 0.45], CHAIR),  # near it
            obj("far", "plant", [5.0, 0.0, 0.45], CHAIR),
        ]
    )
    boxes = SceneBoxes.of(list(graph.objects))
    anchor = np.array([0])
    names = [o.id for o in graph.objects]

    def related(relation: Relation) -> set[str]:
        return {names[i] for i in np.flatnonzero(related_mask(relation, boxes, anchor)[0])}

    assert related(Relation.ON) == {"mug"}
    assert related(Relation.BELOW) == {"box"}
    assert related(Relation.ABOVE) == {"lamp"}
    assert related(Relation.IN) == {"box"}  # the mug's centre is above the table's box
    assert related(Relation.NEAR) == {"mug", "box", "chair"}
    gap = between_mask(boxes, np.array([[4, 5]]))[0]  # between the chair and the plant
    assert not gap.any()
    gap = between_mask(boxes, np.array([[0, 5]]))[0]  # the chair stands between the table and the plant
    assert {names[i] for i in np.flatnonzero(gap)} == {"chair"}


def test_attribute_scores_match_conflict_and_rank() -> None:
    graph = scene(
        [
            obj("w", "table", [0, 0, 0.4], [1, 1, 0.8], color="white"),
            obj("r", "table", [2, 0, 0.4], [2, 1, 0.8], colors=[{"name": "red"}]),
            obj("n", "table", [4, 0, 0.4], [3, 1, 0.8], material="wood"),
        ]
    )
    objects = list(graph.objects)
    sizes = SceneBoxes.of(objects).size
    vocabulary = frozenset({"white", "red", "wooden"})
    assert attribute_scores(("white",), objects, sizes, vocabulary).tolist() == [1.0, -1.0, 0.0]
    assert attribute_scores(("wood",), objects, sizes, vocabulary).tolist() == [0.0, 0.0, 1.0]
    assert attribute_scores(("big",), objects, sizes, vocabulary).tolist() == [-1.0, 0.0, 1.0]
    assert attribute_scores((), objects, sizes, vocabulary).tolist() == [0.0, 0.0, 0.0]


def test_features_of_the_two_mirrored_tables_are_equal(proposer: BuiltinProposer) -> None:
    from app.grounding.parsing import parse_utterance

    found = proposer.candidates(two_rooms(), parse_utterance("the bag is near the table"))
    assert not isinstance(found, str)
    assert found.features.shape == (2, len(FEATURES))
    np.testing.assert_allclose(found.features[0], found.features[1], atol=1e-9)


# --- parameters ---------------------------------------------------------------------------------------------


def test_the_shipped_parameters_load_and_report_their_fit(encoder: TextEncoder) -> None:
    params = ProposerParams.load(DEFAULT_PARAMS_PATH)
    assert set(params.weights) == set(Relation)
    assert params.encoder_sha256 == encoder.sha256
    assert any(np.any(w != 0) for w in params.weights.values())
    unseen = params.info["metrics"]["val_unseen"]
    assert unseen["n"] > 1000
    assert unseen["builtin"]["overall"]["ece"] < 0.05  # the calibration target, as measured
    assert set(params.info["fitted_on"]) == {"train", "val_seen", "val_unseen"}


def test_parameters_round_trip_and_refuse_a_mismatch(tmp_path: Path, encoder: TextEncoder) -> None:
    params = ProposerParams.load(DEFAULT_PARAMS_PATH)
    params.save(tmp_path / "params.json")
    again = ProposerParams.load(tmp_path / "params.json")
    for relation in Relation:
        np.testing.assert_allclose(again.weights[relation], params.weights[relation], atol=1e-6)
    assert again.target_boxes.keys() == params.target_boxes.keys()

    other = dataclasses.replace(params, encoder_sha256="0" * 64)
    with pytest.raises(ModelUnavailable, match="text encoder"):
        BuiltinProposer(encoder, other)
    stale = {**params.to_json(), "features": ["label_cosine"]}
    with pytest.raises(ModelUnavailable, match="refit"):
        ProposerParams.from_json(stale)
    with pytest.raises(ModelUnavailable, match="fit-proposer"):
        ProposerParams.load(tmp_path / "missing.json")


# --- fitting ------------------------------------------------------------------------------------------------


def synthetic_cases(rng: np.random.Generator, weights: np.ndarray, n_cases: int, temperature: float = 1.0):
    """Cases of 2-6 candidates with standard-normal features, the true one drawn from softmax(w.x / T)."""
    cases = []
    for _ in range(n_cases):
        relation = int(rng.integers(weights.shape[0]))
        x = rng.standard_normal((int(rng.integers(2, 7)), weights.shape[1]))
        scores = x @ weights[relation] / temperature
        p = np.exp(scores - scores.max())
        cases.append((relation, x, int(rng.choice(len(x), p=p / p.sum()))))
    return cases


def test_loss_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    weights = rng.standard_normal((3, 4))
    problem = logit_problem(synthetic_cases(rng, weights, 40), np.zeros(4), np.ones(4))
    point = rng.standard_normal(12)
    _, grad = logit_loss(point, problem, 0.1, 3)
    step = 1e-6
    numeric = [
        (logit_loss(point + step * e, problem, 0.1, 3)[0] - logit_loss(point - step * e, problem, 0.1, 3)[0])
        / (2 * step)
        for e in np.eye(12)
    ]
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-7)


def test_fit_recovers_known_weights_and_temperature() -> None:
    rng = np.random.default_rng(1)
    truth = np.array([[1.5, -1.0, 0.0], [0.5, 0.5, -2.0]])
    cases = synthetic_cases(rng, truth, 6000)
    fitted = fit_conditional_logit(logit_problem(cases, np.zeros(3), np.ones(3)), l2=1e-6, n_relations=2)
    np.testing.assert_allclose(fitted, truth, atol=0.15)

    # Scores w.x drawn at temperature 2.5: fitting T on the unscaled scores finds it.
    hot = synthetic_cases(rng, truth, 6000, temperature=2.5)
    scores = [x @ truth[r] for r, x, _ in hot]
    assert fit_temperature(scores, [t for _, _, t in hot]) == pytest.approx(2.5, rel=0.1)


def test_truncated_weights_are_renormalised_and_marked() -> None:
    params = ProposerParams.untrained()
    params.weights[Relation.NEAR][0] = 1.0
    features = np.zeros((8, len(FEATURES)))
    features[:, 0] = np.arange(8.0)  # label_cosine 0..7: the last row scores highest
    row = CaseRows(Relation.NEAR, features, np.zeros(8), 2, "5+", True, True)
    weights, correct = proposal_weights(params, row, 5)
    assert len(weights) == 5 and weights.sum() == pytest.approx(1.0)
    assert np.all(np.diff(weights) < 0)
    assert not correct.any()  # the true row (score 2) is not among the five heaviest
    ratio = math.exp(1.0)
    assert weights[0] / weights[1] == pytest.approx(ratio)


def test_fit_proposer_on_a_small_real_file(tmp_path: Path, encoder: TextEncoder) -> None:
    params = fit_proposer(RESOURCES / "cases.jsonl", encoder, l2_grid=(0.1,))
    report = params.info["metrics"]["train"]
    assert report["n"] == 35
    assert report["parse"] == {"relation_accuracy": 1.0, "anchor_phrase_accuracy": 1.0}
    assert report["true_among_candidates"] == 1.0
    # Fitted on these cases, the weights beat uniform ones on them.
    builtin = report["builtin"]["overall"]
    for uniform in ("uniform_returned", "uniform_candidates"):
        assert builtin["true_hypothesis_nll"] < report[uniform]["overall"]["true_hypothesis_nll"]
    table = summary_table(report)
    assert table.count("\n") == 2 + 1 + len(report["builtin"]["per_ambiguity"]) - 1
    params.save(tmp_path / "params.json")
    loaded = BuiltinProposer.load(encoder, tmp_path / "params.json")
    assert loaded.propose(two_rooms(), "the mug is on the table").grounded


def test_the_cli_registers_fit_proposer() -> None:
    from app.cli import build_parser
    from app.grounding import referent_fit

    args = build_parser().parse_args(["fit-proposer", "--cases", "data/cases", "--l2", "0.01", "0.1"])
    assert args.func is referent_fit.run
    assert args.l2 == [0.01, 0.1] and args.out == Path("models/proposer")
