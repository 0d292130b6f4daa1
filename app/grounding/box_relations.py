"""True spatial relations between a target box and the other objects of a scene: the one set of box
predicates of the project, and its one set of thresholds (the proposer's context counts,
`app.grounding.referent_features.related_mask`, test coarser predicates with these same constants).

Everything works on axis-aligned boxes (metres, z up), as the training layouts provide them. A `Box` holds
lower and upper corners of shape (..., 3); every predicate broadcasts, so one call tests a target against all
anchors of a scene at once (`anchors.lo` of shape (N, 3) gives an (N,) mask) and the same call on two single
boxes gives a 0-d boolean.

The project's own definitions ("vlmap") follow the spirit of the VLA-3D statement generator (vertical
relations from heights plus footprint overlap, "between" from the segment joining two anchors,
closest/farthest among the instances of the target's class) with thresholds chosen for ScanNet's noisy
instance boxes; each is written in the docstring of its predicate and every threshold is a named constant
below. Predicates that other datasets define differently take their thresholds as a rule object
(`OnRule`, `VerticalRule`, `BeneathRule`, `InRule`) or keyword arguments whose defaults are ours;
`app.data.conventions` fills them with Sr3D's and VLA-3D's values, and holds the predicates that only those
conventions use (`hull_occupancy`, `axis_between`, `ranked_ordinal_relations`) here too, so that there is one
set of box relations.

Label policy of the vlmap convention (which objects may serve as anchors), decided here once; a label is of a
class below by `app.vocabulary.in_classes` (any spelling, synonyms, the head noun: raw labels and lemmatised
ones get one answer):

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
* an anchor is never of the target's class (`app.vocabulary.same_class`: "the chair near the chair", "the book
  under the books" are not how people speak), except that the two anchors of "between" may share a label.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject, object_corners
from app.vocabulary import in_classes, same_class

# on: the target's bottom may lie this far above the anchor's top (boxes float a little in scans) ...
ON_GAP_TOLERANCE = 0.10
# ... or sink this far into the anchor's box: ScanNet boxes of things on desks start 5-20 cm below its top ...
ON_SINK_TOLERANCE = 0.25
# ... but stay above this fraction of the anchor's height (a thin anchor's box is not sunk through).
ON_MIN_BOTTOM_FRACTION = 0.5
# on: the target's footprint centre may overhang the anchor's footprint by this much.
ON_XY_MARGIN = 0.05
# on, internal supports (seats, beds, shelves): the supported bottom is at least this high above the anchor's
# base, which keeps things standing on the floor next to or under the anchor out (the same height as
# UNDER_BASE_TOLERANCE, so that "on the seat" and "under the chair" do not share a bottom height; the
# proposer's context counts use it too) ...
INTERNAL_SUPPORT_MIN_HEIGHT = 0.15
# ... and at most this fraction of a seat's height: seats lie below backrests and headboards, while a
# keyboard at 0.8 of a chair's height is on the desk the chair is tucked under (shelves reach their top).
SEAT_SURFACE_MAX_FRACTION = 0.7
# in: how far the target's box may poke out of the container's box at the top or bottom.
IN_Z_TOLERANCE = 0.05
# above / hanging below: vertical gap range between the two boxes ("not touching", "within a max height").
# The gap starts beyond ON_GAP_TOLERANCE: a target between the two neither rests on the anchor nor clearly
# floats over it, and no reading names it. One threshold for the builder and the proposer's context counts.
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
# Slack (metres) of comparisons whose threshold is zero, so that the float round-off of moved boxes cannot
# decide a tie: AI2-THOR's boxes touch exactly (a plate resting on the bottom of its cabinet's box).
ROUND_OFF = 1e-6
# hull_occupancy: grid points per side of the target footprint on which the occupied area is measured
# (400 cells: the measured fraction is within ~2.5% of the exact area fraction).
HULL_GRID = 20


def label_set(text: str) -> frozenset[str]:
    """A label class written as one comma-separated string of names. Labels are matched to it by
    `app.vocabulary.in_classes` (class keys, head nouns): plurals and synonyms need no entry of their own."""
    return frozenset(name.strip() for name in text.split(","))


FLOORS = label_set("floor")
CEILINGS = label_set("ceiling")
FLOOR_CEILING = FLOORS | CEILINGS
WALLS = label_set("wall, closet wall, shower wall")
WALL_LIKE = WALLS | label_set(
    "bathroom stall, partition, divider, pillar, column, beam, pipe, stair rail, railing, rail, stairs"
)
OPENINGS = label_set(
    "door, doorframe, doorway, window, window frame, closet door, bathroom stall door, shower door, "
    "glass door, sliding door, garage door, curtain, blinds, shower curtain, shower glass"
)
# Fixed to a wall or over a basin: their boxes have tops, but nothing is left on them.
WALL_MOUNTED = label_set(
    "faucet, shower head, light switch, mirror, picture, painting, poster, clock, whiteboard, blackboard, "
    "bulletin board, towel bar, soap dispenser, paper towel dispenser, vent, ceiling light"
)
GENERIC = label_set("object, structure, otherstructure, otherprop, otherfurniture, unknown")
PARTS = label_set("drawer, stove knob, knob, handle")
CONTAINERS = label_set(
    "cabinet, kitchen cabinet, file cabinet, bathroom cabinet, drawer, dresser, nightstand, refrigerator, "
    "mini fridge, freezer, microwave, oven, toaster oven, dishwasher, washing machine, clothes dryer, box, "
    "bin, trash can, recycling bin, storage bin, storage container, container, basket, laundry hamper, "
    "bucket, sink, sink basin, bathtub, bathtub basin, closet, wardrobe, wardrobe closet, safe, crate, "
    "bowl, pot, pan, cup, mug, kettle, coffee machine, bag, suitcase"
)
# Boxes with support surfaces inside them: seats under backrests and headboards, boards of shelves.
SEATS = label_set("chair, office chair, armchair, couch, bed, bench")
SHELVES = label_set("shelf, bookshelf, shelving unit, cart, rack, stand, tv stand")
# Furniture with free space underneath: "the box under the table".
CLEARANCE_BELOW = label_set(
    "table, desk, counter, kitchen island, bed, chair, office chair, stool, bench, shelf, tv stand, "
    "coffee table, end table, dining table, bar, piano bench, ottoman, sink"
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
        return cls(*object_corners(objects))

    @property
    def center(self) -> np.ndarray:
        center: np.ndarray = 0.5 * (self.lo + self.hi)
        return center

    @property
    def size(self) -> np.ndarray:
        size: np.ndarray = self.hi - self.lo
        return size

    def take(self, index: np.ndarray) -> Box:
        """The boxes selected by an index array or mask over the leading axis."""
        return Box(self.lo[index], self.hi[index])

    def expand(self, axis: int) -> Box:
        """The boxes with a new axis of length 1 at `axis` (to broadcast one set against another)."""
        return Box(np.expand_dims(self.lo, axis), np.expand_dims(self.hi, axis))


@dataclass(frozen=True)
class TrueReading:
    """One true reading of a target's place: it stands in `relation` to the anchor object(s)."""

    relation: Relation
    anchor_ids: tuple[str, ...]


