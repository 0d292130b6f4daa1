"""The grounding-case builder: relation predicates on hand-made boxes, templates, AI2-THOR reading, and the
builder end to end on real fixture scenes (tests/resources/data): splits, conventions, houses, shifted
maps."""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from app.data.augment import FrameMotion
from app.data.build import (
    SPLITS,
    BuildConfig,
    BuildSummary,
    build_cases,
    read_ai2thor,
    read_scannet,
    room_key,
    split_camel_case,
    thor_placement_relation,
    write_build,
)
from app.data.cases import GroundingCase, read_cases
from app.data.conventions import Convention, holds
from app.data.label_vocabularies import SCANNET_TO_NYU
from app.data.templates import RELATION_PHRASES, indefinite, is_plural, render_utterance, speaker_names
from app.errors import InvalidInput
from app.grounding import box_relations as rel
from app.grounding.box_relations import Box, TrueReading, true_groundings
from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject
from app.vocabulary import same_class

DATA = Path(__file__).parent / "resources" / "data"
SCANNET = DATA / "scannet_scenes.jsonl"
AI2THOR = DATA / "ai2thor_scenes.jsonl"


def box(center: list[float], size: list[float]) -> Box:
    return Box.from_center_size(center, size)


def obj(id_: str, label: str, center: list[float], size: list[float]) -> SceneObject:
    return SceneObject(id=id_, label=label, center=center, size=size)


TABLE = box([0, 0, 0.375], [1.0, 1.0, 0.75])  # top at 0.75


# --- relation predicates on hand-made boxes -----------------------------------------------------------------


def test_on_needs_the_bottom_at_the_anchor_top_and_the_footprint_centre_inside():
    assert rel.is_on(box([0.2, 0.1, 0.80], [0.1, 0.1, 0.1]), TABLE)  # resting on the top
    assert rel.is_on(box([0.2, 0.1, 0.72], [0.1, 0.1, 0.1]), TABLE)  # sunk 8 cm into the box (scan noise)
    assert not rel.is_on(box([0.2, 0.1, 1.10], [0.1, 0.1, 0.1]), TABLE)  # floating 30 cm above
    assert not rel.is_on(box([0.8, 0.1, 0.80], [0.1, 0.1, 0.1]), TABLE)  # beside the table
    assert not rel.is_on(box([0.2, 0.1, 0.30], [0.1, 0.1, 0.1]), TABLE)  # inside the box, below its top
    assert not rel.is_on(box([0, 0, 0.85], [1.2, 1.2, 0.2]), TABLE)  # a bigger footprint is not supported


def test_on_internal_supports_accept_a_seat_below_the_backrest_and_shelf_boards():
    couch = box([0, 0, 0.45], [2.0, 1.0, 0.9])
    reach = rel.internal_support_reach("couch")
    pillow = box([0.3, 0.1, 0.6], [0.4, 0.4, 0.3])  # bottom at 0.45, far below the couch's top
    assert rel.is_on(pillow, couch, reach)
    assert not rel.is_on(pillow, couch)  # as a plain top surface the couch would not carry it
    bag_on_floor = box([0.3, 0.1, 0.2], [0.4, 0.4, 0.4])
    assert not rel.is_on(bag_on_floor, couch, reach)
    chair = box([0, 0, 0.45], [0.6, 0.6, 0.9])
    keyboard_on_desk_above_it = box([0.1, 0, 0.76], [0.45, 0.15, 0.04])  # bottom at 0.82 of the chair
    assert not rel.is_on(keyboard_on_desk_above_it, chair, rel.internal_support_reach("office chair"))
    bookshelf = box([0, 0, 1.0], [1.0, 0.4, 2.0])
    assert rel.is_on(box([0, 0, 1.75], [0.3, 0.2, 0.3]), bookshelf, rel.internal_support_reach("bookshelf"))


def test_in_needs_the_target_enclosed_and_smaller():
    fridge = box([0, 0, 0.9], [0.8, 0.7, 1.8])
    assert rel.is_in(box([0.1, 0, 1.2], [0.1, 0.1, 0.1]), fridge)
    assert not rel.is_in(box([1.0, 0, 1.2], [0.1, 0.1, 0.1]), fridge)
    assert not rel.is_in(box([0.0, 0, 1.9], [0.1, 0.1, 0.3]), fridge)  # sticks out of the top
    assert rel.anchor_allowed(Relation.IN, "kitchen cabinet")
    assert rel.anchor_allowed(Relation.IN, "Trash Can")
    assert not rel.anchor_allowed(Relation.IN, "table")
    assert rel.anchor_allowed(Relation.IN, "drawer") and not rel.anchor_allowed(Relation.ABOVE, "drawer")


