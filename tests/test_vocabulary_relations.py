"""The old disagreements of the vocabulary and of the box relations, each pinned to the one answer that every
caller now gives: the belief, both proposers, the case builder, the conventions and the simulator.

- "Same class" (`app.vocabulary.class_key`): bag / backpack and bin / trash can are other classes (a
  generic word names them loosely, `lexical_match` 1); cushion / pillow are one class (synonyms).
- Region phrases: one normalisation of region names ("Game_Room" is "game room") and one matching
  rule (`app.vocabulary.regions_named`), whoever parses.
- Label classes of the label policies (`app.vocabulary.in_classes`): plurals, synonyms and head nouns.
- Box relations: one set of thresholds (`app.grounding.box_relations`) for the built true readings and the
  proposer's context counts: the vertical gap of "above" and the height of an internal support.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.belief.session import ObservationModel, SensorModel, mapped_look_alikes
from app.data import conventions
from app.data.templates import class_names, generic_names
from app.grounding import box_relations
from app.grounding.box_relations import (
    INTERNAL_SUPPORT_MIN_HEIGHT,
    ON_GAP_TOLERANCE,
    UNDER_BASE_TOLERANCE,
    VERTICAL_MIN_GAP,
    Box,
    anchor_allowed,
    true_groundings,
)
from app.grounding.builtin import BuiltinProposer
from app.grounding.lexical import LexicalProposer
from app.grounding.mixture import map_box
from app.grounding.parsing import parse_utterance
from app.grounding.referent_features import SceneBoxes, related_mask
from app.grounding.relations import Relation
from app.grounding.sensor import broad_boxes
from app.lsm.text_encoder import TextEncoder
from app.scene_graph.model import SceneGraph, SceneObject
from app.sim.noise import LabelNoise
from app.vocabulary import class_key, in_classes, lemmas, lexical_match, regions_named, same_class

# (target, another name, same class?, lexical_match of the other name for the target)
OLD_DISAGREEMENTS = [
    ("backpack", "bag", False, 1),
    ("trash can", "bin", False, 1),
    ("pillow", "cushion", True, 2),
]


def obj(
    oid: str, label: str, center: list[float], size: list[float], region: str | None = None
) -> dict[str, Any]:
    return {"id": oid, "label": label, "center": center, "size": size, "region_id": region}


def graph(objects: list[dict[str, Any]], regions: list[dict[str, Any]] | None = None) -> SceneGraph:
    return SceneGraph.model_validate({"regions": regions or [], "objects": objects})


@pytest.fixture(scope="module")
def proposer() -> BuiltinProposer:
    return BuiltinProposer.load(TextEncoder())


@pytest.mark.parametrize(
    ("phrase", "name", "level"),
    [
        ("blue bin", "trash can", 1),  # a generic head noun with modifiers names as the bare word does
        ("chair", "armchair", 1),  # "the chair on the right" for an armchair (Nr3D)
        ("big bag", "backpack", 1),
        ("chair", "sofa", 0),
        ("blue bin", "chair", 0),
    ],
)
def test_looser_namings_people_use(phrase: str, name: str, level: int) -> None:
    assert lexical_match(lemmas(phrase), lemmas(name)) == level
    assert not same_class(lemmas(phrase), lemmas(name))


# --- same class ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_vocabulary_answers_each_old_disagreement_once(
    target: str, other: str, same: bool, level: int
) -> None:
    assert same_class(target, other) is same
    assert (class_key(target) == class_key(other)) is same
    assert lexical_match(other, target) == level  # "the bag" may mean the backpack: a looser naming


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_belief_compares_classes_only(target: str, other: str, same: bool, level: int) -> None:
    """A robot label, and a mapped look-alike, are the target's only when of its class: a mapped "bag" may be
    the very backpack looked for, so its voxels keep their evidence."""
    del level
    scene = graph(
        [
            obj("t", target, [0.5, 0.5, 0.5], [0.4, 0.4, 0.4]),
            obj("o", other, [2.5, 0.5, 0.5], [0.4, 0.4, 0.4]),
            obj("floor", "floor", [1.5, 0.5, -0.05], [3.0, 1.0, 0.1]),
        ]
    )
    grid = VoxelGrid(origin=(0.0, 0.0, 0.0), shape=(30, 10, 10), voxel_size=0.1)
    look_alikes = mapped_look_alikes(grid, scene, target)
    xs = (np.unravel_index(look_alikes, grid.shape)[0] + 0.5) * grid.voxel_size
    assert np.any(xs < 1.0)  # the mapped object of the target's own class is a look-alike
    assert bool(np.any(xs > 2.0)) is same

    model = ObservationModel(grid, target, {1: target, 2: other}, SensorModel(), look_alikes)
    assert model.is_target([1, 2]).tolist() == [True, same]
    assert model.is_target([other, target.upper() + "S"]).tolist() == [same, True]


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_builtin_proposer_names_loosely_but_counts_classes(
    proposer: BuiltinProposer, target: str, other: str, same: bool, level: int
) -> None:
    """The phrase "the <other>" matches the target-labelled object exactly for a synonym, loosely for a
    generic word; the target's siblings (its kind) are the same class."""
    scene = graph(
        [
            obj("anchor", target, [0.0, 0.0, 0.2], [0.4, 0.4, 0.4]),
            obj("desk", "desk", [3.0, 0.0, 0.375], [1.2, 0.6, 0.75]),
            obj("floor", "floor", [1.5, 0.0, -0.05], [6.0, 3.0, 0.1]),
        ]
    )
    candidates = proposer.candidates(scene, proposer.parse(scene, f"the keys are on the {other}"))
    rows = [k for k, anchors in enumerate(candidates.anchors) if anchors == (0,)]
    assert rows, f"{other!r} should name the {target!r}"
    label_exact = candidates.features[rows, 1]
    label_head = candidates.features[rows, 2]
    assert np.all(label_exact == float(level == 2))
    assert np.all(label_head == float(level == 1))


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_lexical_proposer_names_by_the_same_rule(target: str, other: str, same: bool, level: int) -> None:
    """The lexical proposer names by `lexical_match` too (it read "cushion" as naming no "pillow")."""
    del same, level
    scene = graph(
        [
            obj("anchor", target, [0.0, 0.0, 0.2], [0.4, 0.4, 0.4]),
            obj("desk", "desk", [3.0, 0.0, 0.375], [1.2, 0.6, 0.75]),
        ]
    )
    proposal = LexicalProposer().propose(scene, f"the keys are on the {other}")
    assert [h.anchor_ids for h in proposal.hypotheses] == [("anchor",)]


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_case_builder_and_the_conventions_use_the_same_classes(
    target: str, other: str, same: bool, level: int
) -> None:
    """A speaker may call the target by its synonym or by a covering generic word; an object of the target's
    class never anchors it (vlmap) and is its distractor (Sr3D's contexts)."""
    assert (other in class_names(target)) is same
    assert (other in generic_names(target)) is (level == 1)
    target_obj = SceneObject(id="t", label=target, center=[0.0, 0.0, 0.6], size=[0.3, 0.3, 0.2])
    anchor = SceneObject(id="a", label=other, center=[0.0, 0.0, 0.25], size=[0.8, 0.8, 0.5])
    floor = SceneObject(id="f", label="floor", center=[0.0, 0.0, -0.05], size=[4.0, 4.0, 0.1])
    vlmap = {(r.relation, r.anchor_ids) for r in true_groundings(target_obj, [anchor, floor])}
    assert ((Relation.ON, ("a",)) in vlmap) is not same
    assert conventions.sr3d_context_ok(target_obj, [anchor, floor]) is same


