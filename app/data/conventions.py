"""Relation conventions: how three datasets decide from boxes that a target stands in a relation to anchors.

A grounding case carries `meta["convention"]`, the convention its relation was computed by. All three map
onto the project's fixed relation set (`app.grounding.relations.Relation`) and use the box predicates of
`app.grounding.box_relations` (the one set of box relations), with their own thresholds. Notation: for boxes t
(target) and a (anchor), b_x / t_x are the bottom / top heights, h_x the height, F_x the footprint,
IoM(F_t, F_a) = |F_t ∩ F_a| / min(|F_t|, |F_a|), cover(t, a) = |F_t ∩ F_a| / |F_t|, c_x the centre.
"Class" is `app.vocabulary.class_key`: the same class up to lemmas and synonyms ("sofa" / "couch"). In
every convention an anchor is never of the target's class and never a generic label ("object": it cannot
be named), and the target is never floor, ceiling or wall.

vlmap (the project's own; `app.grounding.box_relations.true_groundings`, its thresholds named there)
    on, in, above, below, near, between (segment between two anchors), closest / farthest among the
    target's class by centre distance with a margin, as defined in `app.grounding.box_relations`.

sr3d (ReferIt3D's Sr3D generator, `referit3d/data_generation/sr3d/`: the generators and their hp.yml)
    Contexts: the target's class has 2..SR3D_MAX_CONTEXT objects (create_sr3d.py --stimulus_is_too_hard 6;
    the published Sr3D refers only to targets with same-class distractors, as every case of the Sr3D dev
    set does).
    closest / farthest (horizontal proximity): anchors unique in the map (their class has one object), not
    of the classes SR3D_PROXIMITY_EXCLUDED; with d the box surface-to-surface distance from the anchor (the
    generator takes the nearest-neighbour distance between the two point clouds),
        closest   <=>  d_t + SR3D_HORIZONTAL_GAP <= min over same-class distractors d_s
        farthest  <=>  d_t - SR3D_HORIZONTAL_GAP >= max over same-class distractors d_s
    between: unique anchors of different classes whose footprints do not meet (IoU < SR3D_ANCHOR_MAX_IOU),
    not of SR3D_PROXIMITY_EXCLUDED; with occ(x) = |F_x ∩ hull(F_a1 ∪ F_a2)| / |F_x|,
        between  <=>  occ(t) >= SR3D_BETWEEN_MIN_OCCUPANCY
                 and  cover(t, a_i) <= SR3D_BETWEEN_MAX_ANCHOR_COVER              (i = 1, 2)
                 and  overlap of [b_t, t_t] with [b_ai, t_ai] >= SR3D_BETWEEN_MIN_Z_OVERLAP h_t   (i = 1, 2)
                 and  every same-class distractor s: |c_s - c_t|_xy >= SR3D_BETWEEN_SAFE_DISTANCE
                 and  every same-class distractor s: occ(s) <= SR3D_BETWEEN_AMBIGUOUS_OCCUPANCY
        (the last rule is the generator's "bad combination" and uniqueness filters together: a distractor
        in the hull makes the pair of anchors ambiguous for the class).
    support / above / below (vertical proximity), anchors of at most SR3D_MAX_CONTEXT objects, not of
    SR3D_VERTICAL_EXCLUDED; in this order of preference:
        supported-by (-> on)  <=>  cover(t, a) > SR3D_MIN_SUPPORTED_COVER
                                   and |b_t - t_a| <= SR3D_MAX_TOUCH_DISTANCE
                                   and |F_t| / |F_a| < SR3D_MAX_SUPPORTING_AREA_RATIO
        supporting            <=>  the same with t and a swapped: the target carries the anchor. Skipped:
                                   Sr3D phrases it "the table with the lamp on top of it", which reads as
                                   "on" and would teach the opposite place; it still pre-empts above/below
        above                 <=>  b_t - t_a > SR3D_MIN_VERTICAL_GAP
                                   and IoM(F_t, F_a) > SR3D_MIN_VERTICAL_OVERLAP
        below                 <=>  b_a - t_t > SR3D_MIN_VERTICAL_GAP
                                   and IoM(F_t, F_a) > SR3D_MIN_VERTICAL_OVERLAP
    and the pair of classes is unique: exactly one (object of the target's class, object of the anchor's
    class) pair of the map is in any vertical relation (the generator's `force_uniqueness` key), and no two
    objects of the target's class overlap by more than SR3D_MAX_DISTRACTOR_OVERLAP of a box's volume.
    The generator's "can support" / "cannot be supported" class lists are not published with it; the vlmap
    label policy stands in (`anchor_allowed(ON)`, `is_structure`).
    Allocentric relations (left / right / front / back) have no relation of ours and are not generated.

vla3d (VLA-3D's scene-graph generator `scene_graph/generate_scene_info.py` with its argument defaults, the
label classes of `scene_graph/special_relation_classes.py`, the README's relation table; the README states
no thresholds, so every number below is the code's default)
    above  <=>  b_t - t_a > VLA3D_ON_THRES and IoM(F_t, F_a) > VLA3D_VERTICAL_IOM
    below  <=>  (b_a - t_t > 0 and IoM > VLA3D_VERTICAL_IOM and the target is not of VLA3D_SUPPORTING)
                or (a of VLA3D_UNDER and b_t <= b_a + VLA3D_UNDER_THRES and t_t <= t_a
                    and IoM > VLA3D_VERTICAL_IOM)
    on     <=>  b_a + VLA3D_UNDER_THRES <= b_t <= t_a + VLA3D_ON_THRES and cover(t, a) > VLA3D_VERTICAL_IOM
                and |F_t| < |F_a| and a not of VLA3D_VERTICAL_STRUCTURES, t not of VLA3D_STRUCTURES
                and not (a of VLA3D_IN and t smaller than a along every axis)
                and (a not a cabinet, or t_t > t_a - VLA3D_IN_THRES h_a)
    in     <=>  a of VLA3D_IN or a cabinet, c_t inside a, b_a < b_t, t_t < t_a, t smaller than a along
                every axis, and (a not a cabinet, or t_t <= t_a - VLA3D_IN_THRES h_a)
    near   <=>  |c_t - c_a| < VLA3D_NEAR_THRES V, V the volume of the target's region box (m^3 taken as m)
    between: with u the unit xy vector from c_a1 to c_a2, intervals [l, h] (length w) of the boxes
             projected on u, o_2 = (h_t - l_a2) / min(w_t, w_a2), o_1 = (h_a1 - l_t) / min(w_t, w_a1):
             c_a1.u < c_t.u < c_a2.u, o_i < VLA3D_OVERLAP_THRES, |o_1 - o_2| < VLA3D_SYMMETRY_THRES,
             -o_i < VLA3D_DISTANCE_THRES, and IoM of the cross-sections in the plane across u
             > VLA3D_BETWEEN_IOM (`app.grounding.box_relations.axis_between`). The generator's second,
             vertical variant (a target between two objects stacked in z) is left out: our "between" is read
             in the floor plane.
    closest / farthest: the target's class sorted by centre distance from the anchor; the target first
             (last) and (d_(j+1) - d_(j)) L > VLA3D_ORDERED_THRES over the first (last) VLA3D_ORDERED_DEPTH
             places, L their mean box length along the direction to the anchor
             (`app.grounding.box_relations.ranked_ordinal_relations`).
    Comparisons at the generator's zero thresholds take `app.grounding.box_relations.ROUND_OFF` of slack
    (AI2-THOR boxes touch exactly; a float's round-off must not decide).
    second_/third_closest and _farthest are not "closest": they are not generated. "beside" is listed by
    the generator but never computed (its code is commented out); it would be "near". "hanging_on" (a box
    within VLA3D hanging_thres_h of a wall-like anchor's side) is not mapped to "on": our "on" puts the
    target on the anchor's top surface, which is not where a picture hanging on a wall is.
    Uniqueness: a VLA-3D statement identifies its target, adding colours and sizes where space does not
    suffice ("Unique" in the README's language generation). Without colours, a binary relation is kept
    only when no other object of the target's class stands in it to the same anchor, "between" when none
    lies between the same two anchors; closest / farthest are unique by definition.

The generators give every threshold used here; none had to be sampled.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from enum import StrEnum

import numpy as np

from app.grounding.box_relations import (
    ROUND_OFF,
    BeneathRule,
    Box,
    InRule,
    OnRule,
    TrueReading,
    VerticalRule,
    anchor_allowed,
    axis_between,
    centre_distance,
    fits_inside,
    footprint_area,
    footprint_intersection,
    footprint_iou,
    height_overlap,
    hull_occupancy,
    is_above,
    is_below,
    is_in,
    is_near,
    is_on,
    is_room_shell,
    is_structure,
    label_set,
    ordinal_relations,
    ranked_ordinal_relations,
    top_in_upper_band,
    true_groundings,
    volume_overlap,
)
from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject
from app.vocabulary import class_key, in_classes


class Convention(StrEnum):
    """Whose definitions a case's relation follows."""

    VLMAP = "vlmap"
    SR3D = "sr3d"
    VLA3D = "vla3d"


