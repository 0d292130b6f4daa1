"""LSM inputs: (SceneGraph, hypothesis, utterance) -> padded, masked tensors.

A `Sample` holds one hypothesis's raw inputs (texts, boxes, roles, relation, region frame); `PackedSamples`
stacks many of them with their text embeddings and slices batches (`LSMBatch`) out of them, computing the
geometry features on the fly. The text encoder is frozen, so embeddings are looked up, never trained:
`EmbeddingCache` keeps them on disk during training and the grounder keeps them in an LRU.

The anchor region frame (s, t) is where the model's output lives (mu_w = s * tanh(.) + t):

    t = mean of the anchors' centres (the midpoint for "between"),
    s = max(max(high - t, t - low) + (m_xy, m_xy, m_z), s_min)     (per axis, metres)

with [low, high] the anchors' joint axis-aligned box, so t +- s holds every anchor plus the margin. For one
anchor this is its centre and half-extent + margin. mu = 0 (the head's initial output) is the anchor's centre,
or the midpoint between the two anchors.

The margin is relation-independent: "near" targets (within 0.6 m of the anchor's surface in the case builder)
and "between" targets stay well inside, and m_z = 1.5 m reaches objects hanging up to 1.5 m above or below
the anchor. s_min keeps tiny anchors from shrinking the frame (and the covariance, whose floor is 0.05 s) to
nothing. "closest" and "farthest" pick one of several same-class objects anywhere in the room, so for them
(with `ordinal_scene_frame`) s is widened per axis until t +- s holds the whole scene's bounding box.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from app.errors import NotFound
from app.grounding.relations import Relation
from app.lsm.model import RELATION_INDEX, ROLE_ANCHOR, ROLE_OTHER, LSMBatch, LSMConfig
from app.scene_graph.model import SceneGraph

Embed = Callable[[Sequence[str]], np.ndarray]
ORDINAL_RELATIONS = (Relation.CLOSEST, Relation.FARTHEST)
_CAMEL_BOUNDARY = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")


@lru_cache(maxsize=4096)  # labels repeat across every request on the same maps
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
    scene_low: np.ndarray  # (3,) corners of the scene's bounding box
    scene_high: np.ndarray  # (3,)
    target: np.ndarray | None = None  # (3,)


@dataclass(frozen=True)
class SceneArrays:
    """A scene graph as arrays, computed once per scene and shared by all of its hypotheses."""

    ids: tuple[str, ...]
    rows: Mapping[str, int]  # object id -> its row in the arrays
    labels: tuple[str, ...]  # embedding texts (label_text)
    centers: np.ndarray  # (M, 3)
    sizes: np.ndarray  # (M, 3) extents of the axis-aligned boxes (yaw included)
    bounds: tuple[np.ndarray, np.ndarray]  # scene's (low, high) corners, objects and regions
    floor_z: float  # 10th percentile of object bottoms: most furniture stands on the floor

    @classmethod
    def of(cls, scene_graph: SceneGraph) -> SceneArrays:
        objects = scene_graph.objects
        centers = np.array([o.center for o in objects], dtype=np.float64).reshape(-1, 3)
        box = np.array([o.size for o in objects], dtype=np.float64).reshape(-1, 3)
        # SceneObject.half_extent for all objects at once: the axis-aligned extent of each yawed box.
        yaw = np.array([o.yaw for o in objects], dtype=np.float64)
        cos, sin = np.abs(np.cos(yaw)), np.abs(np.sin(yaw))
        sizes = np.stack(
            [cos * box[:, 0] + sin * box[:, 1], sin * box[:, 0] + cos * box[:, 1], box[:, 2]], axis=1
        )
        bottoms = centers[:, 2] - 0.5 * sizes[:, 2]
        if scene_graph.regions:  # SceneGraph.bounds() without recomputing every object's extent
            region_centers = np.array([r.center for r in scene_graph.regions], dtype=np.float64)
            region_half = 0.5 * np.array([r.size for r in scene_graph.regions], dtype=np.float64)
            lows = np.concatenate([centers - 0.5 * sizes, region_centers - region_half])
            highs = np.concatenate([centers + 0.5 * sizes, region_centers + region_half])
        else:
            lows, highs = centers - 0.5 * sizes, centers + 0.5 * sizes
        bounds = (lows.min(axis=0), highs.max(axis=0)) if len(lows) else scene_graph.bounds()
        ids = tuple(o.id for o in objects)
        return cls(
            ids=ids,
            rows={object_id: k for k, object_id in enumerate(ids)},
            labels=tuple(label_text(o.label) for o in objects),
            centers=centers,
            sizes=sizes,
            bounds=bounds,
            floor_z=percentile(bottoms, 10.0) if len(objects) else 0.0,
        )


def percentile(values: np.ndarray, q: float) -> float:
    """`np.percentile(values, q)` (linear interpolation) for a 1-d array, without numpy's general machinery
    (a tenth of a millisecond per scene there)."""
    ordered = np.sort(values)
    position = q / 100.0 * (len(ordered) - 1)
    low = int(position)
    high = min(low + 1, len(ordered) - 1)
    return float(ordered[low] + (position - low) * (ordered[high] - ordered[low]))


def region_frame(
    centers: np.ndarray,
    sizes: np.ndarray,
    relation: Relation,
    cfg: LSMConfig,
    scene_bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(t, s) of the anchors' boxes, centers and sizes (A, 3): see the module docstring.

    For closest/farthest (with `cfg.ordinal_scene_frame` and `scene_bounds` given), s is at least the distance
    from t to the farther face of the scene's bounding box on each axis.
    """
    low = np.min(centers - 0.5 * sizes, axis=0)
    high = np.max(centers + 0.5 * sizes, axis=0)
    margin = np.array([cfg.region_margin_xy, cfg.region_margin_xy, cfg.region_margin_z])
    shift = centers.mean(axis=0)
    scale = np.maximum(np.maximum(high - shift, shift - low) + margin, cfg.region_min_half_extent)
    if cfg.ordinal_scene_frame and scene_bounds is not None and relation in ORDINAL_RELATIONS:
        scene_low, scene_high = scene_bounds
        scale = np.maximum(scale, np.maximum(shift - scene_low, scene_high - shift))
    return shift, scale