@pytest.mark.parametrize(("target", "other", "same", "level"), OLD_DISAGREEMENTS)
def test_the_simulator_reports_the_target_class_only(target: str, other: str, same: bool, level: int) -> None:
    """With every target voxel missed (tp 0) and no false positives, only the target's class changes label."""
    del level
    noise = LabelNoise(tp=0.0, fp=0.0, confusion=0.0)
    reported = noise.corrupt([other, "desk"], target, np.random.default_rng(0), vocabulary=["desk", "lamp"])
    assert bool(reported[0] != other) is same
    assert reported[1] == "desk"


# --- label classes ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("label", "names", "member"),
    [
        ("trash cans", box_relations.CONTAINERS, True),  # plural: the builder read raw labels
        ("Kitchen_Cabinets", box_relations.CONTAINERS, True),
        ("cupboard", box_relations.CONTAINERS, True),  # synonym of cabinet
        ("chest of drawers", box_relations.PARTS, False),  # a dresser: head noun "chest", not "drawer"
        ("chest of drawers", box_relations.CONTAINERS, True),
        ("bookshelves", box_relations.SHELVES, True),  # singular "bookshelf", not "bookshelve"
        ("blinds", box_relations.OPENINGS, True),  # the proposer read lemmas: "blind" was no opening
        ("kitchen floor", box_relations.FLOORS, True),
        ("floor lamp", box_relations.FLOORS, False),
    ],
)
def test_label_classes_read_every_spelling_one_way(label: str, names: frozenset[str], member: bool) -> None:
    assert in_classes(label, names) is member


def test_the_label_policy_answers_raw_and_lemmatised_labels_alike() -> None:
    """The builder passes raw labels, the proposer lemmatised ones: the policy gives both one answer."""
    for label in ("trash cans", "washing machines", "blinds", "stairs", "stack of cups", "chest of drawers"):
        for relation in Relation:
            assert anchor_allowed(relation, label) == anchor_allowed(relation, lemmas(label)), (
                label,
                relation,
            )
    assert box_relations.is_floor("Floors") and not box_relations.is_floor("floor lamp")
    assert box_relations.is_ceiling("ceilings") and not box_relations.is_ceiling("ceiling light")


# --- regions ------------------------------------------------------------------------------------------------