# --- Sr3D: referit3d/data_generation/sr3d -------------------------------------------------------------------
# create_sr3d.py --stimulus_is_too_hard (default 6): at most this many objects of the target's class.
SR3D_MAX_CONTEXT = 6
# horizontal_proximity/hp.yml horizontal_gap.
SR3D_HORIZONTAL_GAP = 0.2
# horizontal_proximity/hp.yml and between/hp.yml exclude_anchor_instances.
SR3D_PROXIMITY_EXCLUDED = label_set("clothing, clothes, cup, books, book, bottle, towel")
# between/hp.yml: occ_thresh, min_forbidden_occ_ratio, target_anchor_intersect_ratio_thresh,
# min_target_to_anchor_z_intersection, safe_distance; between_generator.valid_between_anchors: IoU < 0.001.
SR3D_BETWEEN_MIN_OCCUPANCY = 0.51
SR3D_BETWEEN_AMBIGUOUS_OCCUPANCY = 0.1
SR3D_BETWEEN_MAX_ANCHOR_COVER = 0.1
SR3D_BETWEEN_MIN_Z_OVERLAP = 0.2
SR3D_BETWEEN_SAFE_DISTANCE = 0.3
SR3D_ANCHOR_MAX_IOU = 0.001
# vertical_proximity/hp.yml: max_touch_distance, min_above_below_distance, max_supporting_area_ratio,
# min_supported_area_ratio, min_to_be_above_below_area_ratio, exclude_anchor_instances.
SR3D_MAX_TOUCH_DISTANCE = 0.15
SR3D_MIN_VERTICAL_GAP = 0.06
SR3D_MAX_SUPPORTING_AREA_RATIO = 1.5
SR3D_MIN_SUPPORTED_COVER = 0.3
SR3D_MIN_VERTICAL_OVERLAP = 0.2
SR3D_VERTICAL_EXCLUDED = label_set("cup, keyboard")
# vertical_generator.py: contexts whose same-class objects overlap by more than this share of a box's volume.
SR3D_MAX_DISTRACTOR_OVERLAP = 0.3
# reference.py, the phrasing conditions: NEXT_TO (closest within this xy distance, and no object with more
# than SR3D_NEXT_TO_BLOCKING of its footprint in the hull of the two) and IN_CENTER (the target within this
# angle of the line between the anchors, seen from each anchor).
SR3D_NEXT_TO_DISTANCE = 1.2
SR3D_NEXT_TO_BLOCKING = 0.5
SR3D_IN_CENTER_ANGLE = math.radians(30.0)

