"""True spatial relations between a target box and the other objects of a scene.

Everything works on axis-aligned boxes (metres, z up), as the training layouts provide them. A `Box` holds
lower and upper corners of shape (..., 3); every predicate broadcasts, so one call tests a target against all
anchors of a scene at once (`anchors.lo` of shape (N, 3) gives an (N,) mask) and the same call on two single
boxes gives a 0-d boolean.

The definitions follow the spirit of the VLA-3D statement generator (vertical relations from heights plus
footprint overlap, "between" from the segment joining two anchors, closest/farthest among the instances of
the target's class) with thresholds chosen for ScanNet's noisy instance boxes; each is written in the
docstring of its predicate and every threshold is a named constant below.

Label policy (which objects may serve as anchors), decided here once:

* floor and ceiling are never anchors: everything is "near"/"above" the floor, and "on the floor" names no
  location beyond the room itself (the region does that);
* walls (and wall-like partitions) are anchors only for "near" ("the bin near the wall", as in VLA-3D); they
  span the whole height of a room, so "above/below/on/between the wall" and "closest to the wall" say nothing;
* doors, windows and other openings may anchor near, above, below, between, closest and farthest
  ("the chair closest to the door", "the radiator below the window"), but nothing rests on or in them;
* "in" needs a container class (cabinet, drawer, fridge, box, bin, sink, ...);
* parts of furniture (drawers, knobs, handles) anchor only "in" and "near": an object on a dresser is above
  its drawers, but nobody says so, and "between the drawer and the drawer" names no place;
* generic labels ("object", "structure") are never anchors: they cannot be named in an utterance;
* an anchor is never of the target's kind ("the chair near the chair", "the book under the books" are not
  how people speak), except that the two anchors of "between" may share a label with each other.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject

# on: the target's bottom may lie this far above the anchor's top (boxes float a little in scans) ...
ON_GAP_TOLERANCE = 0.10
# ... or sink this far into the anchor's box: ScanNet boxes of things on desks start 5-20 cm below its top.
ON_SINK_TOLERANCE = 0.25
# on: the target's footprint centre may overhang the anchor's footprint by this much.
ON_XY_MARGIN = 0.05
# on, internal supports (seats, beds, shelves): the supported bottom is at least this high above the anchor's
# base, which keeps things standing on the floor next to or under the anchor out ...
INTERNAL_SUPPORT_MIN_HEIGHT = 0.15
# ... and at most this fraction of a seat's height: seats lie below backrests and headboards, while a
# keyboard at 0.8 of a chair's height is on the desk the chair is tucked under (shelves reach their top).
SEAT_SURFACE_MAX_FRACTION = 0.7
# in: how far the target's box may poke out of the container's box at the top or bottom.
IN_Z_TOLERANCE = 0.05
# above / hanging below: vertical gap range between the two boxes ("not touching", "within a max height").
VERTICAL_MIN_GAP = 0.15
VERTICAL_MAX_GAP = 1.50
# above / hanging below: footprint intersection over the smaller footprint.
VERTICAL_MIN_OVERLAP = 0.3
# below, under furniture with clearance: the target's top is this far below the anchor's top ...
UNDER_CLEARANCE = 0.10
# ... and its bottom within this of the anchor's bottom (it stands on the same floor).
UNDER_BASE_TOLERANCE = 0.15
# near: surface-to-surface distance between the boxes.
NEAR_MAX_DISTANCE = 0.6
# between: distance between the two anchors' centres in the floor plane.
BETWEEN_MIN_SEPARATION = 0.5
BETWEEN_MAX_SEPARATION = 3.0
# between: distance of the target's centre from the line through the anchors' centres (floor plane).
BETWEEN_MAX_OFFSET = 0.5
# closest / farthest: the runner-up of the target's class must be this much farther (closer) from the anchor,
# in metres and as a fraction of the target's distance, or people could not tell the instances apart.
ORDINAL_MIN_GAP = 0.3
ORDINAL_MIN_RATIO = 0.1


def label_set(text: str) -> frozenset[str]:
    """A label class written as one comma-separated string."""
    return frozenset(name.strip() for name in text.split(","))


FLOOR_CEILING = label_set("floor, floors, ceiling, ceilings")
WALL_LIKE = label_set(
    "wall, walls, closet wall, closet walls, shower wall, shower walls, bathroom stall, partition, "
    "divider, pillar, column, beam, pipe, pipes, stair rail, railing, rail, stairs"
)
OPENINGS = label_set(
    "door, doors, doorframe, door frame, doorway, window, windows, window frame, closet door, "
    "closet doors, bathroom stall door, shower door, shower doors, glass door, sliding door, "
    "garage door, curtain, curtains, blinds, shower curtain, shower glass"
)
GENERIC = frozenset(
    {"object", "objects", "structure", "otherstructure", "otherprop", "otherfurniture", "unknown"}
)
PARTS = label_set("drawer, drawers, stove knob, knob, knobs, handle, handles")
CONTAINERS = label_set(
    "cabinet, cabinets, kitchen cabinet, kitchen cabinets, file cabinet, bathroom cabinet, drawer, "
    "drawers, dresser, nightstand, night stand, refrigerator, fridge, mini fridge, freezer, "
    "microwave, oven, toaster oven, dishwasher, washing machine, clothes dryer, box, boxes, bin, "
    "trash can, trash bin, garbage can, garbage bin, recycling bin, storage bin, storage container, "
    "container, basket, laundry basket, laundry hamper, hamper, bucket, sink, sink basin, bathtub, "
    "bathtub basin, tub, closet, wardrobe, wardrobe closet, safe, crate, bowl, pot, pan, cup, mug, "
    "kettle, coffee machine, bag, suitcase"
)
# Boxes with support surfaces inside them: seats under backrests and headboards, boards of shelves.
SEATS = label_set("chair, office chair, armchair, arm chair, sofa chair, couch, sofa, bed, bench")
SHELVES = label_set(
    "shelf, shelves, bookshelf, bookshelves, bookcase, shelving unit, cart, rack, stand, tv stand"
)
# Furniture with free space underneath: "the box under the table".
CLEARANCE_BELOW = label_set(
    "table, desk, counter, kitchen counter, countertop, kitchen island, bed, chair, office chair, "
    "stool, bench, shelf, tv stand, coffee table, end table, side table, dining table, bar, "
    "piano bench, ottoman, sink"
)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box(es): lower and upper corners, each (..., 3)."""

    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def from_center_size(
        cls, center: Sequence[float] | np.ndarray, size: Sequence[float] | np.ndarray
    ) -> Box:
        c = np.asarray(center, dtype=float)
        half = 0.5 * np.asarray(size, dtype=float)
        return cls(c - half, c + half)

    @classmethod
    def of(cls, objects: SceneObject | Sequence[SceneObject]) -> Box:
        """The bounding box of one object, or the stacked boxes (N, 3) of several."""
        if isinstance(objects, SceneObject):
            return cls(objects.min_corner, objects.max_corner)
        if not objects:
            return cls(np.zeros((0, 3)), np.zeros((0, 3)))
        return cls(np.stack([o.min_corner for o in objects]), np.stack([o.max_corner for o in objects]))

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.lo + self.hi)

    @property
    def size(self) -> np.ndarray:
        return self.hi - self.lo

    def take(self, index: np.ndarray) -> Box:
        """The boxes selected by an index array or mask over the leading axis."""
        return Box(self.lo[index], self.hi[index])