def test_above_needs_a_gap_overlap_and_bounded_height():
    tv = box([0, 0, 1.2], [1.0, 0.1, 0.6])  # top at 1.5
    assert rel.is_above(box([0, 0, 1.9], [0.3, 0.05, 0.3]), tv)  # gap 0.25
    assert not rel.is_above(box([0, 0, 1.6], [0.3, 0.05, 0.2]), tv)  # touching (gap 0.0)
    assert not rel.is_above(box([0, 0, 3.5], [0.3, 0.05, 0.2]), tv)  # gap 1.9 > max height
    assert not rel.is_above(box([2.0, 0, 1.9], [0.3, 0.05, 0.3]), tv)  # no footprint overlap


def test_below_under_furniture_and_under_a_hanging_anchor():
    bin_under = box([0.1, 0.1, 0.2], [0.3, 0.3, 0.4])
    assert rel.is_below(bin_under, TABLE, clearance=True)
    assert not rel.is_below(bin_under, TABLE, clearance=False)  # a solid block has no "under"
    tall_chair = box([0.1, 0.1, 0.45], [0.5, 0.5, 0.9])  # taller than the table top
    assert not rel.is_below(tall_chair, TABLE, clearance=True)
    wall_shelf = box([0, 0, 1.6], [1.0, 0.3, 0.1])  # hanging, bottom at 1.55
    assert rel.is_below(box([0, 0, 0.3], [0.4, 0.3, 0.6]), wall_shelf)  # gap 0.95
    assert not rel.is_below(box([3.0, 0, 0.3], [0.4, 0.3, 0.6]), wall_shelf)


def test_near_is_a_surface_distance_and_excludes_on():
    assert rel.is_near(box([0.8, 0, 0.3], [0.2, 0.2, 0.2]), TABLE)  # 0.2 m from the table's side
    assert not rel.is_near(box([2.0, 0, 0.3], [0.2, 0.2, 0.2]), TABLE)  # 1.4 m
    mug = obj("m", "mug", [0.2, 0.1, 0.8], [0.1, 0.1, 0.1])
    found = true_groundings(mug, [obj("t", "table", [0, 0, 0.375], [1, 1, 0.75])])
    assert TrueReading(Relation.ON, ("t",)) in found
    assert TrueReading(Relation.NEAR, ("t",)) not in found


def test_between_lies_in_the_gap_close_to_the_segment():
    sofa = box([0, 0, 0.4], [0.9, 2.0, 0.8])
    armchair = box([2.5, 0, 0.4], [0.8, 0.8, 0.8])
    assert rel.is_between(box([1.2, 0.1, 0.5], [0.3, 0.3, 1.0]), sofa, armchair)
    assert rel.is_between(box([1.2, 0.1, 0.5], [0.3, 0.3, 1.0]), armchair, sofa)  # symmetric
    assert not rel.is_between(box([3.5, 0, 0.5], [0.3, 0.3, 1.0]), sofa, armchair)  # beyond the armchair
    assert not rel.is_between(box([1.2, 1.2, 0.5], [0.3, 0.3, 1.0]), sofa, armchair)  # 1.2 m off the line
    assert not rel.is_between(
        box([0.3, 0.0, 0.5], [0.3, 0.3, 1.0]), sofa, armchair
    )  # inside the sofa's footprint
    far_armchair = box([5.0, 0, 0.4], [0.8, 0.8, 0.8])
    assert not rel.is_between(box([2.5, 0, 0.5], [0.3, 0.3, 1.0]), sofa, far_armchair)  # 5 m apart