def make_sample(
    scene: SceneGraph | SceneArrays,
    anchor_ids: Sequence[str],
    relation: Relation,
    utterance: str,
    cfg: LSMConfig,
    target: Sequence[float] | None = None,
) -> Sample:
    """Keep the anchors and the `max_objects - len(anchors)` objects nearest to any anchor's centre."""
    arrays = scene if isinstance(scene, SceneArrays) else SceneArrays.of(scene)
    row = arrays.rows
    missing = [i for i in anchor_ids if i not in row]
    if missing or not anchor_ids:
        msg = f"anchor object ids {missing or list(anchor_ids)} are not in the scene graph"
        raise NotFound(msg)
    anchors = np.array([row[i] for i in dict.fromkeys(anchor_ids)])  # (A,)
    is_other = np.ones(len(arrays.ids), dtype=bool)
    is_other[anchors] = False
    others = np.flatnonzero(is_other)  # (M - A,) in scene order
    n_others = max(cfg.max_objects - len(anchors), 0)
    if len(others) > n_others:
        diff = arrays.centers[others][:, None, :] - arrays.centers[anchors][None, :, :]  # (M - A, A, 3)
        dist = np.linalg.norm(diff, axis=-1).min(axis=1)  # (M - A,)
        others = others[np.argsort(dist, kind="stable")[:n_others]]
    kept = np.concatenate([anchors, others])
    shift, scale = region_frame(
        arrays.centers[anchors], arrays.sizes[anchors], Relation(relation), cfg, arrays.bounds
    )
    return Sample(
        utterance=utterance,
        labels=tuple(arrays.labels[k] for k in kept),
        centers=arrays.centers[kept].astype(np.float32),
        sizes=arrays.sizes[kept].astype(np.float32),
        roles=np.where(np.arange(len(kept)) < len(anchors), ROLE_ANCHOR, ROLE_OTHER).astype(np.int64),
        relation=RELATION_INDEX[Relation(relation)],
        region_shift=shift.astype(np.float32),
        region_scale=scale.astype(np.float32),
        floor_z=arrays.floor_z,
        scene_low=arrays.bounds[0].astype(np.float32),
        scene_high=arrays.bounds[1].astype(np.float32),
        target=None if target is None else np.asarray(target, dtype=np.float32),
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
        texts = list(dict.fromkeys([s.utterance for s in samples] + [t for s in samples for t in s.labels]))
        row = {text: i for i, text in enumerate(texts)}
        self.embeddings = torch.from_numpy(np.ascontiguousarray(embed(texts), dtype=np.float32))  # (U, E)
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
        self.text_index = torch.tensor([row[s.utterance] for s in samples])  # (S,)
        self.label_index = torch.from_numpy(label_index)  # (S, N)
        self.centers = torch.from_numpy(centers)  # (S, N, 3)
        self.sizes = torch.from_numpy(sizes)  # (S, N, 3)
        self.roles = torch.from_numpy(roles)  # (S, N)
        self.mask = torch.from_numpy(np.arange(n_obj) < counts[:, None])  # (S, N)
        self.relation = torch.tensor([s.relation for s in samples])  # (S,)
        self.shift = torch.from_numpy(np.stack([s.region_shift for s in samples]))  # (S, 3)
        self.scale = torch.from_numpy(np.stack([s.region_scale for s in samples]))  # (S, 3)
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
