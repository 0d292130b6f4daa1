"""Relation conventions (vlmap, Sr3D, VLA-3D) on hand-made boxes, the predicates only they use, and their
utterance styles."""

from __future__ import annotations

import numpy as np
import pytest

from app.data.conventions import (
    Convention,
    groundings,
    sr3d_context_ok,
    sr3d_in_center,
    sr3d_next_to,
)
from app.data.templates import SR3D_NEXT_TO_PHRASES, VLA3D_PHRASES, render_sr3d, render_vla3d
from app.grounding import box_relations as rel
from app.grounding.box_relations import Box, TrueReading
from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject

SR3D, VLA3D, VLMAP = Convention.SR3D, Convention.VLA3D, Convention.VLMAP


def obj(id_: str, label: str, lo: list[float], hi: list[float]) -> SceneObject:
    """An object given by its box corners."""
    c = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
    return SceneObject(id=id_, label=label, center=c, size=[b - a for a, b in zip(lo, hi, strict=True)])


def found(convention: Convention, target: SceneObject, others: list[SceneObject], **kw) -> set[TrueReading]:
    return set(groundings(convention, target, others, **kw))


def g(relation: Relation, *anchors: str) -> TrueReading:
    return TrueReading(relation, anchors)


# --- predicates that only other conventions use -------------------------------------------------------------


def test_hull_occupancy_measures_the_share_of_the_footprint_between_two_boxes():
    a = Box(np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 1.0]))
    b = Box(np.array([2.0, 0.0, 0.0]), np.array([3.0, 1.0, 1.0]))
    inside = Box(np.array([0.8, 0.3, 0.0]), np.array([1.2, 0.7, 1.0]))
    half_out = Box(np.array([0.8, 0.5, 0.0]), np.array([1.2, 1.5, 1.0]))  # half above the hull's top edge
    outside = Box(np.array([0.8, 2.0, 0.0]), np.array([1.2, 2.4, 1.0]))
    assert rel.hull_occupancy(inside, a, b) == 1.0
    assert rel.hull_occupancy(half_out, a, b) == pytest.approx(0.5, abs=0.03)
    assert rel.hull_occupancy(outside, a, b) == 0.0
    # The hull of two offset boxes is slanted: a point below the lower box's level at mid-way is inside.
    low = Box(np.array([2.0, -2.0, 0.0]), np.array([3.0, -1.0, 1.0]))
    mid = Box(np.array([0.9, -0.6, 0.0]), np.array([1.1, -0.4, 1.0]))
    assert rel.hull_occupancy(mid, a, low) == 1.0
    assert rel.hull_occupancy(mid, a, b) == 0.0
    # Broadcasting: (2, 1) targets against (1, 2) pairs give a (2, 2) table.
    targets = Box(np.stack([inside.lo, outside.lo])[:, None], np.stack([inside.hi, outside.hi])[:, None])
    firsts = Box(np.stack([a.lo, a.lo])[None], np.stack([a.hi, a.hi])[None])
    seconds = Box(np.stack([b.lo, low.lo])[None], np.stack([b.hi, low.hi])[None])
    assert rel.hull_occupancy(targets, firsts, seconds).shape == (2, 2)