def test_closest_and_farthest_need_a_clear_margin_over_same_class_siblings():
    door = Box(np.array([[0.0, 0.0, 0.0]]), np.array([[0.1, 1.0, 2.0]]))
    target = box([1.0, 0.5, 0.45], [0.5, 0.5, 0.9])
    siblings = Box.of([obj("c2", "chair", [3.0, 0.5, 0.45], [0.5, 0.5, 0.9])])
    closest, farthest = rel.ordinal_relations(target, siblings, door)
    assert closest[0] and not farthest[0]
    near_twin = Box.of([obj("c2", "chair", [1.1, 0.5, 0.45], [0.5, 0.5, 0.9])])  # 10 cm farther: ambiguous
    closest, farthest = rel.ordinal_relations(target, near_twin, door)
    assert not closest[0] and not farthest[0]
    none = Box.of([])
    assert not any(rel.ordinal_relations(target, none, door)[0])


def test_label_policy_of_anchors():
    room = [
        obj("w", "wall", [0, 2.0, 1.2], [4.0, 0.1, 2.4]),
        obj("f", "floor", [0, 0, -0.05], [4.0, 4.0, 0.1]),
        obj("d", "door", [2.0, 1.5, 1.0], [0.1, 0.9, 2.0]),
        obj("c2", "chair", [-1.0, 0.0, 0.45], [0.5, 0.5, 0.9]),
    ]
    chair = obj("c1", "chair", [1.5, 1.6, 0.45], [0.5, 0.5, 0.9])
    found = true_groundings(chair, room)
    anchors = {(g.relation, g.anchor_ids) for g in found}
    assert (Relation.NEAR, ("w",)) in anchors  # "near the wall" is allowed
    assert all("f" not in g.anchor_ids for g in found)  # the floor anchors nothing
    assert all(g.relation is Relation.NEAR for g in found if "w" in g.anchor_ids)
    assert all("c2" not in g.anchor_ids for g in found)  # never the target's own class
    assert (Relation.CLOSEST, ("d",)) in anchors  # the chair closest to the door
    assert not any(g.relation is Relation.CLOSEST for g in true_groundings(chair, room[:3]))  # no sibling
    # Classes are the vocabulary's: plurals and synonyms are one class, a longer word is not.
    assert same_class("book", "Books") and same_class("box", "boxes") and same_class("couch", "sofa")
    assert not same_class("cup", "cupboard")
    couch_twin = obj("s", "sofa", [1.5, 0.2, 0.4], [2.0, 0.9, 0.8])
    on_couch = obj("p", "couch", [1.5, 0.2, 0.9], [0.4, 0.4, 0.2])
    assert all("s" not in g.anchor_ids for g in true_groundings(on_couch, [*room, couch_twin]))


def test_vectorised_predicates_match_pair_by_pair_calls():
    rng = np.random.default_rng(3)
    n = 40
    lo = rng.uniform(-2, 2, size=(n, 3))
    anchors = Box(lo, lo + rng.uniform(0.05, 1.5, size=(n, 3)))
    target = box([0.1, -0.2, 0.6], [0.3, 0.4, 0.5])
    flags = rng.random(n) < 0.5
    masks = {
        "on": rel.is_on(target, anchors, flags),
        "in": rel.is_in(target, anchors),
        "above": rel.is_above(target, anchors),
        "below": rel.is_below(target, anchors, flags),
        "near": rel.is_near(target, anchors),
    }
    for i in range(n):
        one = Box(anchors.lo[i], anchors.hi[i])
        assert masks["on"][i] == rel.is_on(target, one, bool(flags[i]))
        assert masks["in"][i] == rel.is_in(target, one)
        assert masks["above"][i] == rel.is_above(target, one)
        assert masks["below"][i] == rel.is_below(target, one, bool(flags[i]))
        assert masks["near"][i] == rel.is_near(target, one)
        # Surface distance against a direct per-axis reading.
        gaps = [max(0.0, target.lo[k] - one.hi[k], one.lo[k] - target.hi[k]) for k in range(3)]
        assert rel.surface_distance(target, one) == pytest.approx(sum(g * g for g in gaps) ** 0.5)
    assert any(masks["near"]) and not all(masks["near"])


# --- templates ----------------------------------------------------------------------------------------------