@dataclass(frozen=True)
class Grounding:
    """One true reading of a target's place: it stands in `relation` to the anchor object(s)."""

    relation: Relation
    anchor_ids: tuple[str, ...]


# --- label policy -----------------------------------------------------------------------------------------


def same_kind(a: str, b: str) -> bool:
    """Whether two labels name the same kind of thing, up to case and a plural ending ("book", "books")."""
    x, y = a.strip().lower(), b.strip().lower()
    return x == y or x in (y + "s", y + "es") or y in (x + "s", x + "es")


def _in_class(label: str, names: frozenset[str]) -> bool:
    """Whether the label, or its head noun (last word: "file cabinet" -> "cabinet"), belongs to the class."""
    text = label.strip().lower()
    return text in names or text.rsplit(" ", 1)[-1] in names


def is_structure(label: str) -> bool:
    """Floors, ceilings, walls, openings and generic labels: never a target."""
    return any(_in_class(label, names) for names in (FLOOR_CEILING, WALL_LIKE, OPENINGS, GENERIC))


def is_container(label: str) -> bool:
    return _in_class(label, CONTAINERS)


def internal_support_reach(label: str) -> float:
    """Up to which fraction of its height an anchor may carry things inside its box: 0 for a plain top
    surface, SEAT_SURFACE_MAX_FRACTION for seats, 1 for shelves."""
    if _in_class(label, SHELVES):
        return 1.0
    if _in_class(label, SEATS):
        return SEAT_SURFACE_MAX_FRACTION
    return 0.0