@dataclass(frozen=True)
class OnRule:
    """Thresholds of `is_on` (the defaults are the vlmap convention's)."""

    gap: float = ON_GAP_TOLERANCE
    sink: float = ON_SINK_TOLERANCE
    min_bottom_fraction: float = ON_MIN_BOTTOM_FRACTION
    # Footprint test: the target's footprint centre inside the anchor's footprint grown by `xy_margin`, or,
    # with `xy_margin` None, the covered share of the target's footprint |F_t ∩ F_a| / |F_t| >= `min_cover`.
    xy_margin: float | None = ON_XY_MARGIN
    min_cover: float = 0.0
    # |F_t| / |F_a| < max_area_ratio (1: the anchor's footprint is the larger).
    max_area_ratio: float = 1.0
    # The target's top must rise above the anchor's top (it sits on the surface, not inside the box).
    must_poke_out: bool = True
    # Internal supports: the supported bottom at least this far above the anchor's base.
    base_clearance: float = INTERNAL_SUPPORT_MIN_HEIGHT


@dataclass(frozen=True)
class VerticalRule:
    """Thresholds of `is_above` and of the hanging case of `is_below`: the vertical gap g between the boxes
    and the footprint intersection over the smaller footprint (IoM)."""

    min_gap: float = VERTICAL_MIN_GAP
    max_gap: float = VERTICAL_MAX_GAP
    min_overlap: float = VERTICAL_MIN_OVERLAP