def test_templates_cover_every_relation_and_agree_in_number():
    assert set(RELATION_PHRASES) == set(Relation)
    rng = np.random.default_rng(0)
    for relation in Relation:
        anchors = ("sofa", "armchair")[: relation.n_anchors]
        texts = {render_utterance(relation, "mug", anchors, rng, portable=True) for _ in range(60)}
        assert len(texts) > 5
        assert all(any(p in t for p in RELATION_PHRASES[relation]) for t in texts)
    assert is_plural("books") and is_plural("kitchen cabinets") and not is_plural("glass")
    assert indefinite("apple") == "an apple" and indefinite("books") == "books"
    assert indefinite("toilet paper") == "some toilet paper"
    books = {render_utterance(Relation.ON, "books", ("desk",), rng) for _ in range(80)}
    assert not any("books is" in t for t in books)
    # Every utterance names its target, by its label or another name the vocabulary gives it.
    for relation in Relation:
        anchors = ("table", "door")[: relation.n_anchors]
        for _ in range(40):
            text = render_utterance(relation, "trash can", anchors, rng, portable=True)
            assert any(name in text for name in ("trash can", *speaker_names("trash can"))), text
    with pytest.raises(ValueError, match="takes 2"):
        render_utterance(Relation.BETWEEN, "mug", ("sofa",), rng)


# --- AI2-THOR reading ---------------------------------------------------------------------------------------


def test_camel_case_labels_and_receptacle_kinds():
    assert split_camel_case("DiningTable") == "dining table"
    assert split_camel_case("TVStand") == "tv stand"
    assert split_camel_case("CD") == "cd"
    assert split_camel_case("CounterTop") == "countertop"
    assert thor_placement_relation("Fridge") is Relation.IN
    assert thor_placement_relation("SinkBasin") is Relation.IN
    assert thor_placement_relation("CounterTop") is Relation.ON
    assert thor_placement_relation("SomethingNew") is Relation.ON


def test_ai2thor_fixture_placements_become_on_and_in():
    kitchen = next(s for s in read_ai2thor(AI2THOR) if s.scene_id == "kitchens_13")
    assert kitchen.region.name == "kitchen"
    labels = {o.id: o.label for o in kitchen.objects}
    assert labels["CounterTop|+00.99|+00.95|+01.02"] == "countertop"
    assert kitchen.placements is not None
    apple = kitchen.placements["Apple|-00.74|+01.14|-01.55"]
    assert [(labels[a], r) for a, r in apple.items()] == [("fridge", Relation.IN)]
    spatula = {labels[a]: r for a, r in kitchen.placements["Spatula|+01.70|+01.08|+00.07"].items()}
    assert spatula == {"stove burner": Relation.ON, "pot": Relation.IN}
    # "On the floor" is never a placement; the chairs stand on it.
    assert "Chair|+01.07|+00.00|+01.75" not in kitchen.placements
    assert kitchen.notes["placement_on_floor_dropped"] > 0


def test_ai2thor_missing_parents_fall_back_to_the_base_object_or_are_skipped(tmp_path):
    def thor(id_, label, center, parents=()):
        return {
            "id": id_,
            "label": label,
            "center": center,
            "size": [0.2, 0.2, 0.2],
            "parent_receptacles": list(parents),
            "receptacle": False,
            "pickupable": True,
        }

    scene = {
        "scene_id": "kitchens_x",
        "room_type": "kitchens",
        "objects": [
            thor("Sink|+01.00|+00.90|-01.00", "Sink", [1, 1, 0.9]),
            thor("Cup|1", "Cup", [1, 1, 1.0], ["Sink|+01.00|+00.90|-01.00|SinkBasin"]),
            thor("Egg|1", "Egg", [0, 0, 1.0], ["Bowl|9|9|9"]),
        ],
    }
    path = tmp_path / "thor.jsonl"
    path.write_text(json.dumps(scene) + "\n")
    (parsed,) = read_ai2thor(path)
    assert parsed.placements == {"Cup|1": {"Sink|+01.00|+00.90|-01.00": Relation.IN}}
    assert parsed.notes == Counter(placement_parent_resolved_to_base=1, placement_parent_missing=1)


# --- the builder end to end ---------------------------------------------------------------------------------

CONFIG = BuildConfig(
    seed=7,
    augment=2,
    max_cases_per_scene=30,
    unseen_fraction=0.3,
    val_seen_fraction=0.2,
    calib_fraction=0.3,
    house_fraction=1.0,
)
# Copies of the fixture rooms under new scan ids ("scene1089_00", "bedrooms_95"): distinct rooms, so that
# every split gets rooms and the training and calibration rooms make houses.
COPY_IDS = {"scene0": "scene1", "bedrooms_0": "bedrooms_9", "kitchens_1": "kitchens_9"}


