"""LSM inputs: (SceneGraph, hypothesis, target name) -> padded, masked tensors in a canonical local frame.

A `Sample` holds one hypothesis's raw inputs (its text, boxes, roles, relation, region frame); `PackedSamples`
stacks many of them with their text embeddings and slices batches (`LSMBatch`) out of them, computing the
geometry features on the fly. The text encoder is frozen, so embeddings are looked up, never trained:
`EmbeddingCache` keeps them on disk during training and the grounder keeps them in an LRU.

**What the model reads of the language** is the hypothesis, not the utterance: the target's name, the
relation and the anchors' labels. Everything else a person said (which table, "you know, the one I always
use") is the proposer's business; here it could only move the prediction without saying anything about
position. The checkpoint's `text_input` (`app.lsm.model.TEXT_INPUTS`) says how the hypothesis becomes one
embedding e:

- "hypothesis": e = E("the mug on the table") (`hypothesis_text`), one MiniLM pass per new hypothesis;
- "composed": e = normalize(E("mug") + E("on the table")) (`relation_text`): the target's name and the
  relation-anchor phrase are embedded apart. The service pins every vocabulary noun's embedding and a map's
  phrases repeat across utterances, so an utterance about a target never asked for costs no MiniLM pass.

**The local frame.** Every sample is expressed relative to its anchors, so that the prediction moves with
the scene (invariance up to the same rigid motion):

- origin o = the mean of the anchors' centres (world, float64); every input is a difference from it, so no
  absolute coordinate ever reaches float32 or the network;
- yaw phi: the scene's dominant yaw (area-weighted circular mean of the objects' yaws modulo 90 degrees,
  zero for axis-aligned maps), plus the quarter turn that points the centroid of the objects' centres, seen
  from o, along +x (within 45 degrees). Both are rotation-covariant, so turning the whole scene turns the
  frame with it; boxes are re-measured as the axis-aligned boxes of their residual yaw in that frame.

A region hypothesis (no anchor objects: "the table is in the kitchen", or in the whole map) takes the
region's box (the objects' bounding box for the map) as a pseudo-object anchor labelled with the region's
name, or "room".

The anchor region frame (s, t) is where the model's output lives (mu_local = s * tanh(.) + t):

    t = 0 (the anchors' mean centre is the origin),
    s = max(max(high - t, t - low) + (m_xy, m_xy, m_z), s_min)     (per axis, metres)

with [low, high] the anchors' joint axis-aligned box in the local frame, so t +- s holds every anchor plus the
margin. The margin is relation-independent: "near" targets and "between" targets stay well inside, and
m_z = 1.5 m reaches objects hanging up to 1.5 m above or below the anchor. s_min keeps tiny anchors from
shrinking the frame (and the covariance, whose floor is 0.05 s) to nothing. "closest" and "farthest" pick
one of several same-class objects anywhere in the map, so for them (with `ordinal_scene_frame`) s is widened
per axis until t +- s holds the whole scene's bounding box.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from app.errors import NotFound
from app.grounding.box_relations import internal_support_reach
from app.grounding.relations import Relation
from app.lsm.model import RELATION_INDEX, ROLE_ANCHOR, ROLE_OTHER, LSMBatch, LSMConfig
from app.scene_graph.model import SceneGraph, aabb_extents

Embed = Callable[[Sequence[str]], np.ndarray]
ORDINAL_RELATIONS = (Relation.CLOSEST, Relation.FARTHEST)
#: The pseudo-anchor's label for the whole map (a region without a name).
ROOM_LABEL = "room"
#: How `hypothesis_text` says each relation.
RELATION_WORDS: dict[Relation, str] = {
    Relation.ON: "on",
    Relation.IN: "in",
    Relation.NEAR: "near",
    Relation.BETWEEN: "between",
    Relation.ABOVE: "above",
    Relation.BELOW: "below",
    Relation.CLOSEST: "closest to",
    Relation.FARTHEST: "farthest from",
}
_CAMEL_BOUNDARY = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")
_QUARTER = 0.5 * math.pi


@lru_cache(maxsize=4096)  # labels repeat across every request on the same maps
def label_text(label: str) -> str:
    """The phrase a label is embedded as: "DiningTable" -> "dining table", "trash_can" -> "trash can"."""
    words = _CAMEL_BOUNDARY.sub(" ", label).replace("_", " ").replace("-", " ")
    return " ".join(words.lower().split())


def target_text(target: str) -> str:
    """The phrase a target's name is embedded as ("object" for none)."""
    return label_text(target) or "object"


