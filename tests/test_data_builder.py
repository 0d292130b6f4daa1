"""The grounding-case builder: relation predicates on hand-made boxes, AI2-THOR reading, and the builder
end to end on real fixture scenes (tests/resources/data)."""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from app.data import relations as rel
from app.data.build import (
    SPLITS,
    BuildConfig,
    RigidMotion,
    build_cases,
    move_case,
    read_ai2thor,
    read_scannet,
    room_key,
    split_camel_case,
    thor_placement_relation,
    write_build,
)
from app.data.cases import read_cases
from app.data.relations import Box, Grounding, holds, true_groundings
from app.data.templates import RELATION_PHRASES, indefinite, is_plural, render_utterance
from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject

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
    assert Grounding(Relation.ON, ("t",)) in found
    assert Grounding(Relation.NEAR, ("t",)) not in found


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
    assert (
        rel.same_kind("book", "Books")
        and rel.same_kind("box", "boxes")
        and not rel.same_kind("cup", "cupboard")
    )


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

CONFIG = BuildConfig(seed=7, augment=2, max_cases_per_scene=30, unseen_fraction=0.4, val_seen_fraction=0.2)


@pytest.fixture(scope="module")
def scenes():
    return read_scannet(SCANNET) + read_ai2thor(AI2THOR)


@pytest.fixture(scope="module")
def built(scenes):
    return list(build_cases(scenes, CONFIG))


def _target_object(case) -> SceneObject:
    return SceneObject(
        id="__target__", label=case.target.label, center=case.target.position, size=case.target.size
    )


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
        assert case.utterance.strip()


def test_scannet_relations_hold_geometrically_also_after_augmentation(built):
    scannet = [c for _, c in built if c.meta["source"] == "scannet"]
    assert {c.meta["augmentation"] for c in scannet} == {0, 1, 2}
    assert len({c.hypotheses[0].relation for c in scannet}) >= 6
    for case in scannet:
        hyp = case.hypotheses[0]
        grounding = Grounding(hyp.relation, tuple(hyp.anchor_ids))
        assert holds(grounding, _target_object(case), case.scene_graph.objects), case.case_id


def test_ai2thor_on_in_follow_the_parent_receptacles_and_the_rest_the_boxes(built, scenes):
    placements = {s.scene_id: s.placements for s in scenes if s.source == "ai2thor"}
    thor = [c for _, c in built if c.meta["source"] == "ai2thor"]
    relations = Counter(c.hypotheses[0].relation for c in thor)
    assert relations[Relation.ON] and relations[Relation.IN]
    for case in thor:
        hyp = case.hypotheses[0]
        if hyp.relation in (Relation.ON, Relation.IN):
            known = placements[case.meta["scene_id"]][case.meta["target_id"]]
            assert known[hyp.anchor_ids[0]] is hyp.relation
        else:
            grounding = Grounding(hyp.relation, tuple(hyp.anchor_ids))
            assert holds(grounding, _target_object(case), case.scene_graph.objects), case.case_id


def test_splits_are_disjoint_by_scene_and_by_target(built):
    scenes_of = {s: {c.meta["scene_id"] for sp, c in built if sp == s} for s in SPLITS}
    assert not scenes_of["val_unseen"] & (scenes_of["train"] | scenes_of["val_seen"])
    targets_of = {
        s: {(c.meta["scene_id"], c.meta["target_id"]) for sp, c in built if sp == s} for s in SPLITS
    }
    assert targets_of["val_seen"] and not targets_of["val_seen"] & targets_of["train"]
    assert {c.meta["augmentation"] for sp, c in built if sp != "train"} == {0}