@pytest.fixture(scope="module")
def real_scenes():
    return read_scannet(SCANNET) + read_ai2thor(AI2THOR)


@pytest.fixture(scope="module")
def scenes(real_scenes):
    def renamed(scene_id: str) -> str:
        prefix = next(p for p in COPY_IDS if scene_id.startswith(p))
        return COPY_IDS[prefix] + scene_id[len(prefix) :]

    return real_scenes + [dataclasses.replace(s, scene_id=renamed(s.scene_id)) for s in real_scenes]


@pytest.fixture(scope="module")
def built(scenes):
    return list(build_cases(scenes, CONFIG))


def _target_object(case: GroundingCase) -> SceneObject:
    return SceneObject(
        id="__target__", label=case.target.label, center=case.target.position, size=case.target.size
    )


def _target_origin(case: GroundingCase) -> tuple[str, str]:
    """(scan id, object id in that scan) of the case's target: house ids are "<room index>:<id>"."""
    room = int(case.meta["target_region_id"])
    target_id = case.meta["target_id"]
    return case.meta["scene_ids"][room], target_id.split(":", 1)[1] if case.meta["rooms"] > 1 else target_id


def _region_volume(case: GroundingCase) -> float:
    return float(np.prod(case.scene_graph.region(case.meta["target_region_id"]).size))


def test_every_split_gets_cases_and_targets_leave_their_graph(built):
    assert {split for split, _ in built} == set(SPLITS)
    for _, case in built:
        ids = {o.id for o in case.scene_graph.objects}
        assert case.meta["target_id"] not in ids
        assert case.hypotheses and len(case.hypotheses) == 1
        hyp = case.hypotheses[0]
        assert len(hyp.anchor_ids) == hyp.relation.n_anchors
        assert set(hyp.anchor_ids) <= ids
        labels = Counter(o.label for o in case.scene_graph.objects)
        by_id = {o.id: o.label for o in case.scene_graph.objects}
        assert case.meta["ambiguity"] == max(labels[by_id[a]] for a in hyp.anchor_ids)
        assert case.meta["convention"] in {c.value for c in Convention}
        assert case.meta["source"] in {"scannet", "ai2thor"}
        assert case.utterance.strip()
    # What is written reads back as the same case (the file format holds the moved, yawed boxes).
    for _, case in built[::50]:
        assert GroundingCase.model_validate_json(case.model_dump_json(exclude_none=True)) == case


def test_a_relocating_build_moves_a_share_of_the_train_targets_only(scenes, built):
    assert not any(c.meta["relocated"] for _, c in built)  # the default moves nothing
    relocating = build_cases(scenes, dataclasses.replace(CONFIG, relocate_fraction=0.1))
    moved = Counter((split, c.meta["relocated"]) for split, c in relocating if c.meta["augmentation"] == 0)
    share = moved["train", True] / (moved["train", True] + moved["train", False])
    assert 0.03 < share < 0.25  # 0.1 of the targets, a target giving up to 3 cases
    assert not any(relocated for (split, relocated) in moved if split != "train")


def test_every_convention_and_relation_is_represented(built):
    by_convention = Counter((c.meta["convention"], c.hypotheses[0].relation) for _, c in built)
    for convention in Convention:
        relations = {r for (conv, r), n in by_convention.items() if conv == convention.value and n}
        assert len(relations) >= 4, (convention, relations)
    assert not any(r in (Relation.IN, Relation.NEAR) for conv, r in by_convention if conv == "sr3d")


def test_relations_hold_in_the_canonical_frame_by_their_convention(built):
    """The truth of a case is computed on the clean layout: its canonical copy (augmentation 0, outside
    calib) shows exactly that layout, and the convention's predicates say the grounding holds there."""
    canonical = [c for split, c in built if split != "calib" and c.meta["augmentation"] == 0]
    assert {c.meta["rooms"] > 1 for c in canonical} == {False, True}
    for case in canonical:
        assert case.meta["frame"] == {"yaw": 0.0, "offset": [0.0, 0.0, 0.0], "boxes": "aabb"}
        hyp = case.hypotheses[0]
        convention = Convention(case.meta["convention"])
        if (
            convention is Convention.VLMAP
            and case.meta["source"] == "ai2thor"
            and not case.meta["relocated"]
            and hyp.relation in (Relation.ON, Relation.IN)
        ):
            continue  # AI2-THOR's on/in come from its parent receptacles (next test)
        grounding = TrueReading(hyp.relation, tuple(hyp.anchor_ids))
        objects = case.scene_graph.objects
        assert holds(convention, grounding, _target_object(case), objects, _region_volume(case)), case.case_id