def test_axis_between_needs_the_target_on_the_axis_and_is_symmetric_in_its_anchors():
    rule = {"max_overlap": 0.3, "max_asymmetry": 0.5, "max_gap": 1.0, "min_cross_overlap": 0.5}
    a = Box(np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0]))
    b = Box(np.array([2.0, 0.0, 0.0]), np.array([3.0, 1.0, 1.0]))
    t = Box(np.array([1.2, 0.1, 0.1]), np.array([1.8, 0.9, 0.9]))  # gaps 0.2 of a 0.6 target: -o = 1/3
    assert rel.axis_between(t, a, b, **rule)
    off_axis = Box(np.array([1.2, 1.5, 0.1]), np.array([1.8, 2.3, 0.9]))  # no cross-section overlap
    assert not rel.axis_between(off_axis, a, b, **rule)
    lopsided = Box(np.array([1.05, 0.1, 0.1]), np.array([1.35, 0.9, 0.9]))  # gaps 0.05 and 0.65 of 0.3
    assert not rel.axis_between(lopsided, a, b, **rule)
    far_b = Box(np.array([4.0, 0.0, 0.0]), np.array([5.0, 1.0, 1.0]))  # gap 2.2 > 1 target length
    assert not rel.axis_between(t, a, far_b, **rule)
    # Random rows of three boxes roughly in line: the same verdict whichever anchor comes first.
    rng = np.random.default_rng(0)
    n = 2000
    centres = np.stack([np.zeros(n), np.full(n, 1.5), np.full(n, 3.0)], axis=1)[..., None] * [1.0, 0.0, 0.0]
    centres = centres + rng.normal(0.0, 0.3, size=(n, 3, 3))
    half = rng.uniform(0.1, 0.7, size=(n, 3, 3))
    target, first, second = (Box(centres[:, k] - half[:, k], centres[:, k] + half[:, k]) for k in (1, 0, 2))
    forward = rel.axis_between(target, first, second, **rule)
    assert np.array_equal(forward, rel.axis_between(target, second, first, **rule))
    assert 0 < forward.sum() < n


def test_ordinal_relations_by_surface_distance_and_ranked_by_a_scaled_gap():
    door = Box(np.array([[0.0, 0.0, 0.0]]), np.array([[0.1, 1.0, 2.0]]))
    target = Box(np.array([0.6, 0.0, 0.0]), np.array([1.1, 0.5, 0.9]))  # 0.5 m from the door's face
    twin = Box(np.array([[0.85, 0.5, 0.0]]), np.array([[1.35, 1.0, 0.9]]))  # 0.75 m: 0.25 farther
    by_centre = rel.ordinal_relations(target, twin, door)
    by_surface = rel.ordinal_relations(target, twin, door, min_gap=0.2, min_ratio=0.0, surface=True)
    assert not by_centre[0][0] and by_surface[0][0]
    # Ranked: three chairs 1, 2 and 3 m away; 0.5 m boxes: gaps x mean length 0.5 > 0.2 over every place.
    chairs = [Box(np.array([d, 0.0, 0.0]), np.array([d + 0.5, 0.5, 0.5])) for d in (1.0, 2.0, 3.0)]
    anchor = Box(np.array([[-0.25, 0.0, 0.0]]), np.array([[0.25, 0.5, 0.5]]))

    def stack(boxes: list[Box]) -> Box:
        return Box(np.stack([b.lo for b in boxes]), np.stack([b.hi for b in boxes]))

    first = rel.ranked_ordinal_relations(chairs[0], stack(chairs[1:]), anchor, depth=3, min_scaled_gap=0.2)
    last = rel.ranked_ordinal_relations(chairs[2], stack(chairs[:2]), anchor, depth=3, min_scaled_gap=0.2)
    assert first[0][0] and not first[1][0] and last[1][0] and not last[0][0]
    crowded = [*chairs[1:], Box(np.array([3.3, 0.0, 0.0]), np.array([3.8, 0.5, 0.5]))]  # 0.3 x 0.5 < 0.2
    assert rel.ranked_ordinal_relations(chairs[0], stack(crowded), anchor, depth=3, min_scaled_gap=0.2)[0][0]
    assert not rel.ranked_ordinal_relations(
        chairs[2], stack([chairs[0], crowded[0], crowded[2]]), anchor, depth=3, min_scaled_gap=0.2
    )[1][0]


# --- Sr3D ---------------------------------------------------------------------------------------------------


DOOR = obj("door", "door", [0.0, 0.0, 0.0], [0.1, 1.0, 2.0])


def chair(id_: str, x: float, y: float = 0.0) -> SceneObject:
    return obj(id_, "chair", [x, y, 0.0], [x + 0.5, y + 0.5, 0.9])