@dataclass(frozen=True)
class BeneathRule:
    """Thresholds of the furniture-with-clearance case of `is_below`."""

    top_clearance: float = UNDER_CLEARANCE
    base_tolerance: float = UNDER_BASE_TOLERANCE
    # Footprint test: the target's footprint centre inside the anchor's footprint, or, when set, a footprint
    # IoM of at least this.
    min_overlap: float | None = None


@dataclass(frozen=True)
class InRule:
    """Thresholds of `is_in`."""

    z_tolerance: float = IN_Z_TOLERANCE
    # Smaller than the container on every side (else: smaller in volume).
    every_side_smaller: bool = False


ON_RULE = OnRule()
VERTICAL_RULE = VerticalRule()
BENEATH_RULE = BeneathRule()
IN_RULE = InRule()


# --- label policy -----------------------------------------------------------------------------------------


def is_floor(label: str) -> bool:
    return in_classes(label, FLOORS)


def is_ceiling(label: str) -> bool:
    return in_classes(label, CEILINGS)


def is_structure(label: str) -> bool:
    """Floors, ceilings, walls, openings and generic labels: never a small movable target."""
    return any(in_classes(label, names) for names in (FLOOR_CEILING, WALL_LIKE, OPENINGS, GENERIC))


def is_room_shell(label: str) -> bool:
    """Floors, ceilings, walls and generic labels: never a target of any size (doors and windows may be)."""
    return any(in_classes(label, names) for names in (FLOOR_CEILING, WALLS, GENERIC))


def is_wall(label: str) -> bool:
    return in_classes(label, WALLS)


def is_container(label: str) -> bool:
    return in_classes(label, CONTAINERS)


@lru_cache(maxsize=1 << 14)
def internal_support_reach(label: str) -> float:
    """Up to which fraction of its height an anchor may carry things inside its box: 0 for a plain top
    surface, SEAT_SURFACE_MAX_FRACTION for seats, 1 for shelves."""
    if in_classes(label, SHELVES):
        return 1.0
    if in_classes(label, SEATS):
        return SEAT_SURFACE_MAX_FRACTION
    return 0.0


@lru_cache(maxsize=1 << 14)
def has_clearance_below(label: str) -> bool:
    return in_classes(label, CLEARANCE_BELOW)


@lru_cache(maxsize=1 << 16)
def anchor_allowed(relation: Relation, label: str) -> bool:
    """Whether an object with this label may anchor the relation (the policy in the module docstring)."""
    if in_classes(label, FLOOR_CEILING) or in_classes(label, GENERIC):
        return False
    if in_classes(label, WALL_LIKE):
        return relation is Relation.NEAR
    if in_classes(label, OPENINGS):
        return relation not in (Relation.ON, Relation.IN)
    if in_classes(label, PARTS) and relation not in (Relation.IN, Relation.NEAR):
        return False
    if relation is Relation.IN:
        return is_container(label)
    return True


# --- geometry -----------------------------------------------------------------------------------------------