def two_named_rooms() -> SceneGraph:
    """A room named as no room word is ("game room"), so that only the map's region names can name it."""
    regions = [
        {"id": "lr", "name": "Game_Room", "center": [0.0, 0.0, 1.25], "size": [4.0, 4.0, 2.5]},
        {"id": "k", "name": "kitchen", "center": [5.0, 0.0, 1.25], "size": [4.0, 4.0, 2.5]},
    ]
    objects = [
        obj("lr-table", "table", [0.0, 0.0, 0.375], [1.2, 0.8, 0.75], "lr"),
        obj("k-table", "table", [5.0, 0.0, 0.375], [1.2, 0.8, 0.75], "k"),
    ]
    return graph(objects, regions)


def test_a_region_name_is_read_one_way_whoever_parses(proposer: BuiltinProposer) -> None:
    """ "Game_Room" is "game room" for the parser whether the caller passed it as written, lower-cased
    (the sensor and the LSM did) or normalised (the proposers did)."""
    scene = two_named_rooms()
    utterance = "the keys are on the table in the game room"
    for names in (("Game_Room",), ("game_room",), ("game room",)):
        assert parse_utterance(utterance, names).region_phrase == "game room"
    assert proposer.parse(scene, utterance).region_phrase == "game room"
    lexical = LexicalProposer().propose(scene, utterance)
    assert [h.anchor_ids for h in lexical.hypotheses] == [("lr-table",)]
    assert regions_named(scene.regions, "game rooms") == {"lr"}
    boxes, _ = broad_boxes(scene, parse_utterance(utterance, ("game_room",)), map_box(scene))
    assert len(boxes) == 1 and np.allclose(boxes[0].low[:2], [-2.0, -2.0])


def test_the_builtin_proposer_keeps_to_the_named_region(proposer: BuiltinProposer) -> None:
    scene = two_named_rooms()
    candidates = proposer.candidates(
        scene, proposer.parse(scene, "the keys are on the table in the game room")
    )
    anchored = {scene.objects[a[0]].id for a in candidates.anchors if a}
    assert anchored == {"lr-table"}


# --- box relations ------------------------------------------------------------------------------------------


def test_the_relation_thresholds_are_named_once() -> None:
    """The proposer's context predicates hold no thresholds of their own (the old ones had drifted:
    "above" from 0.10 m there, 0.15 m in the builder; internal supports likewise)."""
    import app.grounding.referent_features as features

    for old in ("VERTICAL_GAP", "ON_SINK", "ON_GAP", "INTERNAL_SUPPORT", "NEAR_DISTANCE", "UNDER_BASE"):
        assert not hasattr(features, old), old
    assert VERTICAL_MIN_GAP > ON_GAP_TOLERANCE  # between the two: neither "on" nor "above"
    assert INTERNAL_SUPPORT_MIN_HEIGHT == UNDER_BASE_TOLERANCE  # "on the seat" / "under the chair" partition


@pytest.mark.parametrize(
    ("gap", "above"),
    [(0.12, False), (VERTICAL_MIN_GAP - 0.01, False), (VERTICAL_MIN_GAP + 0.01, True), (1.0, True)],
)
def test_above_starts_at_one_vertical_gap_for_builder_and_proposer(gap: float, above: bool) -> None:
    table = SceneObject(id="table", label="table", center=[0.0, 0.0, 0.375], size=[1.2, 0.8, 0.75])
    lamp = SceneObject(id="lamp", label="lamp", center=[0.0, 0.0, 0.75 + gap + 0.1], size=[0.3, 0.3, 0.2])
    assert bool(box_relations.is_above(Box.of(lamp), Box.of(table))) is above
    built = {(r.relation, r.anchor_ids) for r in true_groundings(lamp, [table])}
    assert ((Relation.ABOVE, ("table",)) in built) is above
    context = related_mask(Relation.ABOVE, SceneBoxes.of([table, lamp]), np.array([0]))
    assert bool(context[0, 1]) is above


@pytest.mark.parametrize(
    ("bottom", "supported"),
    [(0.12, False), (INTERNAL_SUPPORT_MIN_HEIGHT - 0.01, False), (INTERNAL_SUPPORT_MIN_HEIGHT + 0.01, True)],
)
def test_an_internal_support_starts_at_one_height_for_builder_and_proposer(
    bottom: float, supported: bool
) -> None:
    shelf = SceneObject(id="shelf", label="bookshelf", center=[0.0, 0.0, 0.9], size=[1.0, 0.4, 1.8])
    book = SceneObject(id="book", label="book", center=[0.0, 0.0, bottom + 0.1], size=[0.2, 0.2, 0.2])
    built = {(r.relation, r.anchor_ids) for r in true_groundings(book, [shelf])}
    assert ((Relation.ON, ("shelf",)) in built) is supported
    context = related_mask(Relation.ON, SceneBoxes.of([shelf, book]), np.array([0]))
    assert bool(context[0, 1]) is supported
