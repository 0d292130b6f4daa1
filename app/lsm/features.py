"""LSM inputs: (SceneGraph, hypothesis, utterance) -> padded, masked tensors.

A `Sample` holds one hypothesis's raw inputs (texts, boxes, roles, relation, region frame); `PackedSamples`
stacks many of them with their text embeddings and slices batches (`LSMBatch`) out of them, computing the
geometry features on the fly. The text encoder is frozen, so embeddings are looked up, never trained:
`EmbeddingCache` keeps them on disk during training and the grounder keeps them in an LRU.

The anchor region frame (s, t) is where the model's output lives (mu_w = s * tanh(.) + t):

    t = centre of the anchors' joint axis-aligned box,
    s = max(joint half-extent + (m_xy, m_xy, m_z), s_min)          (per axis, metres)

The margin is relation-independent: "near" targets (within 0.6 m of the anchor's surface in the case builder)
and "between" targets stay well inside, and m_z = 1.5 m reaches objects hanging up to 1.5 m above or below
the anchor. s_min keeps tiny anchors from shrinking the frame (and the covariance, whose floor is 0.05 s) to
nothing. "closest" and "farthest" pick one of several same-class objects anywhere in the room, so for them
(with `ordinal_scene_frame`) s is widened per axis until t +- s holds the whole scene's bounding box.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from app.errors import NotFound
from app.grounding.relations import Relation
from app.lsm.model import RELATION_INDEX, ROLE_ANCHOR, ROLE_OTHER, LSMBatch, LSMConfig
from app.scene_graph.model import SceneGraph, SceneObject

Embed = Callable[[Sequence[str]], np.ndarray]
ORDINAL_RELATIONS = (Relation.CLOSEST, Relation.FARTHEST)
_CAMEL_BOUNDARY = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")


def label_text(label: str) -> str:
    """The phrase a label is embedded as: "DiningTable" -> "dining table", "trash_can" -> "trash can"."""
    words = _CAMEL_BOUNDARY.sub(" ", label).replace("_", " ").replace("-", " ")
    return " ".join(words.lower().split())


@dataclass(frozen=True)
class Sample:
    """One hypothesis in its scene: the kept objects (anchors first) and the region frame."""

    utterance: str
    labels: tuple[str, ...]  # n embedding texts
    centers: np.ndarray  # (n, 3) metres
    sizes: np.ndarray  # (n, 3) axis-aligned extents, metres
    roles: np.ndarray  # (n,) ROLE_ANCHOR / ROLE_OTHER
    relation: int  # RELATION_INDEX
    region_shift: np.ndarray  # (3,) t
    region_scale: np.ndarray  # (3,) s
    floor_z: float
    target: np.ndarray | None = None  # (3,)


def region_frame(
    anchors: Sequence[SceneObject],
    relation: Relation,
    cfg: LSMConfig,
    scene_bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(t, s): t the centre of the anchors' joint box, s = max(half-extent + margin, s_min) per axis.

    For closest/farthest (with `cfg.ordinal_scene_frame` and `scene_bounds` given), s is at least the distance
    from t to the farther face of the scene's bounding box on each axis.
    """
    low = np.min([a.min_corner for a in anchors], axis=0)
    high = np.max([a.max_corner for a in anchors], axis=0)
    margin = np.array([cfg.region_margin_xy, cfg.region_margin_xy, cfg.region_margin_z])
    shift = 0.5 * (low + high)
    scale = np.maximum(0.5 * (high - low) + margin, cfg.region_min_half_extent)
    if cfg.ordinal_scene_frame and scene_bounds is not None and relation in ORDINAL_RELATIONS:
        scene_low, scene_high = scene_bounds
        scale = np.maximum(scale, np.maximum(shift - scene_low, scene_high - shift))
    return shift, scale


def floor_height(scene_graph: SceneGraph) -> float:
    """The floor's height: the 10th percentile of object bottoms (most furniture stands on the floor)."""
    if not scene_graph.objects:
        return 0.0
    bottoms = [o.min_corner[2] for o in scene_graph.objects]
    return float(np.percentile(bottoms, 10))