SR3D_SUPPORT = OnRule(
    gap=SR3D_MAX_TOUCH_DISTANCE,
    sink=SR3D_MAX_TOUCH_DISTANCE,
    min_bottom_fraction=0.0,
    xy_margin=None,
    min_cover=SR3D_MIN_SUPPORTED_COVER,
    max_area_ratio=SR3D_MAX_SUPPORTING_AREA_RATIO,
    must_poke_out=False,
)
SR3D_VERTICAL = VerticalRule(
    min_gap=SR3D_MIN_VERTICAL_GAP, max_gap=math.inf, min_overlap=SR3D_MIN_VERTICAL_OVERLAP
)

# --- VLA-3D: scene_graph/generate_scene_info.py argument defaults -------------------------------------------
VLA3D_VERTICAL_IOM = 0.5  # --vertical_iom
VLA3D_ON_THRES = 0.01  # --on_thres
VLA3D_UNDER_THRES = 0.01  # --under_thres
VLA3D_IN_THRES = 0.1  # --in_thres
VLA3D_NEAR_THRES = 0.01  # --near_thres (times the region's volume)
VLA3D_BETWEEN_IOM = 0.5  # --between_iom
VLA3D_OVERLAP_THRES = 0.3  # --overlap_thres
VLA3D_SYMMETRY_THRES = 0.5  # --symmetry_thres
VLA3D_DISTANCE_THRES = 1.0  # --distance_thres
VLA3D_ORDERED_THRES = 0.2  # --ordered_thres
VLA3D_ORDERED_DEPTH = 3  # relate_ordered keeps the first three (closest, second_, third_closest)
# special_relation_classes.py (NYU class names; matched to map labels through the vocabulary). ScanNet's
# "clothes dryer" is NYU's "clothing dryer".
VLA3D_IN = label_set(
    "dishwasher, garbage bin, microwave, refrigerator, sink, box, bathtub, container, night stand, dresser, "
    "drawer, oven, toaster oven, washing machine, clothing dryer, clothes dryer, clothing washer"
)
VLA3D_IN_ON = label_set("cabinet")
VLA3D_VERTICAL_STRUCTURES = label_set("wall, door, door way, door frame, garage door")
VLA3D_STRUCTURES = VLA3D_VERTICAL_STRUCTURES | label_set("floor, ceiling")
VLA3D_UNDER = label_set(
    "cabinet, counter, table, desk, stool, shelf, drawer, dresser, bed, bookshelf, tv stand, bench, chest, "
    "piano bench, bar, night stand, coffee table"
)
VLA3D_SUPPORTING = label_set(
    "cabinet, chair, refrigerator, table, desk, shelves, stand, mail shelf, paper rack, sofa, bookshelf, "
    "mailshelf, bed, night stand, dresser, bench, tv stand, coffee table, ottoman, game table, "
    "foosball table, pool table, ping pong table"
)
# language_generation_configs.json exclude_classes: never target nor anchor.
VLA3D_EXCLUDED = label_set("floor, wall, ceiling")