def test_ai2thor_on_in_follow_the_parent_receptacles_and_the_rest_the_boxes(built, scenes):
    placements = {s.scene_id: s.placements for s in scenes if s.source == "ai2thor"}
    thor = [
        c
        for split, c in built
        if c.meta["source"] == "ai2thor"
        and c.meta["convention"] == "vlmap"
        and c.meta["rooms"] == 1
        and not c.meta["relocated"]
    ]
    relations = Counter(c.hypotheses[0].relation for c in thor)
    assert relations[Relation.ON] and relations[Relation.IN]
    for case in thor:
        hyp = case.hypotheses[0]
        if hyp.relation in (Relation.ON, Relation.IN):
            known = placements[case.meta["scene_id"]][case.meta["target_id"]]
            assert known[hyp.anchor_ids[0]] is hyp.relation


def test_shifted_maps_are_moved_noisy_partial_copies_of_the_canonical_case(built):
    originals = {c.case_id: c for sp, c in built if sp == "train" and c.meta["augmentation"] == 0}
    moved = [c for sp, c in built if sp == "train" and c.meta["augmentation"] > 0]
    assert len(moved) == 2 * len(originals)
    frames: Counter[tuple[bool, str]] = Counter()
    vocabularies: Counter[tuple[str, str]] = Counter()
    for case in moved:
        base = originals[case.case_id.rsplit("/", 1)[0]]
        assert case.hypotheses == base.hypotheses and case.utterance == base.utterance
        frame, noise = case.meta["frame"], case.meta["noise"]
        motion = FrameMotion(frame["yaw"], tuple(frame["offset"]), frame["boxes"] == "yawed")
        frames[motion.quarter_turns is None, frame["boxes"]] += 1
        assert -2.0 <= frame["offset"][2] <= 5.0
        assert case.target.position == pytest.approx(motion.points(base.target.position).tolist(), abs=1e-6)
        before = {o.id: o for o in base.scene_graph.objects}
        after = case.scene_graph.objects
        assert {o.id for o in after} <= set(before) and set(case.hypotheses[0].anchor_ids) <= {
            o.id for o in after
        }
        droppable = len(before) - len(set(case.hypotheses[0].anchor_ids))
        assert len(before) - len(after) == noise["dropped"]
        # meta rounds the drawn fraction to 4 decimals
        fraction = noise["drop_fraction"]
        low, high = math.floor((fraction - 5e-5) * droppable), math.floor((fraction + 5e-5) * droppable)
        assert low <= noise["dropped"] <= high
        assert noise["drop_fraction"] <= 0.2 and 0.05 <= noise["size_noise"] <= 0.10
        reach = math.sqrt(3) * noise["center_jitter"] + 1e-3
        for o in after:
            expected = motion.points(before[o.id].center)
            assert np.linalg.norm(np.subtract(o.center, expected)) <= reach
            assert o.yaw == pytest.approx(0.0) or frame["boxes"] == "yawed"
        vocabulary = case.meta["label_vocabulary"]
        for o in after:
            clean = before[o.id].label
            if vocabulary == "nyu":
                assert o.label == SCANNET_TO_NYU.get(clean, clean)
            elif vocabulary == "ai2thor_types":
                assert split_camel_case(o.label) == clean and " " not in o.label
            else:
                assert o.label == clean
        vocabularies[case.meta["source"], vocabulary] += 1
    assert frames[True, "yawed"] and frames[True, "aabb"] and frames[False, "aabb"]
    assert vocabularies["scannet", "nyu"] and vocabularies["scannet", "native"]