def test_sr3d_closest_and_farthest_among_two_to_six_of_a_class_from_a_unique_anchor():
    near, mid, far = chair("c1", 0.6), chair("c2", 0.85, 1.2), chair("c3", 3.0)
    room = [DOOR, mid, far]
    assert found(SR3D, near, room) == {g(Relation.CLOSEST, "door")}  # 0.5 vs 0.75 m: gap 0.25 >= 0.2
    assert found(SR3D, far, [DOOR, near, mid]) == {g(Relation.FARTHEST, "door")}
    close_twin = chair("c4", 0.7, 1.2)  # 0.6 m: gap 0.1 < 0.2
    assert not found(SR3D, near, [DOOR, close_twin, far])
    second_door = obj("door2", "door", [5.0, 0.0, 0.0], [5.1, 1.0, 2.0])
    assert not found(SR3D, near, [*room, second_door])  # the anchor must be unique
    towel = obj("towel", "towel", [0.0, 3.0, 0.5], [0.1, 3.5, 1.0])  # an excluded anchor class
    assert all(x.anchor_ids != ("towel",) for x in found(SR3D, near, [*room, towel]))
    alone = found(SR3D, near, [DOOR])
    crowd = [DOOR, *(chair(f"x{k}", 1.0 + k, 3.0) for k in range(6))]  # seven chairs: "too hard"
    assert not alone and not found(SR3D, near, crowd)
    assert not sr3d_context_ok(near, [DOOR]) and not sr3d_context_ok(near, crowd)
    assert sr3d_context_ok(near, room)


def test_sr3d_between_in_the_hull_of_two_unique_anchors_without_ambiguous_distractors():
    sofa = obj("sofa", "sofa", [-1.0, 0.0, 0.0], [0.0, 1.0, 0.9])
    armchair = obj("arm", "armchair", [2.0, 0.0, 0.0], [3.0, 1.0, 0.9])
    lamp = obj("l1", "lamp", [0.8, 0.35, 0.0], [1.2, 0.75, 1.5])
    far_lamp = obj("l2", "lamp", [8.0, 8.0, 0.0], [8.4, 8.4, 1.5])
    assert g(Relation.BETWEEN, "sofa", "arm") in found(SR3D, lamp, [sofa, armchair, far_lamp])
    rival = obj("l2", "lamp", [1.5, 0.3, 0.0], [1.9, 0.7, 1.5])  # another lamp in the hull: ambiguous
    assert not any(x.relation is Relation.BETWEEN for x in found(SR3D, lamp, [sofa, armchair, rival]))
    hovering = obj("l1", "lamp", [0.8, 0.3, 1.6], [1.2, 0.7, 2.0])  # no height overlap with the anchors
    assert not any(x.relation is Relation.BETWEEN for x in found(SR3D, hovering, [sofa, armchair, far_lamp]))
    touching = obj("arm", "armchair", [-0.5, 0.5, 0.0], [0.5, 1.5, 0.9])  # footprints meet the sofa's
    assert not any(x.relation is Relation.BETWEEN for x in found(SR3D, lamp, [sofa, touching, far_lamp]))
    assert sr3d_in_center(lamp, sofa, armchair)
    assert not sr3d_in_center(obj("l3", "lamp", [0.1, 0.8, 0.0], [0.3, 2.0, 1.0]), sofa, armchair)


def test_sr3d_support_above_below_for_a_unique_pair_of_classes():
    table = obj("t", "table", [0.0, 0.0, 0.0], [1.0, 1.0, 0.75])
    book = obj("b1", "book", [0.2, 0.2, 0.80], [0.4, 0.5, 0.85])  # 5 cm over the top: touching
    other_book = obj("b2", "book", [3.0, 3.0, 0.0], [3.2, 3.3, 0.05])
    vertical = {Relation.ON, Relation.ABOVE, Relation.BELOW}

    def found_vertical(target: SceneObject, others: list[SceneObject]) -> set[TrueReading]:
        return {x for x in found(SR3D, target, others) if x.relation in vertical}

    assert found_vertical(book, [table, other_book]) == {g(Relation.ON, "t")}
    second_on_table = obj("b2", "book", [0.6, 0.6, 0.76], [0.8, 0.9, 0.80])
    assert not found_vertical(book, [table, second_on_table])  # two (book, table) pairs: not unique
    lamp = obj("l1", "lamp", [0.3, 0.3, 1.5], [0.6, 0.6, 1.8])  # 0.75 m over the table
    other_lamp = obj("l2", "lamp", [4.0, 4.0, 1.5], [4.3, 4.3, 1.8])
    assert found_vertical(lamp, [table, other_lamp]) == {g(Relation.ABOVE, "t")}
    shelf = obj("s", "shelf", [0.0, 0.0, 1.2], [1.0, 0.4, 1.3])  # on a wall
    box = obj("x1", "box", [0.2, 0.0, 0.0], [0.6, 0.4, 0.4])
    other_box = obj("x2", "box", [4.0, 0.0, 0.0], [4.4, 0.4, 0.4])
    assert found_vertical(box, [shelf, other_box]) == {g(Relation.BELOW, "s")}
    # A table carrying a lamp supports it: Sr3D's "supporting", skipped, and it pre-empts "below".
    lit = obj("l1", "lamp", [0.3, 0.3, 0.76], [0.6, 0.6, 1.2])
    other_table = obj("t2", "table", [5.0, 0.0, 0.0], [6.0, 1.0, 0.75])
    assert not found_vertical(table, [lit, other_table])