def test_scannet_rescans_of_one_room_stay_on_one_side(scenes):
    assert room_key("scannet", "scene0179_01") == room_key("scannet", "scene0179_00") == "scannet/scene0179"
    assert room_key("ai2thor", "kitchens_13") == "ai2thor/kitchens_13"
    # A second scan "_01" of every ScanNet room: whichever room is drawn, both scans land on its side.
    rescans = [
        dataclasses.replace(s, scene_id=s.scene_id[:-2] + "01") for s in scenes if s.source == "scannet"
    ]
    pool = scenes + rescans
    for seed in (0, 1, 2):
        scans: dict[str, set[str]] = {s: set() for s in SPLITS}
        for split, case in build_cases(pool, dataclasses.replace(CONFIG, seed=seed, augment=0)):
            if case.meta["source"] == "scannet":
                scans[split].add(case.meta["scene_id"])
        rooms = {s: {room_key("scannet", scene) for scene in scans[s]} for s in SPLITS}
        assert len(rooms["val_unseen"]) == 1
        assert not rooms["val_unseen"] & (rooms["train"] | rooms["val_seen"])
        (room,) = rooms["val_unseen"]
        assert {room.split("/")[1] + "_00", room.split("/")[1] + "_01"} == scans["val_unseen"]


def test_build_is_deterministic_for_a_seed(scenes, built):
    again = list(build_cases(scenes, CONFIG))
    assert [(s, c.model_dump_json()) for s, c in again] == [(s, c.model_dump_json()) for s, c in built]
    other = list(build_cases(scenes, dataclasses.replace(CONFIG, seed=8)))
    assert [c.utterance for _, c in other] != [c.utterance for _, c in built]


def test_augmentation_is_a_rigid_motion_of_the_whole_scene(built):
    originals = {c.case_id: c for sp, c in built if sp == "train" and c.meta["augmentation"] == 0}
    moved = [c for sp, c in built if sp == "train" and c.meta["augmentation"] > 0]
    assert len(moved) == 2 * len(originals)
    for case in moved:
        base = originals[case.case_id.rsplit("/", 1)[0]]
        assert case.hypotheses == base.hypotheses and case.utterance == base.utterance
        anchor = case.hypotheses[0].anchor_ids[0]
        d_new = np.subtract(case.target.position, case.scene_graph.object(anchor).center)
        d_old = np.subtract(base.target.position, base.scene_graph.object(anchor).center)
        assert np.linalg.norm(d_new) == pytest.approx(np.linalg.norm(d_old))
        assert d_new[2] == pytest.approx(d_old[2])
        assert sorted(case.target.size) == pytest.approx(sorted(base.target.size))


def test_quarter_turn_moves_boxes_exactly():
    motion = RigidMotion(1, (2.0, -1.0))
    assert motion.point([1.0, 0.5, 0.3]) == [-0.5 + 2.0, 1.0 - 1.0, 0.3]
    assert motion.size([0.4, 0.2, 0.9]) == [0.2, 0.4, 0.9]
    table = obj("t", "table", [0, 0, 0.375], [1.2, 0.8, 0.75])
    mug = obj("m", "mug", [0.5, 0.3, 0.8], [0.1, 0.1, 0.1])
    for quarter in range(4):
        m = RigidMotion(quarter, (0.3, 0.7))
        assert rel.is_on(Box.of(m.object(mug)), Box.of(m.object(table)))


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
            "--no-progress",
        ]
    )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    for split in SPLITS:
        cases = list(read_cases(out / f"{split}.jsonl"))
        assert len(cases) == summary["cases"][split] > 0
        per_relation = Counter((c.meta["source"], c.hypotheses[0].relation.value) for c in cases)
        listed = Counter(
            {(src, r): n for src, counts in summary["counts"][split].items() for r, n in counts.items()}
        )
        assert per_relation == listed
        assert sum(summary["ambiguity_histogram"][split].values()) == len(cases)
    assert str(out) in capsys.readouterr().out


def test_write_build_returns_the_summary_it_writes(tmp_path, scenes):
    summary = write_build(scenes, tmp_path, dataclasses.replace(CONFIG, augment=0))
    assert json.loads((tmp_path / "summary.json").read_text())["cases"] == {
        s: summary.total(s) for s in SPLITS
    }
    assert summary.total("train") == sum(1 for _ in read_cases(tmp_path / "train.jsonl"))


def test_move_case_keeps_the_graph_valid(built):
    _, case = built[0]
    moved = move_case(case, RigidMotion(3, (1.0, 2.0)))
    again = type(case).model_validate_json(moved.model_dump_json())
    assert again.scene_graph.objects[0].center != case.scene_graph.objects[0].center
    assert {o.id for o in again.scene_graph.objects} == {o.id for o in case.scene_graph.objects}