def test_calib_cases_are_shifted_maps_of_their_own_rooms(built):
    calib = [c for sp, c in built if sp == "calib"]
    assert calib and {c.meta["augmentation"] for c in calib} == {0}
    assert all(c.meta["frame"]["yaw"] not in (0.0,) for c in calib)
    assert any(c.meta["rooms"] > 1 for c in calib)
    assert any(c.meta["label_vocabulary"] != "native" for c in calib)
    assert all(0.10 <= c.meta["noise"]["size_noise"] <= 0.15 for c in calib)


def test_splits_are_disjoint_by_room_and_by_target(built):
    rooms_of = {
        s: {room_key(c.meta["source"], scan) for sp, c in built if sp == s for scan in c.meta["scene_ids"]}
        for s in SPLITS
    }
    trained = rooms_of["train"] | rooms_of["val_seen"]
    assert not rooms_of["val_unseen"] & trained and not rooms_of["calib"] & trained
    assert not rooms_of["val_unseen"] & rooms_of["calib"]
    targets_of = {s: {_target_origin(c) for sp, c in built if sp == s} for s in SPLITS}
    assert targets_of["val_seen"] and not targets_of["val_seen"] & targets_of["train"]
    assert {c.meta["augmentation"] for sp, c in built if sp != "train"} == {0}
    houses = [c for sp, c in built if c.meta["rooms"] > 1]
    assert {sp for sp, c in built if c.meta["rooms"] > 1} == {"train", "calib"}
    for case in houses:
        assert len(case.scene_graph.regions) == case.meta["rooms"] == len(case.meta["scene_ids"])
        regions = {r.id for r in case.scene_graph.regions}
        assert all(o.region_id in regions for o in case.scene_graph.objects)


def test_targets_of_every_size_are_named_in_their_utterance(built, scenes):
    labels = Counter(c.meta["target_name"] for _, c in built)
    assert {"door", "window", "desk", "bed"} & set(labels)
    assert not {"wall", "floor", "ceiling"} & set(labels)
    for _, case in built:
        name = case.meta["target_name"]
        assert any(n in case.utterance for n in (name, *speaker_names(name))), case.utterance
    small = list(build_cases(scenes, dataclasses.replace(CONFIG, all_targets=False, augment=0)))
    assert not {"door", "window", "bed"} & {c.meta["target_name"] for _, c in small}


def test_conventions_option_limits_the_definitions(scenes):
    only = dataclasses.replace(CONFIG, conventions=(Convention.SR3D,), augment=0, house_fraction=0.0)
    cases = [c for _, c in build_cases(scenes, only)]
    assert cases and {c.meta["convention"] for c in cases} == {"sr3d"}
    assert {c.hypotheses[0].relation for c in cases} <= {
        Relation.CLOSEST,
        Relation.FARTHEST,
        Relation.BETWEEN,
        Relation.ON,
        Relation.ABOVE,
        Relation.BELOW,
    }


def test_scannet_rescans_of_one_room_stay_on_one_side(real_scenes):
    assert room_key("scannet", "scene0179_01") == room_key("scannet", "scene0179_00") == "scannet/scene0179"
    assert room_key("ai2thor", "kitchens_13") == "ai2thor/kitchens_13"
    # A second scan "_01" of every ScanNet room: whichever room is drawn, both scans land on its side.
    rescans = [
        dataclasses.replace(s, scene_id=s.scene_id[:-2] + "01") for s in real_scenes if s.source == "scannet"
    ]
    pool = real_scenes + rescans
    config = dataclasses.replace(CONFIG, augment=0, house_fraction=0.0, unseen_fraction=0.4)
    for seed in (0, 1, 2):
        scans: dict[str, set[str]] = {s: set() for s in SPLITS}
        for split, case in build_cases(pool, dataclasses.replace(config, seed=seed)):
            if case.meta["source"] == "scannet":
                scans[split].add(case.meta["scene_id"])
        rooms = {s: {room_key("scannet", scene) for scene in scans[s]} for s in SPLITS}
        assert len(rooms["val_unseen"]) == 1 and len(rooms["calib"]) == 1
        assert not rooms["val_unseen"] & (rooms["train"] | rooms["val_seen"] | rooms["calib"])
        for split in ("val_unseen", "calib"):
            (room,) = rooms[split]
            assert {room.split("/")[1] + "_00", room.split("/")[1] + "_01"} == scans[split]