def test_sr3d_next_to_phrasing_condition():
    near = chair("c1", 0.6)
    assert sr3d_next_to(near, DOOR, [DOOR, chair("c2", 3.0)])
    blocking = obj("bin", "trash can", [0.15, 0.0, 0.0], [0.55, 0.5, 0.6])  # wholly between the two
    assert not sr3d_next_to(near, DOOR, [DOOR, blocking])
    wall = obj("w", "wall", [0.15, -1.0, 0.0], [0.55, 2.0, 2.5])  # walls do not block
    assert sr3d_next_to(near, DOOR, [DOOR, wall])
    assert not sr3d_next_to(chair("c3", 2.0), DOOR, [DOOR])  # 1.9 m apart: more than 1.2


# --- VLA-3D -------------------------------------------------------------------------------------------------

BED = obj("bed", "bed", [0.0, 0.0, 0.0], [2.0, 1.6, 0.6])


def test_vla3d_on_in_and_the_cabinet_band():
    pillow = obj("p1", "pillow", [0.2, 0.2, 0.45], [0.7, 0.6, 0.65])  # sunk into the mattress
    assert g(Relation.ON, "bed") in found(VLA3D, pillow, [BED])
    second = obj("p2", "pillow", [1.2, 0.2, 0.45], [1.7, 0.6, 0.65])
    assert g(Relation.ON, "bed") not in found(VLA3D, pillow, [BED, second])  # two pillows on it: not unique
    fridge = obj("f", "refrigerator", [0.0, 0.0, 0.0], [0.8, 0.7, 1.8])
    cup = obj("cup", "cup", [0.2, 0.2, 1.0], [0.3, 0.3, 1.1])
    assert found(VLA3D, cup, [fridge]) & {g(Relation.IN, "f"), g(Relation.ON, "f")} == {g(Relation.IN, "f")}
    cabinet = obj("cab", "cabinet", [0.0, 0.0, 0.0], [1.0, 0.5, 1.0])
    low = obj("v1", "vase", [0.3, 0.1, 0.2], [0.5, 0.3, 0.5])  # top below 0.9: in
    high = obj("v1", "vase", [0.3, 0.1, 0.7], [0.5, 0.3, 0.95])  # top in the upper 10 %: on
    assert found(VLA3D, low, [cabinet]) & {g(Relation.IN, "cab"), g(Relation.ON, "cab")} == {
        g(Relation.IN, "cab")
    }
    assert found(VLA3D, high, [cabinet]) & {g(Relation.IN, "cab"), g(Relation.ON, "cab")} == {
        g(Relation.ON, "cab")
    }


def test_vla3d_near_scales_with_the_region_volume():
    table = obj("t", "table", [0.0, 0.0, 0.0], [1.0, 1.0, 0.75])
    stool = obj("s", "stool", [1.4, 0.0, 0.0], [1.8, 0.4, 0.5])  # centres 1.04 m apart
    assert g(Relation.NEAR, "t") in found(VLA3D, stool, [table], region_volume=120.0)  # 1.2 m
    assert g(Relation.NEAR, "t") not in found(VLA3D, stool, [table], region_volume=80.0)  # 0.8 m
    assert g(Relation.NEAR, "t") in found(VLMAP, stool, [table])  # 0.4 m between the surfaces