VLA3D_ABOVE = VerticalRule(min_gap=VLA3D_ON_THRES, max_gap=math.inf, min_overlap=VLA3D_VERTICAL_IOM)
# The generator's zero thresholds (t_t <= b_a, t_t <= t_a, b_a < b_t < t_t < t_a) take ROUND_OFF of slack.
VLA3D_HANGING_BELOW = VerticalRule(min_gap=-ROUND_OFF, max_gap=math.inf, min_overlap=VLA3D_VERTICAL_IOM)
VLA3D_BENEATH = BeneathRule(
    top_clearance=-ROUND_OFF, base_tolerance=VLA3D_UNDER_THRES, min_overlap=VLA3D_VERTICAL_IOM
)
VLA3D_ON = OnRule(
    gap=VLA3D_ON_THRES,
    base_clearance=VLA3D_UNDER_THRES,
    xy_margin=None,
    min_cover=VLA3D_VERTICAL_IOM,
    max_area_ratio=1.0,
)
VLA3D_INSIDE = InRule(z_tolerance=ROUND_OFF, every_side_smaller=True)


def _mask(labels: Sequence[str], names: frozenset[str]) -> np.ndarray:
    return np.array([in_classes(lab, names) for lab in labels], dtype=bool)


def _allowed(relation: Relation, labels: Sequence[str]) -> np.ndarray:
    return np.array([anchor_allowed(relation, lab) for lab in labels], dtype=bool)