def make_sample(
    scene_graph: SceneGraph,
    anchor_ids: Sequence[str],
    relation: Relation,
    utterance: str,
    cfg: LSMConfig,
    target: Sequence[float] | None = None,
    floor_z: float | None = None,
) -> Sample:
    """Keep the anchors and the `max_objects - len(anchors)` objects nearest to any anchor's centre."""
    by_id = {o.id: o for o in scene_graph.objects}
    missing = [i for i in anchor_ids if i not in by_id]
    if missing or not anchor_ids:
        msg = f"anchor object ids {missing or list(anchor_ids)} are not in the scene graph"
        raise NotFound(msg)
    anchors = [by_id[i] for i in dict.fromkeys(anchor_ids)]
    anchor_set = {a.id for a in anchors}
    others = [o for o in scene_graph.objects if o.id not in anchor_set]
    n_others = max(cfg.max_objects - len(anchors), 0)
    if others and len(others) > n_others:
        anchor_centers = np.array([a.center for a in anchors])  # (A, 3)
        other_centers = np.array([o.center for o in others])  # (M, 3)
        dist = np.linalg.norm(other_centers[:, None, :] - anchor_centers[None, :, :], axis=-1).min(
            axis=1
        )  # (M,)
        others = [others[i] for i in np.argsort(dist, kind="stable")[:n_others]]
    kept = anchors + others
    shift, scale = region_frame(anchors, Relation(relation), cfg, scene_graph.bounds())
    return Sample(
        utterance=utterance,
        labels=tuple(label_text(o.label) for o in kept),
        centers=np.array([o.center for o in kept], dtype=np.float32),
        sizes=np.array([2.0 * o.half_extent for o in kept], dtype=np.float32),
        roles=np.array([ROLE_ANCHOR] * len(anchors) + [ROLE_OTHER] * len(others), dtype=np.int64),
        relation=RELATION_INDEX[Relation(relation)],
        region_shift=shift.astype(np.float32),
        region_scale=scale.astype(np.float32),
        floor_z=floor_height(scene_graph) if floor_z is None else floor_z,
        target=None if target is None else np.asarray(target, dtype=np.float32),
    )


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


def region_condition(shift: torch.Tensor, scale: torch.Tensor, floor_z: torch.Tensor) -> torch.Tensor:
    """What the head's FiLM sees of (s, t): [log s (3), t_z - floor (1)]; (B, 3), (B, 3), (B,) -> (B, 4).

    The horizontal part of t is left out on purpose: a map frame's x, y origin carries no meaning.
    """
    return torch.cat([torch.log(scale), (shift[:, 2] - floor_z)[:, None]], dim=-1)


class PackedSamples:
    """Many samples padded to a common object count, with index tables into one embedding matrix."""

    def __init__(self, samples: Sequence[Sample], embed: Embed) -> None:
        if not samples:
            msg = "cannot pack zero samples"
            raise ValueError(msg)
        texts = list(dict.fromkeys([s.utterance for s in samples] + [t for s in samples for t in s.labels]))
        row = {text: i for i, text in enumerate(texts)}
        self.embeddings = torch.from_numpy(np.ascontiguousarray(embed(texts), dtype=np.float32))  # (U, E)
        n_samples, n_obj = len(samples), max(len(s.labels) for s in samples)
        self.text_index = torch.tensor([row[s.utterance] for s in samples])  # (S,)
        self.label_index = torch.zeros(n_samples, n_obj, dtype=torch.long)  # (S, N)
        self.centers = torch.zeros(n_samples, n_obj, 3)  # (S, N, 3)
        self.sizes = torch.ones(
            n_samples, n_obj, 3
        )  # (S, N, 3); padding gets unit boxes to keep the logs finite
        self.roles = torch.full((n_samples, n_obj), ROLE_OTHER, dtype=torch.long)  # (S, N)
        self.mask = torch.zeros(n_samples, n_obj, dtype=torch.bool)  # (S, N)
        for i, s in enumerate(samples):
            n = len(s.labels)
            self.label_index[i, :n] = torch.tensor([row[t] for t in s.labels])
            self.centers[i, :n] = torch.from_numpy(s.centers)
            self.sizes[i, :n] = torch.from_numpy(s.sizes)
            self.roles[i, :n] = torch.from_numpy(s.roles)
            self.mask[i, :n] = True
        self.relation = torch.tensor([s.relation for s in samples])  # (S,)
        self.shift = torch.from_numpy(np.stack([s.region_shift for s in samples]))  # (S, 3)
        self.scale = torch.from_numpy(np.stack([s.region_scale for s in samples]))  # (S, 3)
        self.floor_z = torch.tensor([s.floor_z for s in samples], dtype=torch.float32)  # (S,)
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
        return LSMBatch(
            text_emb=self.embeddings[self.text_index[index]],
            label_emb=self.embeddings[self.label_index[index][:, :n]],
            geometry=object_geometry(centers, sizes, shift, scale, floor_z),
            pair=pair_features(centers, sizes, shift, scale),
            roles=self.roles[index][:, :n],
            mask=mask[:, :n],
            relation=self.relation[index],
            region_shift=shift,
            region_scale=scale,
            region_cond=region_condition(shift, scale, floor_z),
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