def test_build_is_deterministic_for_a_seed(scenes, built):
    again = list(build_cases(scenes, CONFIG))
    assert [(s, c.model_dump_json()) for s, c in again] == [(s, c.model_dump_json()) for s, c in built]
    other = list(build_cases(scenes, dataclasses.replace(CONFIG, seed=8)))
    assert [c.utterance for _, c in other] != [c.utterance for _, c in built]


def test_write_build_and_cli_report_the_counts(tmp_path, capsys):
    out = tmp_path / "cases"
    code = main(
        [
            "data",
            "build",
            "--scannet",
            str(SCANNET),
            "--ai2thor",
            str(AI2THOR),
            "--out",
            str(out),
            "--seed",
            "7",
            "--augment",
            "1",
            "--unseen-fraction",
            "0.4",
            "--calib-fraction",
            "0.4",
            "--conventions",
            "vlmap,vla3d",
            "--house-fraction",
            "1",
            "--no-progress",
        ]
    )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["conventions"] == ["vlmap", "vla3d"]
    for split in SPLITS:
        cases = list(read_cases(out / f"{split}.jsonl"))
        assert len(cases) == summary["cases"][split] > 0
        per_relation = Counter((c.meta["source"], c.hypotheses[0].relation.value) for c in cases)
        listed = Counter(
            {(src, r): n for src, counts in summary["counts"][split].items() for r, n in counts.items()}
        )
        assert per_relation == listed
        per_convention = Counter(
            (c.meta["source"], c.meta["convention"], c.hypotheses[0].relation.value) for c in cases
        )
        by_convention = summary["counts_by_convention"][split]
        assert per_convention == Counter(
            {
                (src, conv, r): n
                for src, convs in by_convention.items()
                for conv, counts in convs.items()
                for r, n in counts.items()
            }
        )
        assert sum(summary["ambiguity_histogram"][split].values()) == len(cases)
    assert summary["maps"]["train"]["rooms"] >= 1 and summary["maps"]["calib"]["rooms"] >= 1
    printed = capsys.readouterr().out
    assert str(out) in printed and "calib" in printed
    with pytest.raises(SystemExit, match="conventions"):
        main(["data", "build", "--scannet", str(SCANNET), "--out", str(out), "--conventions", "sr4d"])


def test_write_build_returns_the_summary_it_writes(tmp_path, scenes):
    summary = write_build(scenes, tmp_path, dataclasses.replace(CONFIG, augment=0))
    assert json.loads((tmp_path / "summary.json").read_text())["cases"] == {
        s: summary.total(s) for s in SPLITS
    }
    assert summary.total("train") == sum(1 for _ in read_cases(tmp_path / "train.jsonl"))


def _files_of(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_refused_or_failed_build_leaves_the_previous_build_whole(tmp_path, scenes, monkeypatch):
    out = tmp_path / "cases"
    write_build(scenes, out, dataclasses.replace(CONFIG, augment=0))
    before = _files_of(out)
    assert sorted(before) == sorted([*(f"{s}.jsonl" for s in SPLITS), "summary.json"])

    with pytest.raises(InvalidInput, match="val seen fraction"):
        dataclasses.replace(CONFIG, val_seen_fraction=1.5)
    command = ["data", "build", "--scannet", str(SCANNET), "--out", str(out), "--no-progress"]
    with pytest.raises(
        SystemExit, match=r"vlmap data build: .*unseen fraction must lie in \[0, 1\], got 1.5"
    ):
        main([*command, "--unseen-fraction", "1.5"])
    assert _files_of(out) == before

    def stopped_half_way(*args, **kwargs):  # a build killed or failing after some cases are written
        yield from list(build_cases(*args, **kwargs))[:50]
        msg = "stopped"
        raise RuntimeError(msg)

    monkeypatch.setattr("app.data.build.build_cases", stopped_half_way)
    with pytest.raises(RuntimeError, match="stopped"):
        write_build(scenes, out, dataclasses.replace(CONFIG, augment=1))
    assert _files_of(out) == before  # not a truncated train.jsonl beside the old summary, nor temporary files


def test_summary_lists_the_sources_of_each_split_in_sorted_order():
    summary = BuildSummary()
    summary.scenes["train"].update(["scannet", "ai2thor", "scannet"])  # as a set's hash order may give them
    assert list(summary.to_json()["scenes"]["train"].items()) == [("ai2thor", 1), ("scannet", 2)]