def test_vla3d_above_has_no_height_limit_and_below_knows_furniture_and_hanging_anchors():
    table = obj("t", "table", [0.0, 0.0, 0.0], [1.0, 1.0, 0.75])
    lamp = obj("l", "lamp", [0.3, 0.3, 2.4], [0.7, 0.7, 2.6])  # 1.65 m over the table
    assert g(Relation.ABOVE, "t") in found(VLA3D, lamp, [table])
    assert g(Relation.ABOVE, "t") not in found(VLMAP, lamp, [table])  # vlmap stops at 1.5 m
    box = obj("x", "box", [0.2, 0.2, 0.0], [0.6, 0.6, 0.4])
    assert g(Relation.BELOW, "t") in found(VLA3D, box, [table])
    shelf = obj("s", "shelf", [0.0, 0.0, 1.6], [1.0, 0.4, 1.7])  # furniture with space under it
    tv = obj("tv", "tv", [0.0, 0.0, 1.6], [1.0, 0.1, 2.2])  # a hanging anchor
    bin_ = obj("b", "trash can", [0.2, 0.0, 0.0], [0.6, 0.1, 0.5])
    seat = obj("c", "chair", [0.2, 0.0, 0.0], [0.6, 0.1, 0.9])  # a supporting structure: never hanging-below
    assert g(Relation.BELOW, "s") in found(VLA3D, seat, [shelf])
    assert g(Relation.BELOW, "tv") in found(VLA3D, bin_, [tv])
    assert g(Relation.BELOW, "tv") not in found(VLA3D, seat, [tv])


def test_vla3d_between_and_closest_and_the_excluded_classes():
    sofa = obj("sofa", "sofa", [0.0, 0.0, 0.0], [1.0, 1.0, 0.9])
    armchair = obj("arm", "armchair", [2.0, 0.0, 0.0], [3.0, 1.0, 0.9])
    table = obj("t", "coffee table", [1.2, 0.1, 0.0], [1.8, 0.9, 0.5])
    assert g(Relation.BETWEEN, "sofa", "arm") in found(VLA3D, table, [sofa, armchair])
    c1, c2, c3 = chair("c1", 1.0), chair("c2", 2.0), chair("c3", 3.0)
    lamp = obj("lamp", "lamp", [-0.5, 0.0, 0.0], [0.0, 0.5, 1.5])
    assert g(Relation.CLOSEST, "lamp") in found(VLA3D, c1, [lamp, c2, c3])
    assert g(Relation.FARTHEST, "lamp") in found(VLA3D, c3, [lamp, c1, c2])
    wall = obj("w", "wall", [-0.2, -1.0, 0.0], [-0.1, 3.0, 2.5])
    assert all("w" not in x.anchor_ids for x in found(VLA3D, c1, [wall, lamp, c2, c3]))
    assert not found(VLA3D, wall, [lamp, c1])  # walls are never targets


# --- styles -------------------------------------------------------------------------------------------------


def test_each_convention_speaks_in_its_own_style():
    rng = np.random.default_rng(0)
    closest = {render_sr3d(Relation.CLOSEST, "chair", ("door",), rng) for _ in range(60)}
    assert {t.split(" that ")[0] for t in closest} == {
        "the chair",
        "find the chair",
        "choose the chair",
        "select the chair",
    }
    assert {t.split(" is ")[1].rsplit(" the ", 1)[0] for t in closest} == {"closer to", "close to", "near"}
    next_to = {render_sr3d(Relation.CLOSEST, "chair", ("door",), rng, next_to=True) for _ in range(40)}
    assert all(any(p in t for p in SR3D_NEXT_TO_PHRASES) for t in next_to)
    middle = render_sr3d(Relation.BETWEEN, "kitchen cabinets", ("sink", "stove"), rng, in_center=True)
    assert " are in the " in middle and middle.endswith("of the sink and the stove")
    with pytest.raises(ValueError, match="Sr3D has no"):
        render_sr3d(Relation.NEAR, "chair", ("door",), rng)
    statement = render_vla3d(Relation.ON, "pillow", ("bed",), rng)
    assert statement in {f"the pillow that is {p} the bed" for p in VLA3D_PHRASES[Relation.ON]}
    pair = render_vla3d(Relation.BETWEEN, "lamp", ("chair", "chair"), rng)
    assert pair.endswith("the chair and the other chair")
