"""Plausibility features of referent hypotheses: how well a candidate anchor fits the utterance and the map.

Everything works on the axis-aligned bounding boxes of the scene's objects (metres, z up) as arrays: a
`SceneBoxes` holds lower and upper corners (N, 3). A hypothesis is a row of anchor indices, (H, 1) for a
one-anchor relation and (H, 2) for "between"; `hypothesis_features` returns one row of `FEATURES` per
hypothesis, (H, F). The proposer scores a hypothesis as a linear function of these (weights fitted per
relation on the built grounding cases) and turns the scores into weights with a softmax.

The features, per anchor (averaged over the two anchors of "between" unless said otherwise):

- label_cosine, label_exact, label_head: how the anchor's label matches the anchor phrase (MiniLM cosine;
  same lemmas or synonyms; same head noun), computed by the proposer and passed in;
- target_kind: the anchor is of the target's kind ("the chair near the chair" is rarely meant);
- log_footprint, top_height, bottom_height: the anchor's size and where it sits above the floor;
- log_volume_ratio, log_footprint_ratio: anchor against target size (can it hold / carry the target?);
- height_offset, abs_height_offset, top_gap, under_clearance: where the target usually is against the
  anchor, vertically: its centre height minus the anchor's, the gap between its bottom and the anchor's top
  (small for "on"), and the anchor's bottom over the target's top (positive for "below"); the target's
  box (size and centre height above the floor) is its siblings' median, else the fitted table's;
- siblings_related, others_related: log(1 + how many other objects of the target's kind, and of any other
  kind, stand in the relation to this anchor): a table with chairs around it, a bed with pillows on it, a
  shelf that already carries things; for "between" the objects in the gap of the pair;
- siblings_near: log(1 + objects of the target's kind within `SIBLING_RADIUS` of the anchor's surface);
- context_max, context_mean: MiniLM cosine between the target phrase and the labels of the other objects
  within `SIBLING_RADIUS` of the anchor (not of the target's kind): a mouse is meant near the wall with the
  desk and keyboard, not the bare one; zero when nothing is around or the utterance names no target;
- log_nearest_sibling, log_farthest_sibling, log_reach: floor-plane distances from the anchor to the
  nearest and farthest object of the target's kind and to the farthest corner of the map ("closest to" /
  "farthest from" need room for the target to beat its siblings); zero when the target has no siblings;
- log_separation, pair_too_close, pair_too_far, pair_same_label: the two "between" anchors' floor-plane
  distance (zero for one-anchor relations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.grounding.box_relations import (
    BETWEEN_MAX_OFFSET,
    BETWEEN_MAX_SEPARATION,
    BETWEEN_MIN_SEPARATION,
    INTERNAL_SUPPORT_MIN_HEIGHT,
    NEAR_MAX_DISTANCE,
    ON_GAP_TOLERANCE,
    ON_SINK_TOLERANCE,
    UNDER_BASE_TOLERANCE,
    UNDER_CLEARANCE,
    VERTICAL_MAX_GAP,
    VERTICAL_MIN_GAP,
    Box,
    footprint_contains,
    surface_distance,
)
from app.grounding.parsing import COLOR_WORDS, MATERIAL_WORDS, SHAPE_WORDS, SIZE_WORDS
from app.grounding.relations import Relation
from app.scene_graph.model import SceneObject, object_corners

FEATURES: tuple[str, ...] = (
    "label_cosine",
    "label_exact",
    "label_head",
    "target_kind",
    "log_footprint",
    "top_height",
    "bottom_height",
    "log_volume_ratio",
    "log_footprint_ratio",
    "height_offset",
    "abs_height_offset",
    "top_gap",
    "under_clearance",
    "siblings_related",
    "others_related",
    "siblings_near",
    "context_max",
    "context_mean",
    "log_nearest_sibling",
    "log_farthest_sibling",
    "log_reach",
    "log_separation",
    "pair_too_close",
    "pair_too_far",
    "pair_same_label",
)
N_FEATURES = len(FEATURES)
_COLUMN = {name: j for j, name in enumerate(FEATURES)}

# The context counts test coarse relation predicates (`related_mask`, `between_mask`: they describe the
# anchor, not the target, so no label policy and no footprint overlap), with the one set of thresholds of
# the box relations (`app.grounding.box_relations`).
SIBLING_RADIUS = 1.0  # metres: objects this close to the anchor's surface are its surroundings
# "between": the gap is the middle of the segment joining the anchors' centres, this fraction off each end.
BETWEEN_END_FRACTION = 0.1
MIN_SIZE = 0.02  # metres: floor for box sides in logarithms
DISTANCE_RANGE = (0.1, 30.0)  # metres: clip range of the distances in logarithms
HEIGHT_CLIP = 3.0  # metres: vertical gaps beyond this say nothing more


@dataclass(frozen=True)
class SceneBoxes:
    """The scene's objects as axis-aligned boxes: corners (N, 3) and the floor height (lowest bottom)."""

    lo: np.ndarray
    hi: np.ndarray
    floor: float
    map_lo: np.ndarray  # (2,) floor-plane corners of the map
    map_hi: np.ndarray

    @classmethod
    def of(cls, objects: list[SceneObject]) -> SceneBoxes:
        if not objects:
            msg = "a scene without objects has no boxes"
            raise ValueError(msg)
        lo, hi = object_corners(objects)  # (N, 3) each
        return cls(lo, hi, float(lo[:, 2].min()), lo[:, :2].min(axis=0), hi[:, :2].max(axis=0))

    @property
    def size(self) -> np.ndarray:
        size: np.ndarray = np.maximum(self.hi - self.lo, MIN_SIZE)  # (N, 3)
        return size

    @property
    def center(self) -> np.ndarray:
        center: np.ndarray = 0.5 * (self.lo + self.hi)  # (N, 3)
        return center