def footprint_contains(anchor: Box, point_xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Whether the xy point lies in the anchor's footprint grown by `margin` on every side."""
    inside: np.ndarray = np.all(
        (point_xy >= anchor.lo[..., :2] - margin) & (point_xy <= anchor.hi[..., :2] + margin), axis=-1
    )
    return inside


def footprint_intersection(a: Box, b: Box) -> np.ndarray:
    """Area of the intersection of the two footprints, |F_a ∩ F_b|."""
    side = np.clip(
        np.minimum(a.hi[..., :2], b.hi[..., :2]) - np.maximum(a.lo[..., :2], b.lo[..., :2]), 0.0, None
    )
    area: np.ndarray = side[..., 0] * side[..., 1]
    return area


def footprint_area(a: Box) -> np.ndarray:
    area: np.ndarray = np.prod(a.size[..., :2], axis=-1)
    return area


def footprint_overlap(a: Box, b: Box) -> np.ndarray:
    """Intersection over the smaller footprint, IoM = |F_a ∩ F_b| / min(|F_a|, |F_b|), in [0, 1]."""
    smaller = np.minimum(footprint_area(a), footprint_area(b))
    overlap: np.ndarray = footprint_intersection(a, b) / np.maximum(smaller, 1e-9)
    return overlap


def footprint_iou(a: Box, b: Box) -> np.ndarray:
    """Intersection over union of the two footprints."""
    inter = footprint_intersection(a, b)
    iou: np.ndarray = inter / np.maximum(footprint_area(a) + footprint_area(b) - inter, 1e-9)
    return iou


def height_overlap(a: Box, b: Box) -> np.ndarray:
    """Length of the intersection of the two boxes' height ranges (negative: the gap between them)."""
    overlap: np.ndarray = np.minimum(a.hi[..., 2], b.hi[..., 2]) - np.maximum(a.lo[..., 2], b.lo[..., 2])
    return overlap


def volume_overlap(a: Box, b: Box) -> np.ndarray:
    """Volume of the intersection of the two boxes."""
    side = np.clip(np.minimum(a.hi, b.hi) - np.maximum(a.lo, b.lo), 0.0, None)
    volume: np.ndarray = np.prod(side, axis=-1)
    return volume


def surface_distance(a: Box, b: Box) -> np.ndarray:
    """Distance between the boxes' surfaces, d = ||max(0, lo_a - hi_b, lo_b - hi_a)||; 0 where they touch."""
    gap = np.maximum(0.0, np.maximum(a.lo - b.hi, b.lo - a.hi))
    distance: np.ndarray = np.linalg.norm(gap, axis=-1)
    return distance


def centre_distance(a: Box, b: Box, dims: int = 3) -> np.ndarray:
    """Distance between the boxes' centres, over the first `dims` axes (2: in the floor plane)."""
    distance: np.ndarray = np.linalg.norm(a.center[..., :dims] - b.center[..., :dims], axis=-1)
    return distance


def top_in_upper_band(target: Box, anchor: Box, fraction: float) -> np.ndarray:
    """Whether the target's top lies in the upper `fraction` of the anchor's height:
    t_t > t_a - fraction h_a."""
    return target.hi[..., 2] > anchor.hi[..., 2] - fraction * anchor.size[..., 2]


def fits_inside(target: Box, anchor: Box) -> np.ndarray:
    """Whether the target is smaller than the anchor along every axis."""
    fits: np.ndarray = np.all(target.size < anchor.size, axis=-1)
    return fits


def is_on(
    target: Box, anchor: Box, internal_reach: float | np.ndarray = 0.0, rule: OnRule = ON_RULE
) -> np.ndarray:
    """The anchor supports the target.

    Let b = target bottom, t_a = anchor top, z_a = anchor bottom, h_a = t_a - z_a, c = target footprint
    centre. On a plain top surface (`internal_reach` = 0), with the vlmap thresholds:

        on  <=>  c in footprint(anchor) grown by ON_XY_MARGIN
             and |footprint(target)| < |footprint(anchor)|
             and max(t_a - ON_SINK_TOLERANCE, z_a + ON_MIN_BOTTOM_FRACTION h_a) <= b <= t_a + ON_GAP_TOLERANCE
             and target top > t_a          (it sits on the surface, not inside the anchor's box)

    An anchor with support surfaces inside its box (`internal_reach` = r > 0: a seat under a backrest, the
    boards of a shelf) replaces the height conditions by

        z_a + INTERNAL_SUPPORT_MIN_HEIGHT <= b <= z_a + r h_a + ON_GAP_TOLERANCE.

    `rule` replaces each threshold (`OnRule`): the footprint test may instead ask a covered share of the
    target's footprint, the area condition a ratio |F_t| / |F_a| < max_area_ratio, and the poke-out
    condition may be dropped.
    """
    bottom = target.lo[..., 2]
    base_a = anchor.lo[..., 2]
    top_a = anchor.hi[..., 2]
    reach = np.asarray(internal_reach, dtype=float)
    internal = reach > 0
    lower = np.where(
        internal,
        base_a + rule.base_clearance,
        np.maximum(top_a - rule.sink, base_a + rule.min_bottom_fraction * (top_a - base_a)),
    )
    upper = np.where(internal, base_a + reach * (top_a - base_a), top_a) + rule.gap
    height_ok = (bottom >= lower) & (bottom <= upper)
    pokes_out = internal | (target.hi[..., 2] > top_a) if rule.must_poke_out else True
    area_ok = footprint_area(target) < rule.max_area_ratio * footprint_area(anchor)
    if rule.xy_margin is not None:
        inside_xy = footprint_contains(anchor, target.center[..., :2], rule.xy_margin)
    else:
        cover = footprint_intersection(target, anchor) / np.maximum(footprint_area(target), 1e-9)
        inside_xy = cover >= rule.min_cover
    return inside_xy & area_ok & height_ok & pokes_out


def is_in(target: Box, anchor: Box, rule: InRule = IN_RULE) -> np.ndarray:
    """The anchor's box encloses the target (the anchor must be a container; see `anchor_allowed`):

    in  <=>  target centre inside the anchor's box
         and z_a - IN_Z_TOLERANCE <= target bottom,  target top <= t_a + IN_Z_TOLERANCE
         and vol(target) < vol(anchor)     (`rule.every_side_smaller`: smaller along every axis instead)
    """
    c = target.center
    centre_inside = np.all((c >= anchor.lo) & (c <= anchor.hi), axis=-1)
    z_inside = (target.lo[..., 2] >= anchor.lo[..., 2] - rule.z_tolerance) & (
        target.hi[..., 2] <= anchor.hi[..., 2] + rule.z_tolerance
    )
    if rule.every_side_smaller:
        smaller = fits_inside(target, anchor)
    else:
        smaller = np.prod(target.size, axis=-1) < np.prod(anchor.size, axis=-1)
    inside: np.ndarray = centre_inside & z_inside & smaller
    return inside


def _hangs(gap: np.ndarray, target: Box, anchor: Box, rule: VerticalRule) -> np.ndarray:
    return (
        (gap > rule.min_gap) & (gap <= rule.max_gap) & (footprint_overlap(target, anchor) >= rule.min_overlap)
    )


def is_above(target: Box, anchor: Box, rule: VerticalRule = VERTICAL_RULE) -> np.ndarray:
    """The target floats over the anchor without touching it:

    above  <=>  VERTICAL_MIN_GAP < target bottom - anchor top <= VERTICAL_MAX_GAP
           and  footprint IoM(target, anchor) >= VERTICAL_MIN_OVERLAP
    """
    return _hangs(target.lo[..., 2] - anchor.hi[..., 2], target, anchor, rule)


def is_below(
    target: Box,
    anchor: Box,
    clearance: bool | np.ndarray = False,
    rule: VerticalRule | None = VERTICAL_RULE,
    beneath: BeneathRule = BENEATH_RULE,
) -> np.ndarray:
    """The target is under the anchor, in one of two ways:

    * hanging anchor (a shelf on the wall, a tv, a window): the target is wholly lower, with
      VERTICAL_MIN_GAP < anchor bottom - target top <= VERTICAL_MAX_GAP
      and footprint IoM >= VERTICAL_MIN_OVERLAP (`rule`; None: no hanging case);
    * furniture with clearance (`clearance`: tables, desks, beds, ...): the target stands beneath its top,
      target footprint centre inside the anchor's footprint (or IoM >= `beneath.min_overlap`), target top
      <= anchor top - UNDER_CLEARANCE and target bottom <= anchor bottom + UNDER_BASE_TOLERANCE.
    """
    if rule is None:
        hanging = np.zeros(np.broadcast_shapes(target.lo.shape, anchor.lo.shape)[:-1], dtype=bool)
    else:
        hanging = _hangs(anchor.lo[..., 2] - target.hi[..., 2], target, anchor, rule)
    if beneath.min_overlap is None:
        under_xy = footprint_contains(anchor, target.center[..., :2])
    else:
        under_xy = footprint_overlap(target, anchor) >= beneath.min_overlap
    under = (
        np.asarray(clearance, dtype=bool)
        & under_xy
        & (target.hi[..., 2] <= anchor.hi[..., 2] - beneath.top_clearance)
        & (target.lo[..., 2] <= anchor.lo[..., 2] + beneath.base_tolerance)
    )
    below: np.ndarray = hanging | under
    return below


def is_near(
    target: Box, anchor: Box, max_distance: float | np.ndarray = NEAR_MAX_DISTANCE, *, centres: bool = False
) -> np.ndarray:
    """Surface-to-surface distance at most NEAR_MAX_DISTANCE (`centres`: the distance between the boxes'
    centres, below `max_distance`). `true_groundings` further drops anchors the target is on or in: "near"
    is the relation people use when it is neither."""
    if centres:
        return centre_distance(target, anchor) < max_distance
    return surface_distance(target, anchor) <= max_distance


def _extent_along(box: Box, direction_xy: np.ndarray) -> np.ndarray:
    """Half length of the box's footprint projected on a unit xy direction: h_x |u_x| + h_y |u_y|."""
    half = 0.5 * box.size[..., :2]
    extent: np.ndarray = np.sum(half * np.abs(direction_xy), axis=-1)
    return extent


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
    between: np.ndarray = separated & in_gap & (np.abs(d) <= BETWEEN_MAX_OFFSET) & z_ok
    return between


def hull_occupancy(target: Box, first: Box, second: Box, grid: int = HULL_GRID) -> np.ndarray:
    """The share of the target's footprint inside the convex hull of the two anchors' footprints,
    |F_t ∩ hull(F_1 ∪ F_2)| / |F_t|, measured on a grid x grid lattice of cell centres of F_t.

    The hull of two convex sets is the union of the segments between them, so a point p lies in it iff some
    lambda in [0, 1] puts it in the box lambda F_1 + (1 - lambda) F_2 (corners lambda lo_1 + (1 - lambda) lo_2
    and lambda hi_1 + (1 - lambda) hi_2): per axis two linear inequalities in lambda, whose intervals must
    meet.
    """
    steps = (np.arange(grid) + 0.5) / grid  # (G,)
    gx, gy = np.meshgrid(steps, steps, indexing="ij")
    frac = np.stack([gx.ravel(), gy.ravel()], axis=-1)  # (G*G, 2)
    lo_t = target.lo[..., None, :2]
    points = lo_t + frac * (target.hi[..., None, :2] - lo_t)  # (..., G*G, 2)
    lo1, hi1 = first.lo[..., None, :2], first.hi[..., None, :2]
    lo2, hi2 = second.lo[..., None, :2], second.hi[..., None, :2]
    lower = np.zeros(np.broadcast_shapes(points.shape, lo1.shape, lo2.shape)[:-1])
    upper = np.ones_like(lower)
    # lo_2 + lambda (lo_1 - lo_2) <= p  and  hi_2 + lambda (hi_1 - hi_2) >= p, per axis.
    for slope, rhs, sign in ((lo1 - lo2, points - lo2, 1.0), (hi1 - hi2, points - hi2, -1.0)):
        a, b = sign * slope, sign * rhs  # a lambda <= b
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = b / a
        upper = np.minimum(upper, np.where(a > 0, bound, np.inf).min(axis=-1))
        lower = np.maximum(lower, np.where(a < 0, bound, -np.inf).max(axis=-1))
        infeasible = np.any((a == 0) & (b < 0), axis=-1)
        upper = np.where(infeasible, -np.inf, upper)
    occupancy: np.ndarray = np.mean(lower <= upper, axis=-1)
    return occupancy


def axis_between(
    target: Box,
    first: Box,
    second: Box,
    *,
    max_overlap: float,
    max_asymmetry: float,
    max_gap: float,
    min_cross_overlap: float,
) -> np.ndarray:
    """The target lies between two anchors along the axis joining their centres (in the floor plane).

    With u the unit xy vector from the first anchor's centre to the second's and v ⟂ u, project every box on
    u (interval [l, h] of length w) and s_i its centre's position. With o_2 = (h_t - l_2) / min(w_t, w_2) and
    o_1 = (h_1 - l_t) / min(w_t, w_1) (how far the target's interval runs into each anchor's, negative: the
    gap between them in units of the smaller length):

        between  <=>  s_1 < s_t < s_2
                 and  o_1 < max_overlap,  o_2 < max_overlap,  |o_1 - o_2| < max_asymmetry
                 and  -o_1 < max_gap,  -o_2 < max_gap
                 and  IoM(cross-section of the target, of each anchor) > min_cross_overlap
                      (cross-sections: the boxes projected on the (v, z) plane)
    """
    delta = second.center[..., :2] - first.center[..., :2]
    u = delta / np.maximum(np.linalg.norm(delta, axis=-1), 1e-9)[..., None]
    v = np.stack([-u[..., 1], u[..., 0]], axis=-1)

    def interval(box: Box, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mid = np.sum(box.center[..., :2] * direction, axis=-1)
        half = _extent_along(box, direction)
        return mid - half, mid + half

    (l1, h1), (lt, ht), (l2, h2) = (interval(b, u) for b in (first, target, second))
    s1, st, s2 = 0.5 * (l1 + h1), 0.5 * (lt + ht), 0.5 * (l2 + h2)
    wt = ht - lt
    o2 = (ht - l2) / np.maximum(np.minimum(wt, h2 - l2), 1e-9)
    o1 = (h1 - lt) / np.maximum(np.minimum(wt, h1 - l1), 1e-9)
    along = (
        (s1 < st)
        & (st < s2)
        & (o1 < max_overlap)
        & (o2 < max_overlap)
        & (np.abs(o1 - o2) < max_asymmetry)
        & (-o1 < max_gap)
        & (-o2 < max_gap)
    )

    def cross_iom(anchor: Box) -> np.ndarray:
        (la, ha), (lb, hb) = interval(target, v), interval(anchor, v)
        width = np.clip(np.minimum(ha, hb) - np.maximum(la, lb), 0.0, None)
        height = np.clip(height_overlap(target, anchor), 0.0, None)
        area_t = (ha - la) * target.size[..., 2]
        area_a = (hb - lb) * anchor.size[..., 2]
        iom: np.ndarray = width * height / np.maximum(np.minimum(area_t, area_a), 1e-9)
        return iom

    between: np.ndarray = (
        along & (cross_iom(first) > min_cross_overlap) & (cross_iom(second) > min_cross_overlap)
    )
    return between


def _distances(anchors: Box, objects: Box, surface: bool) -> np.ndarray:
    """(N, M) distances between N anchors and M objects: surface-to-surface, or between centres."""
    a, o = anchors.expand(1), objects.expand(0)
    return surface_distance(a, o) if surface else centre_distance(a, o)


def ordinal_relations(
    target: Box,
    siblings: Box,
    anchors: Box,
    *,
    min_gap: float = ORDINAL_MIN_GAP,
    min_ratio: float = ORDINAL_MIN_RATIO,
    surface: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Whether the target is the closest / farthest instance of its class from each anchor (VLA-3D semantics:
    "the chair closest to the door"). With d_t the centre distance (`surface`: surface-to-surface distance)
    from the anchor to the target and d_s those to its same-class siblings (at least one is needed):

        closest   <=>  min d_s - d_t >= max(ORDINAL_MIN_GAP, ORDINAL_MIN_RATIO * d_t)
        farthest  <=>  d_t - max d_s >= max(ORDINAL_MIN_GAP, ORDINAL_MIN_RATIO * d_t)

    Returns two (N,) masks over the N anchors; both all-false without siblings.
    """
    n = anchors.lo.shape[0]
    if siblings.lo.shape[0] == 0:
        return np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    d_t = _distances(anchors, Box(target.lo[None], target.hi[None]), surface)[:, 0]  # (N,)
    d_s = _distances(anchors, siblings, surface)  # (N, S)
    margin = np.maximum(min_gap, min_ratio * d_t)
    closest = d_s.min(axis=1) - d_t >= margin
    farthest = d_t - d_s.max(axis=1) >= margin
    return closest, farthest


def ranked_ordinal_relations(
    target: Box, siblings: Box, anchors: Box, *, depth: int, min_scaled_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Closest / farthest by a ranking that must be clear over its first `depth` places.

    For each anchor, sort the target's class (target and siblings, at least two objects) by centre distance
    d_(1) <= d_(2) <= ... and let L be the mean length of the first k = min(depth, n) objects' boxes projected
    on the direction to the anchor. Then

        closest   <=>  the target is first  and  (d_(j+1) - d_(j)) L > min_scaled_gap for all j < k
        farthest  <=>  the target is last   and  the same over the last k places.

    Returns two (N,) masks over the N anchors; both all-false without siblings.
    """
    n = anchors.lo.shape[0]
    if siblings.lo.shape[0] == 0:
        return np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    group = Box(
        np.concatenate([target.lo[None], siblings.lo]), np.concatenate([target.hi[None], siblings.hi])
    )
    d = _distances(anchors, group, surface=False)  # (N, M), column 0 is the target
    direction = anchors.center[:, None, :] - group.center[None, :, :]  # (N, M, 3)
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-9)
    lengths = np.sum(group.size[None] * np.abs(direction), axis=-1)  # (N, M)
    order = np.argsort(d, axis=1, kind="stable")  # (N, M)
    d_sorted = np.take_along_axis(d, order, axis=1)
    l_sorted = np.take_along_axis(lengths, order, axis=1)
    k = min(depth, group.lo.shape[0])

    def clear(dist: np.ndarray, length: np.ndarray) -> np.ndarray:
        is_clear: np.ndarray = np.all(
            np.abs(np.diff(dist, axis=1)) * length.mean(axis=1, keepdims=True) > min_scaled_gap, axis=1
        )
        return is_clear

    closest = (order[:, 0] == 0) & clear(d_sorted[:, :k], l_sorted[:, :k])
    farthest = (order[:, -1] == 0) & clear(d_sorted[:, ::-1][:, :k], l_sorted[:, ::-1][:, :k])
    return closest, farthest


# --- all relations of one target (vlmap convention) ---------------------------------------------------------


def true_groundings(
    target: SceneObject,
    others: Sequence[SceneObject],
    placements: Mapping[str, Relation] | None = None,
) -> list[TrueReading]:
    """Every true (relation, anchor(s)) reading of the target's place among `others` (the target excluded),
    by the vlmap convention.

    `placements` maps anchor ids to ON/IN where the true support is known (AI2-THOR's parent receptacles):
    then on/in come from it alone, and the box predicates for on/in only keep those anchors out of "near".
    Closest/farthest need at least one other object of the target's class in `others`.
    """
    if not others:
        return []
    boxes = Box.of(others)
    tbox = Box.of(target)
    ids = [o.id for o in others]
    labels = [o.label for o in others]
    same = np.array([same_class(lab, target.label) for lab in labels])
    other_class = ~same

    def allowed(relation: Relation) -> np.ndarray:
        mask: np.ndarray = other_class & np.array([anchor_allowed(relation, lab) for lab in labels])
        return mask

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
    out = [TrueReading(rel, (ids[i],)) for rel, mask in masks.items() for i in np.flatnonzero(mask).tolist()]

    idx = np.flatnonzero(allowed(Relation.BETWEEN))
    if idx.size >= 2:
        i, j = np.triu_indices(idx.size, k=1)
        first, second = idx[i], idx[j]
        hit = is_between(tbox, boxes.take(first), boxes.take(second))
        out.extend(
            TrueReading(Relation.BETWEEN, (ids[a], ids[b]))
            for a, b in zip(first[hit].tolist(), second[hit].tolist(), strict=True)
        )

    if same.any():
        ord_idx = np.flatnonzero(allowed(Relation.CLOSEST))
        closest, farthest = ordinal_relations(tbox, boxes.take(same), boxes.take(ord_idx))
        out.extend(TrueReading(Relation.CLOSEST, (ids[k],)) for k in ord_idx[closest].tolist())
        out.extend(TrueReading(Relation.FARTHEST, (ids[k],)) for k in ord_idx[farthest].tolist())
    return out


def holds(grounding: TrueReading, target: SceneObject, graph_objects: Iterable[SceneObject]) -> bool:
    """Whether a box-computed grounding is geometrically true for the target among `graph_objects`.

    Re-derives the relation with the predicates above (used to check built cases and rigid motions); on/in
    are checked geometrically, so AI2-THOR placements that the boxes do not show come out False.
    """
    objects = list(graph_objects)
    found = true_groundings(target, objects)
    return grounding in found