def _pairs(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(index.size, k=1)
    return index[i], index[j]


def _stack(target: Box, siblings: Box) -> Box:
    """The target's box first, then its siblings': (1 + S, 3)."""
    return Box(np.concatenate([target.lo[None], siblings.lo]), np.concatenate([target.hi[None], siblings.hi]))


def sr3d_context_ok(target: SceneObject, others: Sequence[SceneObject]) -> bool:
    """Whether Sr3D would refer to this target at all: 2..SR3D_MAX_CONTEXT objects of its class."""
    key = class_key(target.label)
    n = 1 + sum(class_key(o.label) == key for o in others)
    return 2 <= n <= SR3D_MAX_CONTEXT


def _sr3d(target: SceneObject, others: Sequence[SceneObject]) -> list[TrueReading]:
    if not others or not sr3d_context_ok(target, others):
        return []
    labels = [o.label for o in others]
    keys = [class_key(lab) for lab in labels]
    counts = Counter(keys)
    ids = [o.id for o in others]
    boxes, tbox = Box.of(others), Box.of(target)
    same = np.array([k == class_key(target.label) for k in keys])
    siblings = boxes.take(same)
    unique = np.array([counts[k] == 1 for k in keys])
    out: list[TrueReading] = []

    proximity = ~same & unique & ~_mask(labels, SR3D_PROXIMITY_EXCLUDED)
    near_idx = np.flatnonzero(proximity & _allowed(Relation.CLOSEST, labels))
    closest, farthest = ordinal_relations(
        tbox, siblings, boxes.take(near_idx), min_gap=SR3D_HORIZONTAL_GAP, min_ratio=0.0, surface=True
    )
    out += [TrueReading(Relation.CLOSEST, (ids[k],)) for k in near_idx[closest].tolist()]
    out += [TrueReading(Relation.FARTHEST, (ids[k],)) for k in near_idx[farthest].tolist()]

    out += _sr3d_vertical(target, tbox, boxes, siblings, labels, keys, counts, same, ids)

    pair_idx = np.flatnonzero(proximity & _allowed(Relation.BETWEEN, labels))
    safe = bool(np.all(centre_distance(tbox, siblings, dims=2) >= SR3D_BETWEEN_SAFE_DISTANCE))
    if pair_idx.size >= 2 and safe:
        first, second = _pairs(pair_idx)
        a1, a2 = boxes.take(first), boxes.take(second)
        t_area = max(float(footprint_area(tbox)), 1e-9)
        t_height = max(float(tbox.size[2]), 1e-9)
        hit = (
            (footprint_iou(a1, a2) < SR3D_ANCHOR_MAX_IOU)
            & (footprint_intersection(tbox, a1) / t_area <= SR3D_BETWEEN_MAX_ANCHOR_COVER)
            & (footprint_intersection(tbox, a2) / t_area <= SR3D_BETWEEN_MAX_ANCHOR_COVER)
            & (height_overlap(tbox, a1) >= SR3D_BETWEEN_MIN_Z_OVERLAP * t_height)
            & (height_overlap(tbox, a2) >= SR3D_BETWEEN_MIN_Z_OVERLAP * t_height)
        )
        hit[hit] = hull_occupancy(tbox, a1.take(hit), a2.take(hit)) >= SR3D_BETWEEN_MIN_OCCUPANCY
        if siblings.lo.shape[0] and hit.any():
            # (S, P) occupancies of the distractors for the pairs the target passes.
            occ = hull_occupancy(siblings.expand(1), a1.take(hit).expand(0), a2.take(hit).expand(0))
            hit[hit] = np.all(occ <= SR3D_BETWEEN_AMBIGUOUS_OCCUPANCY, axis=0)
        out += [
            TrueReading(Relation.BETWEEN, (ids[a], ids[b]))
            for a, b in zip(first[hit].tolist(), second[hit].tolist(), strict=True)
        ]
    return out


def _sr3d_vertical(
    target: SceneObject,
    tbox: Box,
    boxes: Box,
    siblings: Box,
    labels: Sequence[str],
    keys: Sequence[str],
    counts: Counter[str],
    same: np.ndarray,
    ids: Sequence[str],
) -> list[TrueReading]:
    group = _stack(tbox, siblings)  # (1 + S, 3): the target's class, target first
    vols = np.prod(group.size, axis=-1)
    inter = volume_overlap(group.expand(1), group.expand(0))  # (1 + S, 1 + S)
    np.fill_diagonal(inter, 0.0)
    if np.any(inter / np.maximum(vols[:, None], 1e-9) > SR3D_MAX_DISTRACTOR_OVERLAP):
        return []
    anchors = (
        ~same
        & ~_mask(labels, SR3D_VERTICAL_EXCLUDED)
        & np.array([counts[k] <= SR3D_MAX_CONTEXT for k in keys])
    )
    g, b = group.expand(1), boxes.expand(0)  # (1 + S, 1) against (1, N)
    can_support = _allowed(Relation.ON, labels)
    supported_by = is_on(g, b, 0.0, SR3D_SUPPORT) & can_support & (not is_structure(target.label))
    supporting = is_on(b, g, 0.0, SR3D_SUPPORT) & np.array([not is_structure(lab) for lab in labels])
    supporting &= anchor_allowed(Relation.ON, target.label)
    above = is_above(g, b, SR3D_VERTICAL) & _allowed(Relation.ABOVE, labels)
    below = is_below(g, b, False, SR3D_VERTICAL) & _allowed(Relation.BELOW, labels)
    related = (supported_by | supporting | above | below) & anchors  # (1 + S, N)
    pairs_per_class: Counter[str] = Counter()
    for k in np.flatnonzero(related.any(axis=0)).tolist():
        pairs_per_class[keys[k]] += int(related[:, k].sum())
    out = []
    for k in np.flatnonzero(related[0]).tolist():
        if pairs_per_class[keys[k]] != 1:
            continue
        if supported_by[0, k]:
            out.append(TrueReading(Relation.ON, (ids[k],)))
        elif supporting[0, k]:
            continue
        elif above[0, k]:
            out.append(TrueReading(Relation.ABOVE, (ids[k],)))
        else:
            out.append(TrueReading(Relation.BELOW, (ids[k],)))
    return out


def sr3d_next_to(target: SceneObject, anchor: SceneObject, others: Sequence[SceneObject]) -> bool:
    """Sr3D's NEXT_TO phrasing condition for a closest reference: the two within SR3D_NEXT_TO_DISTANCE in
    the floor plane, and no other object (walls and floor aside) with more than SR3D_NEXT_TO_BLOCKING of its
    footprint in the hull of their footprints."""
    tbox, abox = Box.of(target), Box.of(anchor)
    if float(centre_distance(tbox, abox, dims=2)) > SR3D_NEXT_TO_DISTANCE:
        return False
    rest = [o for o in others if o.id != anchor.id and not is_room_shell(o.label)]
    if not rest:
        return True
    return not np.any(hull_occupancy(Box.of(rest), tbox, abox) > SR3D_NEXT_TO_BLOCKING)


def sr3d_in_center(target: SceneObject, first: SceneObject, second: SceneObject) -> bool:
    """Sr3D's IN_CENTER phrasing condition for a between reference: seen from each anchor, the target lies
    within SR3D_IN_CENTER_ANGLE of the direction to the other anchor (floor plane)."""
    t, a, b = (np.asarray(o.center[:2], dtype=float) for o in (target, first, second))

    def angle(origin: np.ndarray, towards: np.ndarray) -> float:
        u, w = towards - origin, t - origin
        norm = float(np.linalg.norm(u) * np.linalg.norm(w))
        return math.acos(max(-1.0, min(1.0, float(u @ w) / norm))) if norm > 0 else math.pi

    return 0.0 < angle(a, b) < SR3D_IN_CENTER_ANGLE and 0.0 < angle(b, a) < SR3D_IN_CENTER_ANGLE


def _vla3d_binary(
    tbox: Box, boxes: Box, labels: Sequence[str], target_label: str, region_volume: float
) -> dict[Relation, np.ndarray]:
    """The VLA-3D binary relations of the box(es) `tbox` ((..., 1, 3) against anchors (1, N, 3) or one
    box against (N, 3)) with a target class label: masks of the anchors' shape."""
    in_on = _mask(labels, VLA3D_IN_ON)
    container = _mask(labels, VLA3D_IN)
    target_structure = in_classes(target_label, VLA3D_STRUCTURES)
    on = (
        is_on(tbox, boxes, 1.0, VLA3D_ON)
        & ~_mask(labels, VLA3D_VERTICAL_STRUCTURES)
        & ~(container & fits_inside(tbox, boxes))
        & (~in_on | top_in_upper_band(tbox, boxes, VLA3D_IN_THRES))
    ) & (not target_structure)
    upper_band = top_in_upper_band(tbox, boxes, VLA3D_IN_THRES)
    inside = is_in(tbox, boxes, VLA3D_INSIDE) & (container | (in_on & ~upper_band))
    hanging = None if in_classes(target_label, VLA3D_SUPPORTING) else VLA3D_HANGING_BELOW
    return {
        Relation.ON: on,
        Relation.IN: inside,
        Relation.ABOVE: is_above(tbox, boxes, VLA3D_ABOVE),
        Relation.BELOW: is_below(tbox, boxes, _mask(labels, VLA3D_UNDER), hanging, VLA3D_BENEATH),
        Relation.NEAR: is_near(tbox, boxes, VLA3D_NEAR_THRES * region_volume, centres=True),
    }


def _vla3d(target: SceneObject, others: Sequence[SceneObject], region_volume: float) -> list[TrueReading]:
    if not others or in_classes(target.label, VLA3D_EXCLUDED):
        return []
    labels = [o.label for o in others]
    ids = [o.id for o in others]
    boxes, tbox = Box.of(others), Box.of(target)
    key = class_key(target.label)
    same = np.array([class_key(lab) == key for lab in labels])
    siblings = boxes.take(same)
    anchors = ~same & ~_mask(labels, VLA3D_EXCLUDED) & np.array([not is_room_shell(lab) for lab in labels])
    out: list[TrueReading] = []
    masks = _vla3d_binary(tbox, boxes, labels, target.label, region_volume)
    rivals = (
        _vla3d_binary(siblings.expand(1), boxes.expand(0), labels, target.label, region_volume)
        if siblings.lo.shape[0]
        else {}
    )
    for relation, mask in masks.items():
        hit = mask & anchors
        if relation in rivals:
            hit &= ~rivals[relation].any(axis=0)
        out += [TrueReading(relation, (ids[k],)) for k in np.flatnonzero(hit).tolist()]

    pair_idx = np.flatnonzero(anchors)
    if pair_idx.size >= 2:
        first, second = _pairs(pair_idx)
        rule = {
            "max_overlap": VLA3D_OVERLAP_THRES,
            "max_asymmetry": VLA3D_SYMMETRY_THRES,
            "max_gap": VLA3D_DISTANCE_THRES,
            "min_cross_overlap": VLA3D_BETWEEN_IOM,
        }
        a1, a2 = boxes.take(first), boxes.take(second)
        # Symmetric in the anchors (reversing them reverses the axis), so one order per pair suffices.
        hit = axis_between(tbox, a1, a2, **rule)
        if siblings.lo.shape[0] and hit.any():
            rival = axis_between(siblings.expand(1), a1.take(hit).expand(0), a2.take(hit).expand(0), **rule)
            hit[hit] = ~rival.any(axis=0)  # rival: (S, P)
        out += [
            TrueReading(Relation.BETWEEN, (ids[a], ids[b]))
            for a, b in zip(first[hit].tolist(), second[hit].tolist(), strict=True)
        ]

    if siblings.lo.shape[0]:
        ord_idx = np.flatnonzero(anchors)
        closest, farthest = ranked_ordinal_relations(
            tbox, siblings, boxes.take(ord_idx), depth=VLA3D_ORDERED_DEPTH, min_scaled_gap=VLA3D_ORDERED_THRES
        )
        out += [TrueReading(Relation.CLOSEST, (ids[k],)) for k in ord_idx[closest].tolist()]
        out += [TrueReading(Relation.FARTHEST, (ids[k],)) for k in ord_idx[farthest].tolist()]
    return out


def groundings(
    convention: Convention,
    target: SceneObject,
    others: Sequence[SceneObject],
    *,
    placements: Mapping[str, Relation] | None = None,
    region_volume: float | None = None,
) -> list[TrueReading]:
    """Every (relation, anchor(s)) reading of the target's place among `others` (the target excluded) that
    the convention makes true.

    `placements` (AI2-THOR's parent receptacles) feed the vlmap convention's on/in; the others compute every
    relation from the boxes. `region_volume` is the volume of the target's region box (VLA-3D's "near");
    by default that of the box around the target and `others`.
    """
    if convention is Convention.VLMAP:
        return true_groundings(target, others, placements)
    if convention is Convention.SR3D:
        return _sr3d(target, others)
    if region_volume is None:
        every = Box.of([target, *others])
        region_volume = float(np.prod(every.hi.max(axis=0) - every.lo.min(axis=0)))
    return _vla3d(target, others, region_volume)


def holds(
    convention: Convention,
    grounding: TrueReading,
    target: SceneObject,
    objects: Sequence[SceneObject],
    region_volume: float | None = None,
) -> bool:
    """Whether the grounding is true for the target among `objects` by the convention's box predicates
    (AI2-THOR placements left out: on/in are checked from the boxes)."""
    return grounding in groundings(convention, target, objects, region_volume=region_volume)