def has_clearance_below(label: str) -> bool:
    return _in_class(label, CLEARANCE_BELOW)


def anchor_allowed(relation: Relation, label: str) -> bool:
    """Whether an object with this label may anchor the relation (the policy in the module docstring)."""
    if _in_class(label, FLOOR_CEILING) or _in_class(label, GENERIC):
        return False
    if _in_class(label, WALL_LIKE):
        return relation is Relation.NEAR
    if _in_class(label, OPENINGS):
        return relation not in (Relation.ON, Relation.IN)
    if _in_class(label, PARTS) and relation not in (Relation.IN, Relation.NEAR):
        return False
    if relation is Relation.IN:
        return is_container(label)
    return True


# --- geometry -----------------------------------------------------------------------------------------------


def footprint_contains(anchor: Box, point_xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Whether the xy point lies in the anchor's footprint grown by `margin` on every side."""
    return np.all(
        (point_xy >= anchor.lo[..., :2] - margin) & (point_xy <= anchor.hi[..., :2] + margin), axis=-1
    )


def footprint_overlap(a: Box, b: Box) -> np.ndarray:
    """Intersection over the smaller footprint, IoM = |F_a ∩ F_b| / min(|F_a|, |F_b|), in [0, 1]."""
    side = np.clip(
        np.minimum(a.hi[..., :2], b.hi[..., :2]) - np.maximum(a.lo[..., :2], b.lo[..., :2]), 0.0, None
    )
    inter = side[..., 0] * side[..., 1]
    area_a = np.prod(a.size[..., :2], axis=-1)
    area_b = np.prod(b.size[..., :2], axis=-1)
    return inter / np.maximum(np.minimum(area_a, area_b), 1e-9)


def surface_distance(a: Box, b: Box) -> np.ndarray:
    """Distance between the boxes' surfaces, d = ||max(0, lo_a - hi_b, lo_b - hi_a)||; 0 where they touch."""
    gap = np.maximum(0.0, np.maximum(a.lo - b.hi, b.lo - a.hi))
    return np.linalg.norm(gap, axis=-1)


def is_on(target: Box, anchor: Box, internal_reach: float | np.ndarray = 0.0) -> np.ndarray:
    """The anchor supports the target.

    Let b = target bottom, t_a = anchor top, z_a = anchor bottom, h_a = t_a - z_a, c = target footprint
    centre. On a plain top surface (`internal_reach` = 0):

        on  <=>  c in footprint(anchor) grown by ON_XY_MARGIN
             and |footprint(anchor)| > |footprint(target)|
             and max(t_a - ON_SINK_TOLERANCE, z_a + h_a / 2) <= b <= t_a + ON_GAP_TOLERANCE
             and target top > t_a          (it sits on the surface, not inside the anchor's box)

    An anchor with support surfaces inside its box (`internal_reach` = r > 0: a seat under a backrest, the
    boards of a shelf) replaces the height conditions by

        z_a + INTERNAL_SUPPORT_MIN_HEIGHT <= b <= z_a + r h_a + ON_GAP_TOLERANCE.
    """
    bottom = target.lo[..., 2]
    base_a = anchor.lo[..., 2]
    top_a = anchor.hi[..., 2]
    reach = np.asarray(internal_reach, dtype=float)
    internal = reach > 0
    lower = np.where(
        internal,
        base_a + INTERNAL_SUPPORT_MIN_HEIGHT,
        np.maximum(top_a - ON_SINK_TOLERANCE, anchor.center[..., 2]),
    )
    upper = np.where(internal, base_a + reach * (top_a - base_a), top_a) + ON_GAP_TOLERANCE
    height_ok = (bottom >= lower) & (bottom <= upper)
    pokes_out = internal | (target.hi[..., 2] > top_a)
    bigger = np.prod(anchor.size[..., :2], axis=-1) > np.prod(target.size[..., :2], axis=-1)
    inside_xy = footprint_contains(anchor, target.center[..., :2], ON_XY_MARGIN)
    return inside_xy & bigger & height_ok & pokes_out


def is_in(target: Box, anchor: Box) -> np.ndarray:
    """The anchor's box encloses the target (the anchor must be a container; see `anchor_allowed`):

    in  <=>  target centre inside the anchor's box
         and z_a - IN_Z_TOLERANCE <= target bottom,  target top <= t_a + IN_Z_TOLERANCE
         and vol(target) < vol(anchor)
    """
    c = target.center
    centre_inside = np.all((c >= anchor.lo) & (c <= anchor.hi), axis=-1)
    z_inside = (target.lo[..., 2] >= anchor.lo[..., 2] - IN_Z_TOLERANCE) & (
        target.hi[..., 2] <= anchor.hi[..., 2] + IN_Z_TOLERANCE
    )
    smaller = np.prod(target.size, axis=-1) < np.prod(anchor.size, axis=-1)
    return centre_inside & z_inside & smaller


def is_above(target: Box, anchor: Box) -> np.ndarray:
    """The target floats over the anchor without touching it:

    above  <=>  VERTICAL_MIN_GAP < target bottom - anchor top <= VERTICAL_MAX_GAP
           and  footprint IoM(target, anchor) >= VERTICAL_MIN_OVERLAP
    """
    gap = target.lo[..., 2] - anchor.hi[..., 2]
    return (
        (gap > VERTICAL_MIN_GAP)
        & (gap <= VERTICAL_MAX_GAP)
        & (footprint_overlap(target, anchor) >= VERTICAL_MIN_OVERLAP)
    )


def is_below(target: Box, anchor: Box, clearance: bool | np.ndarray = False) -> np.ndarray:
    """The target is under the anchor, in one of two ways:

    * hanging anchor (a shelf on the wall, a tv, a window): the target is wholly lower, with
      VERTICAL_MIN_GAP < anchor bottom - target top <= VERTICAL_MAX_GAP
      and footprint IoM >= VERTICAL_MIN_OVERLAP;
    * furniture with clearance (`clearance`: tables, desks, beds, ...): the target stands beneath its top,
      target footprint centre inside the anchor's footprint, target top <= anchor top - UNDER_CLEARANCE and
      target bottom <= anchor bottom + UNDER_BASE_TOLERANCE.
    """
    gap = anchor.lo[..., 2] - target.hi[..., 2]
    hanging = (
        (gap > VERTICAL_MIN_GAP)
        & (gap <= VERTICAL_MAX_GAP)
        & (footprint_overlap(target, anchor) >= VERTICAL_MIN_OVERLAP)
    )
    beneath = (
        np.asarray(clearance, dtype=bool)
        & footprint_contains(anchor, target.center[..., :2])
        & (target.hi[..., 2] <= anchor.hi[..., 2] - UNDER_CLEARANCE)
        & (target.lo[..., 2] <= anchor.lo[..., 2] + UNDER_BASE_TOLERANCE)
    )
    return hanging | beneath


def is_near(target: Box, anchor: Box) -> np.ndarray:
    """Surface-to-surface distance at most NEAR_MAX_DISTANCE. `true_groundings` further drops anchors the
    target is on or in: "near" is the relation people use when it is neither."""
    return surface_distance(target, anchor) <= NEAR_MAX_DISTANCE


def _extent_along(box: Box, direction_xy: np.ndarray) -> np.ndarray:
    """Half length of the box's footprint projected on a unit xy direction: h_x |u_x| + h_y |u_y|."""
    half = 0.5 * box.size[..., :2]
    return np.sum(half * np.abs(direction_xy), axis=-1)


def is_between(target: Box, first: Box, second: Box) -> np.ndarray:
    """The target lies in the gap between two anchors, in the floor plane.

    With p1, p2 the anchors' footprint centres, u = (p2 - p1) / L, L = |p2 - p1|, and c the target's
    footprint centre, s = (c - p1) . u its position along the segment and d its distance from the line:

        between  <=>  BETWEEN_MIN_SEPARATION <= L <= BETWEEN_MAX_SEPARATION
                 and  e1 < s < L - e2        (past both anchors' footprints, e_i = extent of anchor i along u)
                 and  |d| <= BETWEEN_MAX_OFFSET
                 and  the target's height range meets the anchors' joint height range (not hovering over both)
    """
    p1 = first.center[..., :2]
    p2 = second.center[..., :2]
    c = target.center[..., :2]
    delta = p2 - p1
    length = np.linalg.norm(delta, axis=-1)
    u = delta / np.maximum(length, 1e-9)[..., None]
    rel = c - p1
    s = np.sum(rel * u, axis=-1)
    d = rel[..., 0] * u[..., 1] - rel[..., 1] * u[..., 0]
    in_gap = (s > _extent_along(first, u)) & (s < length - _extent_along(second, u))
    z_lo = np.minimum(first.lo[..., 2], second.lo[..., 2])
    z_hi = np.maximum(first.hi[..., 2], second.hi[..., 2])
    z_ok = (target.lo[..., 2] <= z_hi) & (target.hi[..., 2] >= z_lo)
    separated = (length >= BETWEEN_MIN_SEPARATION) & (length <= BETWEEN_MAX_SEPARATION)
    return separated & in_gap & (np.abs(d) <= BETWEEN_MAX_OFFSET) & z_ok


def ordinal_relations(target: Box, siblings: Box, anchors: Box) -> tuple[np.ndarray, np.ndarray]:
    """Whether the target is the closest / farthest instance of its class from each anchor (VLA-3D semantics:
    "the chair closest to the door"). With d_t the centre distance from the anchor to the target and d_s those
    to its same-class siblings (at least one is needed):

        closest   <=>  min d_s - d_t >= max(ORDINAL_MIN_GAP, ORDINAL_MIN_RATIO * d_t)
        farthest  <=>  d_t - max d_s >= max(ORDINAL_MIN_GAP, ORDINAL_MIN_RATIO * d_t)

    Returns two (N,) masks over the N anchors; both all-false without siblings.
    """
    n = anchors.lo.shape[0]
    if siblings.lo.shape[0] == 0:
        return np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    a = anchors.center  # (N, 3)
    d_t = np.linalg.norm(a - target.center, axis=-1)  # (N,)
    d_s = np.linalg.norm(a[:, None, :] - siblings.center[None, :, :], axis=-1)  # (N, S)
    margin = np.maximum(ORDINAL_MIN_GAP, ORDINAL_MIN_RATIO * d_t)
    closest = d_s.min(axis=1) - d_t >= margin
    farthest = d_t - d_s.max(axis=1) >= margin
    return closest, farthest


# --- all relations of one target ----------------------------------------------------------------------------


def true_groundings(
    target: SceneObject,
    others: Sequence[SceneObject],
    placements: Mapping[str, Relation] | None = None,
) -> list[Grounding]:
    """Every true (relation, anchor(s)) reading of the target's place among `others` (the target excluded).

    `placements` maps anchor ids to ON/IN where the true support is known (AI2-THOR's parent receptacles):
    then on/in come from it alone, and the box predicates for on/in only keep those anchors out of "near".
    Closest/farthest need at least one other object with the target's label in `others`.
    """
    if not others:
        return []
    boxes = Box.of(others)
    tbox = Box.of(target)
    ids = [o.id for o in others]
    labels = [o.label for o in others]
    label = target.label.lower()
    other_class = np.array([not same_kind(lab, label) for lab in labels])

    def allowed(relation: Relation) -> np.ndarray:
        return other_class & np.array([anchor_allowed(relation, lab) for lab in labels])

    reach = np.array([internal_support_reach(lab) for lab in labels])
    clearance = np.array([has_clearance_below(lab) for lab in labels])
    on = is_on(tbox, boxes, reach) & allowed(Relation.ON)
    inside = is_in(tbox, boxes) & allowed(Relation.IN) & ~on
    if placements is not None:
        known = np.array([i in placements for i in ids])
        supported = on | inside | known
        on = np.array([placements.get(i) is Relation.ON for i in ids]) & other_class
        inside = np.array([placements.get(i) is Relation.IN for i in ids]) & other_class
    else:
        supported = on | inside
    masks = {
        Relation.ON: on,
        Relation.IN: inside,
        Relation.ABOVE: is_above(tbox, boxes) & allowed(Relation.ABOVE),
        Relation.BELOW: is_below(tbox, boxes, clearance) & allowed(Relation.BELOW),
        Relation.NEAR: is_near(tbox, boxes) & allowed(Relation.NEAR) & ~supported,
    }
    out = [Grounding(rel, (ids[i],)) for rel, mask in masks.items() for i in np.flatnonzero(mask).tolist()]

    pair_ok = allowed(Relation.BETWEEN)
    idx = np.flatnonzero(pair_ok)
    if idx.size >= 2:
        i, j = np.triu_indices(idx.size, k=1)
        first, second = idx[i], idx[j]
        hit = is_between(tbox, boxes.take(first), boxes.take(second))
        out.extend(
            Grounding(Relation.BETWEEN, (ids[a], ids[b]))
            for a, b in zip(first[hit].tolist(), second[hit].tolist(), strict=True)
        )

    siblings = [o for o in others if o.label.lower() == label]
    if siblings:
        ord_idx = np.flatnonzero(allowed(Relation.CLOSEST))
        closest, farthest = ordinal_relations(tbox, Box.of(siblings), boxes.take(ord_idx))
        out.extend(Grounding(Relation.CLOSEST, (ids[k],)) for k in ord_idx[closest].tolist())
        out.extend(Grounding(Relation.FARTHEST, (ids[k],)) for k in ord_idx[farthest].tolist())
    return out


def holds(grounding: Grounding, target: SceneObject, graph_objects: Iterable[SceneObject]) -> bool:
    """Whether a box-computed grounding is geometrically true for the target among `graph_objects`.

    Re-derives the relation with the predicates above (used to check built cases and rigid motions); on/in
    are checked geometrically, so AI2-THOR placements that the boxes do not show come out False.
    """
    objects = list(graph_objects)
    found = true_groundings(target, objects)
    return grounding in found