def surface_distances(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> np.ndarray:
    """`app.grounding.box_relations.surface_distance` of every pair: (A, 3), (B, 3) corners -> (A, B)."""
    return surface_distance(Box(lo_a, hi_a).expand(1), Box(lo_b, hi_b).expand(0))


def related_mask(relation: Relation, boxes: SceneBoxes, anchors: np.ndarray) -> np.ndarray:
    """(A, N): object n stands in `relation` to anchor `anchors[a]` (never to itself).

    With the thresholds of `app.grounding.box_relations`: on: footprint centre over the anchor, bottom at its
    top (within ON_SINK_TOLERANCE below, ON_GAP_TOLERANCE above) or on an internal support (at least
    INTERNAL_SUPPORT_MIN_HEIGHT over the anchor's base, under its top: any anchor may be a shelf); in: centre
    inside the box and smaller; above: centre over the footprint, bottom VERTICAL_MIN_GAP to VERTICAL_MAX_GAP
    over the top; below: centre under the footprint, top UNDER_CLEARANCE under the anchor's top and bottom
    within UNDER_BASE_TOLERANCE of its base or wholly under it; near, closest, farthest: surface distance
    <= NEAR_MAX_DISTANCE.
    """
    lo_a, hi_a = boxes.lo[anchors], boxes.hi[anchors]  # (A, 3)
    center = boxes.center  # (N, 3)
    anchor = Box(lo_a, hi_a).expand(1)  # (A, 1, 3)
    over = footprint_contains(anchor, center[None, :, :2])  # (A, N): footprint centre over the anchor's
    bottom, top = boxes.lo[None, :, 2], boxes.hi[None, :, 2]  # (1, N)
    a_bottom, a_top = lo_a[:, None, 2], hi_a[:, None, 2]  # (A, 1)
    mask: np.ndarray  # (A, N)
    if relation is Relation.ON:
        on_top = (bottom >= a_top - ON_SINK_TOLERANCE) & (bottom <= a_top + ON_GAP_TOLERANCE)
        inside = (bottom >= a_bottom + INTERNAL_SUPPORT_MIN_HEIGHT) & (bottom < a_top)
        mask = over & (on_top | inside)
    elif relation is Relation.IN:
        volume = np.prod(boxes.size, axis=1)  # (N,)
        enclosed = np.all((center[None] >= lo_a[:, None]) & (center[None] <= hi_a[:, None]), axis=-1)
        mask = enclosed & (volume[None] < volume[anchors][:, None])
    elif relation is Relation.ABOVE:
        mask = over & (bottom > a_top + VERTICAL_MIN_GAP) & (bottom <= a_top + VERTICAL_MAX_GAP)
    elif relation is Relation.BELOW:
        on_floor = (bottom <= a_bottom + UNDER_BASE_TOLERANCE) | (top <= a_bottom)
        mask = over & (top <= a_top - UNDER_CLEARANCE) & on_floor
    else:
        mask = surface_distances(lo_a, hi_a, boxes.lo, boxes.hi) <= NEAR_MAX_DISTANCE
    mask[np.arange(len(anchors)), anchors] = False
    return mask


def between_mask(boxes: SceneBoxes, pairs: np.ndarray) -> np.ndarray:
    """(P, N): object n lies in the gap of pair p: floor-plane centre within BETWEEN_MAX_OFFSET of the
    segment joining the anchors' centres, projecting onto its middle (BETWEEN_END_FRACTION off each end)."""
    c = boxes.center[:, :2]  # (N, 2)
    a, b = c[pairs[:, 0]], c[pairs[:, 1]]  # (P, 2)
    ab = b - a
    length2 = np.maximum(np.sum(ab * ab, axis=1), 1e-9)  # (P,)
    t = np.einsum("pnd,pd->pn", c[None] - a[:, None], ab) / length2[:, None]  # (P, N)
    closest = a[:, None] + t[..., None] * ab[:, None]  # (P, N, 2)
    offset = np.linalg.norm(c[None] - closest, axis=-1)  # (P, N)
    middle = (t > BETWEEN_END_FRACTION) & (t < 1.0 - BETWEEN_END_FRACTION)
    mask: np.ndarray = middle & (offset <= BETWEEN_MAX_OFFSET)
    rows = np.arange(len(pairs))
    mask[rows, pairs[:, 0]] = False
    mask[rows, pairs[:, 1]] = False
    return mask


def _log_distance(d: np.ndarray) -> np.ndarray:
    log_distance: np.ndarray = np.log(np.clip(d, *DISTANCE_RANGE))
    return log_distance


def anchor_features(
    relation: Relation,
    boxes: SceneBoxes,
    anchors: np.ndarray,
    siblings: np.ndarray,
    target_box: np.ndarray,
    target_cosine: np.ndarray | None = None,
) -> np.ndarray:
    """Size, context and ordinal features of single anchors, (A, F) with the label and pair columns zero.

    `siblings` is a boolean mask (N,) of the objects of the target's kind; `target_box` (4,) the target's
    likely size (dx, dy, dz) and centre height above the floor, metres;
    `target_cosine` (N,) the cosine between the target phrase and each object's label (None: no target).
    """
    out = np.zeros((len(anchors), N_FEATURES))
    size = boxes.size[anchors]  # (A, 3)
    footprint = size[:, 0] * size[:, 1]
    target = np.maximum(np.asarray(target_box[:3], dtype=np.float64), MIN_SIZE)
    target_z = boxes.floor + float(target_box[3])
    out[:, _COLUMN["log_footprint"]] = np.log(footprint)
    out[:, _COLUMN["top_height"]] = boxes.hi[anchors, 2] - boxes.floor
    out[:, _COLUMN["bottom_height"]] = boxes.lo[anchors, 2] - boxes.floor
    out[:, _COLUMN["log_volume_ratio"]] = np.log(np.prod(size, axis=1) / np.prod(target))
    out[:, _COLUMN["log_footprint_ratio"]] = np.log(footprint / (target[0] * target[1]))
    offset = target_z - boxes.center[anchors, 2]
    out[:, _COLUMN["height_offset"]] = offset
    out[:, _COLUMN["abs_height_offset"]] = np.abs(offset)
    out[:, _COLUMN["top_gap"]] = np.minimum(
        np.abs(target_z - 0.5 * target[2] - boxes.hi[anchors, 2]), HEIGHT_CLIP
    )
    out[:, _COLUMN["under_clearance"]] = np.clip(
        boxes.lo[anchors, 2] - (target_z + 0.5 * target[2]), -HEIGHT_CLIP, HEIGHT_CLIP
    )

    related = related_mask(relation, boxes, anchors)  # (A, N)
    out[:, _COLUMN["siblings_related"]] = np.log1p(np.sum(related & siblings[None], axis=1))
    out[:, _COLUMN["others_related"]] = np.log1p(np.sum(related & ~siblings[None], axis=1))

    corners = np.array(
        [[x, y] for x in (boxes.map_lo[0], boxes.map_hi[0]) for y in (boxes.map_lo[1], boxes.map_hi[1])]
    )  # (4, 2)
    center = boxes.center[anchors, :2]  # (A, 2)
    reach = np.linalg.norm(center[:, None] - corners[None], axis=-1).max(axis=1)
    out[:, _COLUMN["log_reach"]] = _log_distance(reach)

    if target_cosine is not None:
        around = surface_distances(boxes.lo[anchors], boxes.hi[anchors], boxes.lo, boxes.hi) <= SIBLING_RADIUS
        around[np.arange(len(anchors)), anchors] = False
        around &= ~siblings[None]  # (A, N)
        count = around.sum(axis=1)
        cosines = np.where(around, target_cosine[None], -np.inf)
        has = count > 0
        out[has, _COLUMN["context_max"]] = cosines[has].max(axis=1)
        out[has, _COLUMN["context_mean"]] = (
            np.where(around, target_cosine[None], 0.0).sum(axis=1) / np.maximum(count, 1)
        )[has]

    sibling_ids = np.flatnonzero(siblings)
    if len(sibling_ids):
        near = surface_distances(
            boxes.lo[anchors], boxes.hi[anchors], boxes.lo[sibling_ids], boxes.hi[sibling_ids]
        )
        itself = anchors[:, None] == sibling_ids[None]  # (A, S): an anchor of the target's kind
        out[:, _COLUMN["siblings_near"]] = np.log1p(np.sum((near <= SIBLING_RADIUS) & ~itself, axis=1))
        planar = np.linalg.norm(center[:, None] - boxes.center[sibling_ids, :2][None], axis=-1)  # (A, S)
        if np.any(~itself):
            nearest = np.where(itself, np.inf, planar).min(axis=1)
            farthest = np.where(itself, -np.inf, planar).max(axis=1)
            has = np.isfinite(nearest)
            out[has, _COLUMN["log_nearest_sibling"]] = _log_distance(nearest[has])
            out[has, _COLUMN["log_farthest_sibling"]] = _log_distance(farthest[has])
    return out


def hypothesis_features(
    relation: Relation,
    boxes: SceneBoxes,
    groups: np.ndarray,
    label_features: np.ndarray,
    siblings: np.ndarray,
    target_box: np.ndarray,
    same_label: np.ndarray | None = None,
    target_cosine: np.ndarray | None = None,
) -> np.ndarray:
    """(H, F) features of hypotheses `groups` (H, k) of object indices, k = 1, or 2 for "between".

    `label_features` (H, k, 3) holds label_cosine, label_exact and label_head of each anchor against the
    phrase that named it; `same_label` (H,) marks "between" pairs whose anchors share a label; `target_cosine`
    as in `anchor_features`.
    """
    groups = np.asarray(groups, dtype=np.int64)
    unique, inverse = np.unique(groups, return_inverse=True)
    per_anchor = anchor_features(relation, boxes, unique, siblings, target_box, target_cosine)  # (U, F)
    per_anchor[:, _COLUMN["target_kind"]] = siblings[unique]
    stacked = per_anchor[inverse.reshape(groups.shape)]  # (H, k, F)
    stacked[:, :, :3] = label_features
    out: np.ndarray = stacked.mean(axis=1)
    out[:, _COLUMN["target_kind"]] = stacked[:, :, _COLUMN["target_kind"]].max(axis=1)
    if groups.shape[1] == 2:
        in_gap = between_mask(boxes, groups)  # (H, N)
        out[:, _COLUMN["siblings_related"]] = np.log1p(np.sum(in_gap & siblings[None], axis=1))
        out[:, _COLUMN["others_related"]] = np.log1p(np.sum(in_gap & ~siblings[None], axis=1))
        c = boxes.center[:, :2]
        separation = np.linalg.norm(c[groups[:, 0]] - c[groups[:, 1]], axis=1)
        out[:, _COLUMN["log_separation"]] = _log_distance(separation)
        out[:, _COLUMN["pair_too_close"]] = separation < BETWEEN_MIN_SEPARATION
        out[:, _COLUMN["pair_too_far"]] = separation > BETWEEN_MAX_SEPARATION
        if same_label is not None:
            out[:, _COLUMN["pair_same_label"]] = same_label
    return out


# --- attributes ---------------------------------------------------------------------------------------------

# Attribute values that name the same thing, folded onto one word.
_ATTRIBUTE_SYNONYMS = {"gray": "grey", "navy": "blue", "wood": "wooden", "metallic": "metal"}
_KINDS = (("color", COLOR_WORDS), ("size", SIZE_WORDS), ("material", MATERIAL_WORDS), ("shape", SHAPE_WORDS))
# Relative sizes: the word, and which box measure it ranks (+1 prefers large, -1 small).
_SIZE_RANKS: dict[str, tuple[str, float]] = {
    "small": ("volume", -1.0),
    "little": ("volume", -1.0),
    "tiny": ("volume", -1.0),
    "big": ("volume", 1.0),
    "large": ("volume", 1.0),
    "huge": ("volume", 1.0),
    "tall": ("height", 1.0),
    "high": ("height", 1.0),
    "short": ("height", -1.0),
    "low": ("height", -1.0),
    "long": ("length", 1.0),
    "wide": ("length", 1.0),
    "narrow": ("length", -1.0),
}
# SceneObject.attributes keys whose values describe the object (VLA-3D "colors" hold {"name": ...} dicts).
DESCRIPTIVE_KEYS = frozenset(
    {"color", "colour", "colors", "colours", "color_labels", "size", "material", "shape", "texture"}
)


def fold_attribute(word: str) -> str:
    return _ATTRIBUTE_SYNONYMS.get(word, word)


def object_attribute_words(obj: SceneObject) -> frozenset[str]:
    """Lower-case words of the object's descriptive attributes ({"color": "white"} -> {"white"})."""
    words: set[str] = set()

    def collect(value: object) -> None:
        if isinstance(value, str):
            words.update(fold_attribute(w) for w in value.lower().replace("_", " ").split())
        elif isinstance(value, dict):
            collect(value.get("name"))
        elif isinstance(value, list | tuple):
            for item in value:
                collect(item)

    for key, value in obj.attributes.items():
        if key.lower() in DESCRIPTIVE_KEYS:
            collect(value)
    return frozenset(words)


def attribute_kind(word: str) -> str | None:
    """ "color", "size", "material" or "shape" for a known attribute word, else None."""
    for kind, vocabulary in _KINDS:
        if word in vocabulary:
            return kind
    return None


def attribute_scores(
    words: tuple[str, ...],
    candidates: list[SceneObject],
    sizes: np.ndarray,
    vocabulary: frozenset[str],
) -> np.ndarray:
    """Agreement of each candidate with the attribute words of its anchor phrase, in [-1, 1], (C,).

    A word the candidate's attributes carry scores +1; a word of a kind that the candidate describes
    otherwise -1 (it is "red" where "white" was asked); 0 when it says nothing of that kind. A size word that
    no object carries (`vocabulary`: every attribute word of the scene) ranks the candidates by their box
    `sizes` (C, 3) instead: +1 for the largest ("big") down to -1 for the smallest. Words are averaged.
    """
    if not words or not candidates:
        return np.zeros(len(candidates))
    carried = [object_attribute_words(o) for o in candidates]
    carried_kinds = [{attribute_kind(w) for w in c} for c in carried]
    scores = np.zeros((len(words), len(candidates)))
    for i, raw in enumerate(words):
        word, kind = fold_attribute(raw), attribute_kind(raw)
        if word in vocabulary:
            scores[i] = [
                1.0 if word in c else (-1.0 if kind is not None and kind in k else 0.0)
                for c, k in zip(carried, carried_kinds, strict=True)
            ]
        elif raw in _SIZE_RANKS and len(candidates) > 1:
            measure, sign = _SIZE_RANKS[raw]
            if measure == "volume":
                value = np.prod(sizes, axis=1)
            elif measure == "height":
                value = sizes[:, 2]
            else:
                value = sizes[:, :2].max(axis=1)
            if np.ptp(value) > 1e-6:
                rank = np.argsort(np.argsort(value))  # 0 for the smallest
                scores[i] = sign * (2.0 * rank / (len(candidates) - 1) - 1.0)
    mean_scores: np.ndarray = scores.mean(axis=0)
    return mean_scores