def relation_text(relation: Relation, anchor_labels: Sequence[str]) -> str:
    """The relation and the anchors: "on the table", "between the sofa and the tv stand"."""
    anchors = " and the ".join(label_text(a) for a in anchor_labels) or ROOM_LABEL
    return f"{RELATION_WORDS[Relation(relation)]} the {anchors}"


def hypothesis_text(target: str, relation: Relation, anchor_labels: Sequence[str]) -> str:
    """The whole hypothesis: "the mug on the table", "the lamp between the sofa and the tv stand"."""
    return f"the {target_text(target)} {relation_text(relation, anchor_labels)}"


@dataclass(frozen=True)
class Sample:
    """One hypothesis in its scene, in its local frame: the kept objects (anchors first) and the region."""

    text: str  # hypothesis_text, or relation_text when `target_text` is set ("composed")
    labels: tuple[str, ...]  # n embedding texts
    centers: np.ndarray  # (n, 3) metres, local frame
    sizes: np.ndarray  # (n, 3) axis-aligned extents in the local frame, metres
    roles: np.ndarray  # (n,) ROLE_ANCHOR / ROLE_OTHER
    relation: int  # RELATION_INDEX
    region_shift: np.ndarray  # (3,) t, local frame
    region_scale: np.ndarray  # (3,) s
    anchor_low: np.ndarray  # (3,) corners of the anchors' joint box, local frame
    anchor_high: np.ndarray  # (3,)
    plain_top: bool  # one anchor object with a plain top surface (things rest on it, not inside it)
    floor_z: float  # local frame
    scene_low: np.ndarray  # (3,) corners of the scene's bounding box, local frame
    scene_high: np.ndarray  # (3,)
    origin: np.ndarray  # (3,) float64: the local frame's origin in the world
    yaw: float  # the local frame's rotation about z: world = R(yaw) local + origin
    target: np.ndarray | None = None  # (3,) local frame
    target_text: str | None = None  # "composed": embedded apart from `text`, the two summed

    def to_world(self, mean: np.ndarray, covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A local-frame mean (3,) and covariances (..., 3, 3) in the world frame (`to_world`)."""
        means, world = to_world([self], mean[None], np.asarray(covariances)[None])
        return means[0], world[0]


def to_world(
    samples: Sequence[Sample], means: np.ndarray, covariances: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Local-frame means (K, 3) and covariances (K, ..., 3, 3) of K samples in the world frame:
    R_k mu_k + o_k and R_k Sigma R_k^T, with R_k = R(yaw_k) and o_k each sample's frame."""
    rotations = np.stack([rotation_z(s.yaw) for s in samples])  # (K, 3, 3)
    origins = np.stack([s.origin for s in samples])  # (K, 3)
    world_means = np.einsum("kij,kj->ki", rotations, means) + origins
    turn = rotations.reshape(len(samples), *[1] * (covariances.ndim - 3), 3, 3)  # (K, 1..., 3, 3)
    return world_means, turn @ covariances @ np.swapaxes(turn, -1, -2)


def rotation_z(yaw: float) -> np.ndarray:
    """R(yaw) about +z, (3, 3)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SceneArrays:
    """A scene graph as arrays, computed once per scene and shared by all of its hypotheses (world frame)."""

    ids: tuple[str, ...]
    rows: Mapping[str, int]  # object id -> its row in the arrays
    labels: tuple[str, ...]  # embedding texts (label_text)
    centers: np.ndarray  # (M, 3)
    dims: np.ndarray  # (M, 3) the boxes' own sides (before yaw)
    yaws: np.ndarray  # (M,)
    regions: Mapping[str, tuple[np.ndarray, np.ndarray, str]]  # id -> (centre, size, embedding text)
    map_box: tuple[
        np.ndarray, np.ndarray
    ]  # (centre, sides) of the objects' bounding box, turned by dominant_yaw
    floor_z: float  # 10th percentile of object bottoms: most furniture stands on the floor
    dominant_yaw: float  # in [-pi/4, pi/4): the scene's yaw modulo a quarter turn
    centroid: np.ndarray  # (3,) mean of the objects' centres
    _turned_boxes: dict[float, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, compare=False, repr=False
    )

    def turned_box(self, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """Corners (low, high) of the box around every object's and region's box in the frame turned by `yaw`
        about the world origin (points R(yaw)^T p); the box in a local frame with origin o is this minus
        R(yaw)^T o. A scene's frame yaws are its dominant yaw plus quarter turns, so a few boxes, computed
        once, serve all of its hypotheses."""
        cached = self._turned_boxes.get(yaw)
        if cached is None:
            turn = rotation_z(yaw)
            centers, half = self.centers @ turn, 0.5 * aabb_extents(self.dims, self.yaws - yaw)  # (M, 3)
            low, high = (centers - half).min(axis=0), (centers + half).max(axis=0)
            if self.regions:
                region_centers = np.stack([c for c, _, _ in self.regions.values()]) @ turn
                region_half = 0.5 * aabb_extents(
                    np.stack([size for _, size, _ in self.regions.values()]), np.full(len(self.regions), -yaw)
                )
                low = np.minimum(low, (region_centers - region_half).min(axis=0))
                high = np.maximum(high, (region_centers + region_half).max(axis=0))
            cached = self._turned_boxes[yaw] = (low, high)
        return cached

    @classmethod
    def of(cls, scene_graph: SceneGraph) -> SceneArrays:
        objects = scene_graph.objects
        if not objects:
            msg = "the scene graph has no objects to ground in"
            raise NotFound(msg)
        centers = np.array([o.center for o in objects], dtype=np.float64).reshape(-1, 3)
        dims = np.array([o.size for o in objects], dtype=np.float64).reshape(-1, 3)
        yaws = np.array([o.yaw for o in objects], dtype=np.float64)
        extents = aabb_extents(dims, yaws)  # (M, 3)
        # Area-weighted circular mean of 4 yaw: quarter turns of a box look alike.
        area = dims[:, 0] * dims[:, 1]
        sin4, cos4 = float(area @ np.sin(4.0 * yaws)), float(area @ np.cos(4.0 * yaws))
        dominant = 0.25 * math.atan2(sin4, cos4) if math.hypot(sin4, cos4) > 1e-9 * area.sum() else 0.0
        # The map's box in the dominant frame (so that it turns with the scene), as a yawed box.
        turn = rotation_z(dominant)
        aligned = centers @ turn  # (M, 3): R^T c
        half = 0.5 * aabb_extents(dims, yaws - dominant)
        low, high = (aligned - half).min(axis=0), (aligned + half).max(axis=0)
        ids = tuple(o.id for o in objects)
        return cls(
            ids=ids,
            rows={object_id: k for k, object_id in enumerate(ids)},
            labels=tuple(label_text(o.label) for o in objects),
            centers=centers,
            dims=dims,
            yaws=yaws,
            regions={
                r.id: (
                    np.asarray(r.center, dtype=np.float64),
                    np.asarray(r.size, dtype=np.float64),
                    label_text(r.name) or ROOM_LABEL,
                )
                for r in scene_graph.regions
            },
            map_box=(turn @ (0.5 * (low + high)), high - low),
            floor_z=percentile(centers[:, 2] - 0.5 * extents[:, 2], 10.0),
            dominant_yaw=dominant,
            centroid=centers.mean(axis=0),
        )


def percentile(values: np.ndarray, q: float) -> float:
    """`np.percentile(values, q)` (linear interpolation) for a 1-d array, without numpy's general machinery
    (a tenth of a millisecond per scene there)."""
    ordered = np.sort(values)
    position = q / 100.0 * (len(ordered) - 1)
    low = int(position)
    high = min(low + 1, len(ordered) - 1)
    return float(ordered[low] + (position - low) * (ordered[high] - ordered[low]))


def frame_yaw(arrays: SceneArrays, origin: np.ndarray) -> float:
    """The local frame's yaw: the dominant yaw plus the quarter turn that puts the objects' centroid, seen
    from `origin`, within 45 degrees of +x (the dominant yaw alone when the centroid is at the origin)."""
    direction = arrays.centroid[:2] - origin[:2]
    if float(np.hypot(*direction)) < 1e-6:
        return arrays.dominant_yaw
    angle = math.atan2(direction[1], direction[0]) - arrays.dominant_yaw
    turns = math.floor(angle / _QUARTER + 0.5)
    return arrays.dominant_yaw + turns * _QUARTER


def region_frame(
    low: np.ndarray,
    high: np.ndarray,
    relation: Relation,
    cfg: LSMConfig,
    scene_bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """s for the anchors' joint box [low, high] about t = 0 (the local origin): see the module docstring.

    For closest/farthest (with `cfg.ordinal_scene_frame` and `scene_bounds` given), s is at least the distance
    from t to the farther face of the scene's bounding box on each axis.
    """
    margin = np.array([cfg.region_margin_xy, cfg.region_margin_xy, cfg.region_margin_z])
    scale: np.ndarray = np.maximum(np.maximum(high, -low) + margin, cfg.region_min_half_extent)
    if cfg.ordinal_scene_frame and scene_bounds is not None and relation in ORDINAL_RELATIONS:
        scene_low, scene_high = scene_bounds
        scale = np.maximum(scale, np.maximum(-scene_low, scene_high))
    return scale


def make_sample(
    scene: SceneGraph | SceneArrays,
    anchor_ids: Sequence[str],
    relation: Relation,
    target_name: str,
    cfg: LSMConfig,
    target: Sequence[float] | None = None,
    region_id: str | None = None,
) -> Sample:
    """Keep the anchors and the `max_objects - len(anchors)` objects nearest to any anchor's centre.

    No `anchor_ids`: a region hypothesis, anchored on region `region_id`'s box (the map's when None or
    unknown). `target_name` is what the speaker called the target ("mug"); the sample's text is
    `hypothesis_text` of it, or with `cfg.text_input` "composed" `relation_text` and `target_text` apart.
    `target` (world) is carried into the local frame, for training and evaluation.
    """
    arrays = scene if isinstance(scene, SceneArrays) else SceneArrays.of(scene)
    row = arrays.rows
    missing = [i for i in anchor_ids if i not in row]
    if missing:
        msg = f"anchor object ids {missing} are not in the scene graph"
        raise NotFound(msg)
    anchors = np.array([row[i] for i in dict.fromkeys(anchor_ids)], dtype=np.int64)  # (A,)
    if len(anchors):
        anchor_centers, anchor_dims = arrays.centers[anchors], arrays.dims[anchors]
        anchor_yaws, anchor_labels = arrays.yaws[anchors], tuple(arrays.labels[k] for k in anchors)
    else:
        if region_id is not None and region_id in arrays.regions:
            centre, size, name = arrays.regions[region_id]
            box_yaw = 0.0
        else:  # the whole map
            (centre, size), name, box_yaw = arrays.map_box, ROOM_LABEL, arrays.dominant_yaw
        anchor_centers, anchor_dims, anchor_labels = centre[None], size[None], (name,)
        anchor_yaws = np.full(1, box_yaw)
    origin = anchor_centers.mean(axis=0)  # (3,)
    is_other = np.ones(len(arrays.ids), dtype=bool)
    is_other[anchors] = False
    others = np.flatnonzero(is_other)  # (M - A,) in scene order
    n_others = max(cfg.max_objects - len(anchor_centers), 0)
    if len(others) > n_others:
        diff = arrays.centers[others][:, None, :] - anchor_centers[None, :, :]  # (M - A, A, 3)
        dist = np.linalg.norm(diff, axis=-1).min(axis=1)  # (M - A,)
        others = others[np.argsort(dist, kind="stable")[:n_others]]

    yaw = frame_yaw(arrays, origin)
    rotation = rotation_z(yaw)  # world = R local + origin

    def local(points: np.ndarray) -> np.ndarray:
        local_points: np.ndarray = (points - origin) @ rotation  # (N, 3): R^T (p - o) row by row
        return local_points

    kept_centers = np.concatenate([local(anchor_centers), local(arrays.centers[others])])  # (n, 3)
    kept_sizes = np.concatenate(
        [
            aabb_extents(anchor_dims, anchor_yaws - yaw),
            aabb_extents(arrays.dims[others], arrays.yaws[others] - yaw),
        ]
    )
    turned_low, turned_high = arrays.turned_box(yaw)
    scene_low, scene_high = turned_low - origin @ rotation, turned_high - origin @ rotation
    n_anchors = len(anchor_centers)
    anchor_low = (kept_centers[:n_anchors] - 0.5 * kept_sizes[:n_anchors]).min(axis=0)
    anchor_high = (kept_centers[:n_anchors] + 0.5 * kept_sizes[:n_anchors]).max(axis=0)
    scale = region_frame(anchor_low, anchor_high, Relation(relation), cfg, (scene_low, scene_high))
    composed = cfg.text_input == "composed"
    return Sample(
        text=relation_text(relation, anchor_labels)
        if composed
        else hypothesis_text(target_name, relation, anchor_labels),
        labels=anchor_labels + tuple(arrays.labels[k] for k in others),
        centers=kept_centers.astype(np.float32),
        sizes=kept_sizes.astype(np.float32),
        roles=np.where(np.arange(len(kept_centers)) < n_anchors, ROLE_ANCHOR, ROLE_OTHER).astype(np.int64),
        relation=RELATION_INDEX[Relation(relation)],
        region_shift=np.zeros(3, dtype=np.float32),
        region_scale=scale.astype(np.float32),
        anchor_low=anchor_low.astype(np.float32),
        anchor_high=anchor_high.astype(np.float32),
        plain_top=len(anchors) == 1 and internal_support_reach(anchor_labels[0]) == 0,
        floor_z=float(arrays.floor_z - origin[2]),
        scene_low=scene_low.astype(np.float32),
        scene_high=scene_high.astype(np.float32),
        origin=origin,
        yaw=yaw,
        target=None
        if target is None
        else local(np.asarray(target, dtype=np.float64)[None])[0].astype(np.float32),
        target_text=target_text(target_name) if composed else None,
    )


def object_features(
    centers: torch.Tensor,
    sizes: torch.Tensor,
    shift: torch.Tensor,
    scale: torch.Tensor,
    floor_z: torch.Tensor,
    label_emb: torch.Tensor,
    text_emb: torch.Tensor,
) -> torch.Tensor:
    """[12-d geometry, cos(label, utterance)] per object; label_emb (B, N, E), text_emb (B, E) -> (B, N, 13).

    The cosine between an object's label and the utterance (both unit vectors) marks the objects the sentence
    talks about, e.g. the other chairs when the target is "the chair farthest from the door".
    """
    relevance = torch.einsum("bne,be->bn", label_emb, text_emb)[..., None]  # (B, N, 1)
    return torch.cat([object_geometry(centers, sizes, shift, scale, floor_z), relevance], dim=-1)


def object_geometry(
    centers: torch.Tensor,
    sizes: torch.Tensor,
    shift: torch.Tensor,
    scale: torch.Tensor,
    floor_z: torch.Tensor,
) -> torch.Tensor:
    """Per-object 12-d geometry in the anchor frame: centers, sizes (B, N, 3), t, s (B, 3), floor (B,).

    [(c - t) / s (3), size / 2s (3), log size (3), bottom and top height above floor (2), ||c - t|| (1)].
    """
    s, t = scale[:, None, :], shift[:, None, :]  # (B, 1, 3)
    floor = floor_z[:, None]  # (B, 1)
    bottom = centers[..., 2] - 0.5 * sizes[..., 2] - floor  # (B, N)
    top = centers[..., 2] + 0.5 * sizes[..., 2] - floor  # (B, N)
    return torch.cat(
        [
            (centers - t) / s,
            0.5 * sizes / s,
            torch.log(sizes.clamp(min=1e-2)),
            bottom[..., None],
            top[..., None],
            torch.linalg.vector_norm(centers - t, dim=-1, keepdim=True),
        ],
        dim=-1,
    )  # (B, N, 12)


def pair_features(
    centers: torch.Tensor, sizes: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor
) -> torch.Tensor:
    """12-d anchor-centric feature of each ordered pair (i, j); centers, sizes (B, N, 3) -> (B, N, N, 12).

    [(c_j - c_i) / s (3), size_i / 2s (3), size_j / 2s (3), ||c_j - c_i|| (1), ||c_i - t||, ||c_j - t|| (2)].
    """
    bsz, n_obj, _ = centers.shape
    s = scale[:, None, None, :]  # (B, 1, 1, 3)
    rel = centers[:, None, :, :] - centers[:, :, None, :]  # (B, N, N, 3): c_j - c_i
    half = 0.5 * sizes / scale[:, None, :]  # (B, N, 3)
    to_anchor = torch.linalg.vector_norm(centers - shift[:, None, :], dim=-1)  # (B, N)
    return torch.cat(
        [
            rel / s,
            half[:, :, None, :].expand(bsz, n_obj, n_obj, 3),
            half[:, None, :, :].expand(bsz, n_obj, n_obj, 3),
            torch.linalg.vector_norm(rel, dim=-1, keepdim=True),
            to_anchor[:, :, None, None].expand(bsz, n_obj, n_obj, 1),
            to_anchor[:, None, :, None].expand(bsz, n_obj, n_obj, 1),
        ],
        dim=-1,
    )  # (B, N, N, 12)


def region_condition(
    shift: torch.Tensor,
    scale: torch.Tensor,
    floor_z: torch.Tensor,
    scene_low: torch.Tensor,
    scene_high: torch.Tensor,
) -> torch.Tensor:
    """What the head's FiLM sees of (s, t) and the room around it; (B, 3) x 2, (B,), (B, 3) x 2 -> (B, 10).

    [log s (3), t_z - floor (1), (scene centre - t) / s (3), scene half-extent / s (3)]. The absolute x, y of
    t are left out on purpose (a map frame's origin carries no meaning); where the room lies relative to the
    anchors does ("farthest from the door" points across the room).
    """
    centre, half = 0.5 * (scene_low + scene_high), 0.5 * (scene_high - scene_low)  # (B, 3)
    return torch.cat(
        [torch.log(scale), (shift[:, 2] - floor_z)[:, None], (centre - shift) / scale, half / scale], dim=-1
    )


class PackedSamples:
    """Many samples padded to a common object count, with index tables into one embedding matrix."""

    def __init__(self, samples: Sequence[Sample], embed: Embed) -> None:
        if not samples:
            msg = "cannot pack zero samples"
            raise ValueError(msg)
        names = [s.target_text for s in samples if s.target_text is not None]
        texts = list(
            dict.fromkeys([s.text for s in samples] + names + [t for s in samples for t in s.labels])
        )
        row: dict[str | tuple[str, str], int] = {text: i for i, text in enumerate(texts)}
        embeddings = np.ascontiguousarray(embed(texts), dtype=np.float32)  # (U, E)
        # A composed sample's embedding is a row of its own after the texts': normalize(E(name) + E(text)).
        pairs = list(dict.fromkeys((s.text, s.target_text) for s in samples if s.target_text is not None))
        if pairs:
            summed = embeddings[[row[t] for t, _ in pairs]] + embeddings[[row[n] for _, n in pairs]]  # (C, E)
            summed /= np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), 1e-12)
            row.update({pair: len(texts) + k for k, pair in enumerate(pairs)})
            embeddings = np.concatenate([embeddings, summed])
        self.embeddings = torch.from_numpy(embeddings)  # (U + C, E)
        counts = np.array([len(s.labels) for s in samples])
        n_samples, n_obj = len(samples), int(counts.max())
        # Filled as numpy arrays (a slice assignment there costs a fraction of torch's), then shared.
        label_index = np.zeros((n_samples, n_obj), dtype=np.int64)
        centers = np.zeros((n_samples, n_obj, 3), dtype=np.float32)
        sizes = np.ones((n_samples, n_obj, 3), dtype=np.float32)  # padding: unit boxes keep the logs finite
        roles = np.full((n_samples, n_obj), ROLE_OTHER, dtype=np.int64)
        for i, s in enumerate(samples):
            n = counts[i]
            label_index[i, :n] = [row[t] for t in s.labels]
            centers[i, :n] = s.centers
            sizes[i, :n] = s.sizes
            roles[i, :n] = s.roles
        self.text_index = torch.tensor(
            [row[s.text if s.target_text is None else (s.text, s.target_text)] for s in samples]
        )  # (S,)
        self.label_index = torch.from_numpy(label_index)  # (S, N)
        self.centers = torch.from_numpy(centers)  # (S, N, 3)
        self.sizes = torch.from_numpy(sizes)  # (S, N, 3)
        self.roles = torch.from_numpy(roles)  # (S, N)
        self.mask = torch.from_numpy(np.arange(n_obj) < counts[:, None])  # (S, N)
        self.relation = torch.tensor([s.relation for s in samples])  # (S,)
        self.shift = torch.from_numpy(np.stack([s.region_shift for s in samples]))  # (S, 3)
        self.scale = torch.from_numpy(np.stack([s.region_scale for s in samples]))  # (S, 3)
        self.anchor_low = torch.from_numpy(np.stack([s.anchor_low for s in samples]))  # (S, 3)
        self.anchor_high = torch.from_numpy(np.stack([s.anchor_high for s in samples]))  # (S, 3)
        self.plain_top = torch.tensor([s.plain_top for s in samples], dtype=torch.bool)  # (S,)
        self.floor_z = torch.tensor([s.floor_z for s in samples], dtype=torch.float32)  # (S,)
        self.scene_low = torch.from_numpy(np.stack([s.scene_low for s in samples]))  # (S, 3)
        self.scene_high = torch.from_numpy(np.stack([s.scene_high for s in samples]))  # (S, 3)
        targets = [s.target for s in samples if s.target is not None]
        self.target = torch.from_numpy(np.stack(targets)) if len(targets) == len(samples) else None  # (S, 3)

    def __len__(self) -> int:
        return len(self.relation)

    def batch(self, index: torch.Tensor | slice | None = None) -> LSMBatch:
        """The samples at `index` (all if None), cropped to their largest object count."""
        index = slice(None) if index is None else index
        mask = self.mask[index]  # (B, N)
        n = max(int(mask.sum(dim=1).max()), 1)
        centers, sizes = self.centers[index][:, :n], self.sizes[index][:, :n]  # (B, n, 3)
        shift, scale, floor_z = self.shift[index], self.scale[index], self.floor_z[index]
        text_emb = self.embeddings[self.text_index[index]]  # (B, E)
        label_emb = self.embeddings[self.label_index[index][:, :n]]  # (B, n, E)
        return LSMBatch(
            text_emb=text_emb,
            label_emb=label_emb,
            object_features=object_features(centers, sizes, shift, scale, floor_z, label_emb, text_emb),
            pair=pair_features(centers, sizes, shift, scale),
            roles=self.roles[index][:, :n],
            mask=mask[:, :n],
            relation=self.relation[index],
            region_shift=shift,
            region_scale=scale,
            anchor_low=self.anchor_low[index],
            anchor_high=self.anchor_high[index],
            plain_top=self.plain_top[index],
            region_cond=region_condition(
                shift, scale, floor_z, self.scene_low[index], self.scene_high[index]
            ),
            target=None if self.target is None else self.target[index],
        )


class EmbeddingCache:
    """Text -> frozen embedding, kept in memory and in an .npz file; missing texts go to the text encoder.

    The file records the encoder's weights sha256 and is ignored if it came from different weights.
    """

    def __init__(self, path: Path | None, encoder_sha256: str, encoder_factory: Callable[[], Embed]) -> None:
        self.path = None if path is None else Path(path)
        self.encoder_sha256 = encoder_sha256
        self._encoder_factory = encoder_factory
        self._encoder: Embed | None = None
        self._table: dict[str, np.ndarray] = {}
        if self.path is not None and self.path.is_file():
            with np.load(self.path) as data:
                if str(data["encoder_sha256"]) == encoder_sha256:
                    self._table = dict(zip(data["texts"].tolist(), data["embeddings"], strict=True))

    def __len__(self) -> int:
        return len(self._table)

    def __call__(self, texts: Sequence[str]) -> np.ndarray:
        missing = [t for t in dict.fromkeys(texts) if t not in self._table]
        if missing:
            if self._encoder is None:
                self._encoder = self._encoder_factory()
            self._table.update(zip(missing, self._encoder(missing), strict=True))
        return np.stack([self._table[t] for t in texts]).astype(np.float32)

    def save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        texts = list(self._table)
        np.savez(
            self.path,
            texts=np.array(texts, dtype=str),
            embeddings=np.stack([self._table[t] for t in texts]) if texts else np.zeros((0, 384), np.float32),
            encoder_sha256=np.array(self.encoder_sha256),
        )
