"""One robot's belief about one target: the layers (`BeliefState`) and the session record around them.

`BeliefState` owns the two float32 layers of `app.belief.fusion` and a version counter that every update
increments. `Session` adds what turns raw robot messages into layer increments: the scene graph, the
grid, the target class, the label map (id -> name) and the default sensor model. Stores (`app.stores`)
persist sessions; `Session.observation_batch` / `detection_batch` turn a message into an
`IncrementBatch` (flat voxel indices + increments) that a store logs and applies.

Label matching: a robot label names the target when both are of the same class (`app.vocabulary.class_key`;
the rule, and why a look-alike is only the same class, never a looser naming, is written there once).

Mapped look-alikes: the scene graph never holds the target (that is why the robot searches), but it may
hold other objects of the target's class (the other chairs when the target is a chair). A class-level
segmenter labels their voxels with the target's class whether or not the target is there, so at a voxel
inside such an object's box P(y | t = i) = P(y | t != i) for every label y: the label is explained by the
mapped object and equation (4) adds nothing there (`mapped_look_alikes`). Without this, every sighting of
a known look-alike counted as a sighting of the target and, repeated, drove its vision log-weight to the
clamp, taking the belief's mass from wherever the language put it. Detector probabilities (5) are taken
as already instance-aware and are not filtered.

Unknown target: a session may start with an empty target label ("": the class is not known yet, e.g.
until the first utterance names it). Detector probabilities (equation (5)) need no class and fuse as
usual; labelled observations (equation (4)) raise `Conflict` until `Session.set_target_label` (or a
store's `set_target_label`) names the class.
"""

from __future__ import annotations

import itertools
import math
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.belief import fusion
from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_MAX_VOXELS, DEFAULT_VOXEL_SIZE_M, VoxelGrid
from app.belief.summary import DEFAULT_TOP_K, ON_MARGIN_M, PosteriorSummary, cached_place_index, summarize
from app.errors import Conflict, InvalidInput, LimitExceeded
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph
from app.vocabulary import class_key

#: Default sensor model: placeholders for a decent semantic segmenter; set them from its confusion matrix.
DEFAULT_TRUE_POSITIVE_RATE = 0.9
DEFAULT_FALSE_POSITIVE_RATE = 0.05
#: Label maps whose largest id is below this are looked up in a dense table (one int8 per id: a lookup per
#: voxel is the fastest there is); larger ids are found by binary search, so no id allocates memory.
_DENSE_LABEL_IDS = 1 << 16
#: Look-alikes of at most this many voxels are found in a batch by comparison rather than a grid mask.
_FEW_LOOK_ALIKE_VOXELS = 4


@dataclass(frozen=True)
class LabelNames:
    """Class names of a batch as codes into the distinct names: what a batch of string labels is decoded to,
    so that its memory is one int32 per label plus each distinct name once (a fixed-width numpy string array
    takes the longest name's width for every label)."""

    codes: np.ndarray  # (M,) int32 indices into `names`
    names: tuple[str, ...]

    @classmethod
    def of(cls, labels: Sequence[str]) -> LabelNames:
        index: dict[str, int] = {}
        codes = np.fromiter((index.setdefault(name, len(index)) for name in labels), np.int32, len(labels))
        return cls(codes, tuple(index))

    def __len__(self) -> int:
        return len(self.codes)


#: A batch's labels: label-map ids, or class names (a list, a numpy string array, or `LabelNames`).
Labels = Sequence[int] | Sequence[str] | np.ndarray | LabelNames


def check_target_label(target_label: str, label_map: Mapping[int, str]) -> None:
    """InvalidInput (field "target_label") unless the label names a class the label map (if any) knows."""
    key = class_key(target_label) if isinstance(target_label, str) else ""
    if not key:
        msg = f"the target label must name a class, got {target_label!r}"
        raise InvalidInput(msg, "target_label")
    if label_map and not any(class_key(name) == key for name in label_map.values()):
        msg = f"no name in the session's label_map matches the target {target_label!r}"
        raise InvalidInput(msg, "target_label")


@dataclass(frozen=True)
class SensorModel:
    """tp = P(label = target | target in the voxel), fp = P(label = target | target not in the voxel)."""

    tp: float = DEFAULT_TRUE_POSITIVE_RATE
    fp: float = DEFAULT_FALSE_POSITIVE_RATE

    def __post_init__(self) -> None:
        fusion.check_sensor_model(self.tp, self.fp)


@dataclass(frozen=True)
class IncrementBatch:
    """Vision-layer increments ready to apply: what a store logs and replays."""

    flat_idx: np.ndarray  # (M,) int64 voxel indices, may repeat
    increments: np.ndarray  # (M,) float32 log-likelihood ratios
    n_outside: int = 0  # points of the message that fell outside the grid (dropped)


@dataclass(frozen=True)
class UpdateResult:
    """What a store answers to an update."""

    session_id: str
    version: int
    voxels_updated: int
    voxels_outside: int = 0


@dataclass(frozen=True)
class SessionInfo:
    """A session without its scene graph and layers (what listings and `info` return); "" = unknown target."""

    id: str
    robot_id: str
    target_label: str
    n_voxels: int
    created_at: float
    updated_at: float
    version: int
    grid: VoxelGrid
    sensor_model: SensorModel
    label_map: dict[int, str]


class BeliefState:
    """The two log-weight layers of one belief (fusion equations (2)-(5)) and its version counter."""

    def __init__(
        self,
        grid: VoxelGrid,
        limits: fusion.LayerLimits | None = None,
        lang: np.ndarray | None = None,
        vis: np.ndarray | None = None,
        version: int = 0,
    ) -> None:
        self.grid = grid
        self.limits = limits or fusion.LayerLimits()
        self.lang = self._layer(lang, "lang")  # (N,) float32, max 0, >= -lang_span
        self.vis = self._layer(vis, "vis")  # (N,) float32 in [vis_min, vis_max]
        self.version = version

    def _layer(self, values: np.ndarray | None, name: str) -> np.ndarray:
        if values is None:
            return np.zeros(self.grid.n_voxels, dtype=fusion.LAYER_DTYPE)
        layer = np.ascontiguousarray(values, dtype=fusion.LAYER_DTYPE)
        if layer.shape != (self.grid.n_voxels,):
            msg = f"layer {name} has shape {layer.shape}, the grid needs ({self.grid.n_voxels},)"
            raise InvalidInput(msg, name)
        return layer

    @property
    def nbytes(self) -> int:
        return self.lang.nbytes + self.vis.nbytes

    def apply_utterance(self, mixture: GaussianMixture) -> int:
        """Equation (3) for one utterance, then shift and clamp the language layer; returns the version."""
        span = self.limits.lang_span
        fusion.apply_language(self.lang, language_log_likelihood(self.grid, mixture, span), span)
        self.version += 1
        return self.version

    def apply_increments(self, batch: IncrementBatch) -> int:
        """Add a batch of vision-layer increments (equations (4)/(5)) and clamp; returns the new version."""
        fusion.apply_increments(
            self.vis, batch.flat_idx, batch.increments, self.limits.vis_min, self.limits.vis_max
        )
        self.version += 1
        return self.version

    def posterior(self) -> np.ndarray:
        """softmax(lang + vis), (N,) float64."""
        return fusion.posterior(self.lang, self.vis)

    def summary(self, scene_graph: SceneGraph | None = None, **kwargs: Any) -> PosteriorSummary:
        return summarize(self.grid, self.lang, self.vis, scene_graph, **kwargs)

    def copy(self) -> BeliefState:
        return BeliefState(self.grid, self.limits, self.lang.copy(), self.vis.copy(), self.version)


def language_log_likelihood(
    grid: VoxelGrid, mixture: GaussianMixture, span: float = fusion.LANG_LOG_SPAN
) -> np.ndarray:
    """`fusion.language_log_likelihood` with the mixture checked first (a bad one is the client's error):
    the term for a language layer of span up to `span` (the default layers')."""
    means, covs = np.asarray(mixture.means), np.asarray(mixture.covariances)
    if means.ndim != 2 or means.shape[1:] != (3,) or covs.shape != (len(means), 3, 3):
        msg = f"mixture needs (K, 3) means and (K, 3, 3) covariances, got {means.shape} and {covs.shape}"
        raise InvalidInput(msg, "mixture")
    lows, highs = np.asarray(mixture.box_lows), np.asarray(mixture.box_highs)
    n_boxes = len(mixture.box_weights)
    if lows.shape != (n_boxes, 3) or highs.shape != (n_boxes, 3):
        msg = f"mixture needs (B, 3) box corners, got {lows.shape} and {highs.shape}"
        raise InvalidInput(msg, "mixture")
    parameters = (means, covs, mixture.weights, mixture.box_weights, lows, highs)
    if not all(np.all(np.isfinite(p)) for p in parameters):
        msg = "mixture parameters must be finite"
        raise InvalidInput(msg, "mixture")
    if np.any(highs <= lows):
        msg = "mixture boxes need high > low on every axis"
        raise InvalidInput(msg, "mixture")
    try:
        return fusion.language_log_likelihood(grid, mixture, span)
    except np.linalg.LinAlgError as exc:
        msg = f"mixture covariances must be positive definite: {exc}"
        raise InvalidInput(msg, "mixture") from exc


def mapped_look_alikes(grid: VoxelGrid, scene_graph: SceneGraph, target_label: str) -> np.ndarray:
    """Sorted flat indices of the voxels inside the boxes of scene-graph objects of the target's class.

    Boxes are the objects' own (yaw respected, nothing added on top); an object smaller than a voxel gets the
    voxel holding its centre, as in the summary's places. Empty when the target class is unknown.
    """
    key = class_key(target_label) if target_label else ""
    if not key:
        return np.zeros(0, dtype=np.int64)
    inside = None  # (nx, ny, nz) bool, made when an object matches: no per-object index lists
    for place in cached_place_index(grid, scene_graph, on_margin=0.0).objects:  # one per object, in order
        if class_key(place.label) != key:
            continue
        if inside is None:
            inside = np.zeros(grid.shape, dtype=bool)
        inside[place.slices] |= True if place.mask is None else place.mask
    return np.zeros(0, dtype=np.int64) if inside is None else np.flatnonzero(inside)


class ObservationModel:
    """Turns robot messages (labels or detector probabilities at points or voxels) into vision increments.

    Holds what that needs of a session: the grid, the target class, the label map, the default sensor
    model and the voxels of mapped look-alikes (`mapped_look_alikes`, where labels carry no evidence);
    stores that keep the scene graph apart (Redis) pass those voxels in. An empty `target_label` means the
    class is not known yet: detections work, labelled observations raise `Conflict`.
    """

    def __init__(
        self,
        grid: VoxelGrid,
        target_label: str,
        label_map: dict[int, str],
        sensor_model: SensorModel,
        look_alikes: np.ndarray | None = None,
    ) -> None:
        self.grid = grid
        self.target_label = target_label
        self.sensor_model = sensor_model
        # Over the whole grid, so that a batch is filtered by one lookup per voxel (np.isin cost ~10 ms/100k);
        # made on the first labelled batch (a store may build a model per update, e.g. for a detection).
        self._look_alikes = (
            np.asarray(look_alikes, dtype=np.int64) if look_alikes is not None and len(look_alikes) else None
        )
        self._look_alike_mask_made: np.ndarray | None = None
        # (tp, fp) -> float32 increment of each label id (NaN: not in the label map), `_id_increments`
        self._increment_tables: dict[tuple[float, float], np.ndarray] = {}
        self._target_key = class_key(target_label)
        if target_label and not self._target_key:
            msg = f"the target label {target_label!r} names no class"
            raise InvalidInput(msg, "target_label")
        if any(k < 0 for k in label_map):
            msg = "label ids must be non-negative integers"
            raise InvalidInput(msg, "label_map")
        # label id -> 1 (names the target) or 0 (another class); ids not in the map are refused
        self._ids = np.array(sorted(label_map), dtype=np.int64)
        self._id_classes = np.array(
            [class_key(label_map[i]) == self._target_key for i in self._ids.tolist()], dtype=np.int8
        )
        self._known_keys = frozenset(class_key(name) for name in label_map.values())
        if self._target_key and label_map and not np.any(self._id_classes == 1):
            msg = f"no name in label_map matches the target {target_label!r}; name it or send string labels"
            raise InvalidInput(msg, "label_map")
        self._dense: np.ndarray | None = None
        if len(self._ids) and self._ids[-1] < _DENSE_LABEL_IDS:
            self._dense = np.full(int(self._ids[-1]) + 1, -1, dtype=np.int8)
            self._dense[self._ids] = self._id_classes
        self._dense_has_gaps = self._dense is not None and bool(np.any(self._dense < 0))

    @property
    def _look_alike_mask(self) -> np.ndarray | None:
        """(N,) bool: the voxels of mapped look-alikes; None if there are none."""
        if self._look_alikes is not None and self._look_alike_mask_made is None:
            mask = np.zeros(self.grid.n_voxels, dtype=bool)
            mask[self._look_alikes] = True
            self._look_alike_mask_made = mask
        return self._look_alike_mask_made

    def _id_increments(self, labels: Labels, tp: float, fp: float) -> np.ndarray | None:
        """Equation (4)'s increment of each label id in one lookup, (M,) float32: the same values as
        `fusion.vision_increments(self.is_target(labels), tp, fp)`. None where that fast case does not
        apply (no target class, string labels, sparse or no label map, invalid rates, any id not in the
        map): the caller then takes that path, which raises exactly as before."""
        if not (
            self._dense is not None
            and self._target_key
            and isinstance(labels, np.ndarray)
            and labels.ndim == 1
            and labels.dtype.kind in "iu"
            and len(labels)
            and 0.0 < fp < tp < 1.0
        ):
            return None
        table = self._increment_tables.get((tp, fp))
        if table is None:
            hit, miss = fusion.vision_increments(np.array([True, False]), tp, fp).tolist()
            table = np.select([self._dense == 1, self._dense == 0], [hit, miss], np.nan).astype(
                fusion.LAYER_DTYPE
            )
            if len(self._increment_tables) >= 8:
                self._increment_tables.clear()
            self._increment_tables[(tp, fp)] = table
        if not _all_below(labels, len(table)):
            return None  # an id not in the map
        increments = table.take(labels, mode="clip")
        if self._dense_has_gaps and math.isnan(float(increments.sum())):  # an id in no gap of the map
            return None
        return increments

    def _classes_of_ids(self, ids: np.ndarray) -> np.ndarray:
        """(M,) int8: 1 target, 0 another class, -1 not in the label map."""
        if self._dense is not None:
            in_table = (ids >= 0) & (ids < len(self._dense))
            return np.where(in_table, self._dense[np.where(in_table, ids, 0)], -1).astype(np.int8)
        if not len(self._ids):
            return np.full(len(ids), -1, dtype=np.int8)
        slot = np.minimum(np.searchsorted(self._ids, ids), len(self._ids) - 1)
        return np.where(self._ids[slot] == ids, self._id_classes[slot], -1).astype(np.int8)

    def _names_are_target(self, names: Sequence[str]) -> np.ndarray:
        """(K,) bool for distinct class names; a name of no class, or of none in the label map, is refused."""
        keys = [class_key(str(name)) for name in names]
        nameless = [name for name, key in zip(names, keys, strict=True) if not key]
        if nameless:
            msg = f"labels {[str(n)[:40] for n in nameless[:10]]} name no class"
            raise InvalidInput(msg, "labels")
        if self._known_keys:
            unknown = [name for name, key in zip(names, keys, strict=True) if key not in self._known_keys]
            if unknown:
                msg = f"labels {[str(n)[:40] for n in unknown[:10]]} are not in the session's label map"
                raise InvalidInput(msg, "labels")
        return np.array([key == self._target_key for key in keys], dtype=bool)

    def is_target(self, labels: Labels) -> np.ndarray:
        """(M,) bool: which labels name the target. Integer ids must be in the label map; class names must
        name a class, and one of the label map's when the session has one."""
        if not self._target_key:
            msg = "the session's target class is unknown: set target_label or send an utterance first"
            raise Conflict(msg)
        if isinstance(labels, LabelNames):
            return self._names_are_target(labels.names)[labels.codes] if len(labels) else np.zeros(0, bool)
        arr = np.asarray(labels)
        if arr.ndim != 1:
            msg = f"labels must be a flat list, got shape {arr.shape}"
            raise InvalidInput(msg, "labels")
        if arr.size == 0:
            return np.zeros(0, dtype=bool)
        if arr.dtype.kind in "iu":
            classes = self._classes_of_ids(arr.astype(np.int64, copy=False))
            if np.any(classes < 0):
                bad = arr[classes < 0]
                msg = f"label ids {np.unique(bad)[:10].tolist()} are not in the session's label map"
                raise InvalidInput(msg, "labels")
            target: np.ndarray = classes == 1
            return target
        if arr.dtype.kind == "U":
            names, inverse = np.unique(arr, return_inverse=True)
            return self._names_are_target(names.tolist())[inverse]
        msg = f"labels must be all integers (ids in the label map) or all strings, got dtype {arr.dtype}"
        raise InvalidInput(msg, "labels")

    def voxel_indices(
        self,
        n: int,
        points: np.ndarray | None,
        flat_idx: np.ndarray | None,
        max_voxels: int | None,
        voxels: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(indices inside the grid, mask of the n inputs kept) from one of points (n, 3), flat_idx (n,) or
        voxels (n, 3) integer coordinates; points and voxels outside the grid are dropped. `max_voxels`:
        the most a batch may carry (the service's `max_batch_voxels`; None: no limit)."""
        if sum(x is not None for x in (points, flat_idx, voxels)) != 1:
            msg = "give exactly one of points, flat_idx or voxels"
            raise InvalidInput(msg, "points")
        if max_voxels is not None and n > max_voxels:
            msg = f"a batch may carry at most {max_voxels} voxels, got {n}"
            raise LimitExceeded(msg, "max_batch_voxels")
        if voxels is not None:
            ijk = np.asarray(voxels)
            if ijk.shape != (n, 3) or (n and ijk.dtype.kind not in "iu"):
                msg = f"voxels must be ({n}, 3) integers to match the labels, got {ijk.shape} {ijk.dtype}"
                raise InvalidInput(msg, "voxels")
            shape = np.asarray(self.grid.shape)
            kept = np.ones(n, dtype=bool)
            # One pass first: a batch wholly inside the grid (the usual case) needs no row mask.
            if n and np.any((ijk < 0) | (ijk >= shape)):
                kept = np.all((ijk >= 0) & (ijk < shape), axis=1)
                ijk = ijk[kept]
            return self.grid.ijk_to_flat(ijk).astype(np.int64), kept
        if points is not None:
            pts = np.asarray(points, dtype=np.float64)
            if pts.shape != (n, 3):
                msg = f"points must have shape ({n}, 3) to match the labels, got {pts.shape}"
                raise InvalidInput(msg, "points")
            if not np.all(np.isfinite(pts)):
                msg = "points must be finite"
                raise InvalidInput(msg, "points")
            flat, inside = self.grid.locate(pts)
            return flat[inside], inside
        idx = np.asarray(flat_idx)
        if idx.shape != (n,) or (n and idx.dtype.kind not in "iu"):
            msg = f"flat_idx must be ({n},) integers to match the labels, got {idx.shape} {idx.dtype}"
            raise InvalidInput(msg, "flat_idx")
        if n and not _all_below(idx, self.grid.n_voxels):
            msg = f"flat_idx must lie in [0, {self.grid.n_voxels})"
            raise InvalidInput(msg, "flat_idx")
        return idx.astype(np.int64), np.ones(n, dtype=bool)

    def observation_batch(
        self,
        labels: Labels,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        max_voxels: int | None = None,
    ) -> IncrementBatch:
        """Equation (4) for labelled voxels (points, flat indices or voxel coordinates); tp/fp override the
        default model.

        Voxels of mapped look-alikes are left out: their labels are explained by the mapped object.
        """
        tp = self.sensor_model.tp if tp is None else tp
        fp = self.sensor_model.fp if fp is None else fp
        by_id = self._id_increments(labels, tp, fp)  # label ids: one table lookup
        if by_id is None:
            is_target = self.is_target(labels)
            idx, kept = self.voxel_indices(len(is_target), points, flat_idx, max_voxels, voxels)
            increments = fusion.vision_increments(is_target[kept], tp, fp)
            n_outside = int(len(kept) - kept.sum())
        else:
            idx, kept = self.voxel_indices(len(by_id), points, flat_idx, max_voxels, voxels)
            n_outside = int(len(kept) - np.count_nonzero(kept))
            increments = by_id[kept] if n_outside else by_id
        if self._look_alikes is not None:
            explained = self._explained(idx)
            if explained.any():
                idx, increments = _drop(idx, explained), _drop(increments, explained)
        return IncrementBatch(idx, increments, n_outside)

    def _explained(self, idx: np.ndarray) -> np.ndarray:
        """(M,) bool: which voxels lie in a mapped look-alike. A look-alike of a voxel or a few (an object
        smaller than a voxel: a remote, a key) is compared directly, a pass per voxel; else one lookup in
        the mask over the grid."""
        look_alikes = self._look_alikes
        assert look_alikes is not None
        if len(look_alikes) <= _FEW_LOOK_ALIKE_VOXELS:
            explained: np.ndarray = idx == look_alikes[0]
            for voxel in look_alikes[1:]:
                explained |= idx == voxel
            return explained
        mask = self._look_alike_mask
        assert mask is not None
        return mask.take(idx)

    def detection_batch(
        self,
        p_target: np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        prior: float = 0.5,
        max_voxels: int | None = None,
    ) -> IncrementBatch:
        """Equation (5) for voxels with detector probabilities p_target, computed under its `prior`."""
        p = np.asarray(p_target, dtype=np.float64).reshape(-1)
        idx, kept = self.voxel_indices(len(p), points, flat_idx, max_voxels, voxels)
        return IncrementBatch(idx, fusion.detector_increments(p[kept], prior), int(len(kept) - kept.sum()))


def _all_below(values: np.ndarray, bound: int) -> bool:
    """0 <= v < bound for every integer v, in one pass where the bound is at most the dtype's largest value
    (read as unsigned of the same width and byte order, a negative integer is then above the bound)."""
    if values.dtype.kind == "u":
        return bool(values.max() < bound)
    if bound <= np.iinfo(values.dtype).max + 1:
        return bool(values.view(values.dtype.str.replace("i", "u")).max() < bound)
    return bool(values.min() >= 0)  # every value is below the bound


def _drop(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    """values[~where]; a few dropped entries (a batch grazing a look-alike) by copying the runs between
    them, which costs a third of a boolean compress."""
    hits = np.flatnonzero(where)
    if len(hits) > 64:
        kept: np.ndarray = values[~where]
        return kept
    bounds = [-1, *hits.tolist(), len(values)]
    return np.concatenate([values[a + 1 : b] for a, b in itertools.pairwise(bounds)])


@dataclass
class Session:
    """A robot's search for one target on one scene graph: metadata plus the belief layers."""

    id: str
    robot_id: str
    scene_graph: SceneGraph
    grid: VoxelGrid
    target_label: str
    sensor_model: SensorModel
    label_map: dict[int, str]
    created_at: float
    updated_at: float
    belief: BeliefState
    _observer: ObservationModel | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ObservationModel(self.grid, self.target_label, self.label_map, self.sensor_model)  # validates

    @property
    def observer(self) -> ObservationModel:
        """Built on first use (finding the mapped look-alikes reads the scene graph)."""
        if self._observer is None:
            look_alikes = mapped_look_alikes(self.grid, self.scene_graph, self.target_label)
            self._observer = ObservationModel(
                self.grid, self.target_label, self.label_map, self.sensor_model, look_alikes
            )
        return self._observer

    def replace_scene_graph(self, scene_graph: SceneGraph) -> None:
        """Use a new scene graph for later utterances and look-alikes; stores bump the version."""
        self.scene_graph = scene_graph
        self._observer = None

    @property
    def version(self) -> int:
        return self.belief.version

    def info(self) -> SessionInfo:
        """The metadata without the scene graph or the layers (nothing large is copied)."""
        return SessionInfo(
            id=self.id,
            robot_id=self.robot_id,
            target_label=self.target_label,
            n_voxels=self.grid.n_voxels,
            created_at=self.created_at,
            updated_at=self.updated_at,
            version=self.version,
            grid=self.grid,
            sensor_model=self.sensor_model,
            label_map=dict(self.label_map),
        )

    def set_target_label(self, target_label: str) -> None:
        """Name the target class (`check_target_label`) and rebuild the observer; stores bump the version.

        Vision evidence fused before stays in the layers: it was about the previous class, if any.
        """
        check_target_label(target_label, self.label_map)
        self.target_label = target_label
        self._observer = None

    def observation_batch(
        self,
        labels: Labels,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        max_voxels: int | None = None,
    ) -> IncrementBatch:
        """`ObservationModel.observation_batch` for this session."""
        return self.observer.observation_batch(
            labels, points=points, flat_idx=flat_idx, voxels=voxels, tp=tp, fp=fp, max_voxels=max_voxels
        )

    def detection_batch(
        self,
        p_target: np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        prior: float = 0.5,
        max_voxels: int | None = None,
    ) -> IncrementBatch:
        """`ObservationModel.detection_batch` for this session."""
        return self.observer.detection_batch(
            p_target, points=points, flat_idx=flat_idx, voxels=voxels, prior=prior, max_voxels=max_voxels
        )

    def summary(
        self, *, top_k: int = DEFAULT_TOP_K, max_places: int = 10, on_margin: float = ON_MARGIN_M
    ) -> PosteriorSummary:
        return self.belief.summary(self.scene_graph, top_k=top_k, max_places=max_places, on_margin=on_margin)

    def meta(self) -> dict[str, Any]:
        """Everything but the layers, as JSON/msgpack-safe values."""
        return {
            "id": self.id,
            "robot_id": self.robot_id,
            "scene_graph": self.scene_graph.model_dump(mode="json"),
            "grid": self.grid.to_dict(),
            "target_label": self.target_label,
            "sensor_model": {"tp": self.sensor_model.tp, "fp": self.sensor_model.fp},
            "label_map": [[k, v] for k, v in sorted(self.label_map.items())],
            "limits": {
                "vis_min": self.belief.limits.vis_min,
                "vis_max": self.belief.limits.vis_max,
                "lang_span": self.belief.limits.lang_span,
            },
            "created_at": self.created_at,
            "updated_at": self.updated_at,
            "version": self.version,
        }

    @classmethod
    def from_meta(
        cls,
        meta: dict[str, Any],
        lang: np.ndarray | None = None,
        vis: np.ndarray | None = None,
        scene_graph: SceneGraph | None = None,
    ) -> Session:
        """Inverse of `meta`, with the layers (zeros if absent); `scene_graph` skips re-validating it."""
        grid = VoxelGrid.from_dict(meta["grid"])
        limits = fusion.LayerLimits(**meta["limits"])
        return cls(
            id=meta["id"],
            robot_id=meta["robot_id"],
            scene_graph=scene_graph
            if scene_graph is not None
            else SceneGraph.model_validate(meta["scene_graph"]),
            grid=grid,
            target_label=meta["target_label"],
            sensor_model=SensorModel(**meta["sensor_model"]),
            label_map={int(k): str(v) for k, v in meta["label_map"]},
            created_at=meta["created_at"],
            updated_at=meta["updated_at"],
            belief=BeliefState(grid, limits, lang, vis, meta["version"]),
        )

    def copy(self) -> Session:
        """A copy that shares the (immutable) scene graph and grid but not the layers."""
        return Session(
            self.id,
            self.robot_id,
            self.scene_graph,
            self.grid,
            self.target_label,
            self.sensor_model,
            dict(self.label_map),
            self.created_at,
            self.updated_at,
            self.belief.copy(),
        )


def new_session(
    robot_id: str,
    scene_graph: SceneGraph,
    target_label: str,
    *,
    label_map: dict[int, str] | None = None,
    sensor_model: SensorModel | None = None,
    voxel_size: float = DEFAULT_VOXEL_SIZE_M,
    margin: float = DEFAULT_MARGIN_M,
    max_voxels: int = DEFAULT_MAX_VOXELS,
    limits: fusion.LayerLimits | None = None,
    grid: VoxelGrid | None = None,
    session_id: str | None = None,
    now: float | None = None,
) -> Session:
    """A fresh session with a uniform belief on `grid`, by default `VoxelGrid.around(scene_graph, ...)`.

    `target_label` may be "" (not known yet; see the module docstring).
    """
    if not robot_id:
        msg = "robot_id must not be empty"
        raise InvalidInput(msg, "robot_id")
    if grid is None:
        grid = VoxelGrid.around(scene_graph, voxel_size=voxel_size, margin=margin, max_voxels=max_voxels)
    elif grid.n_voxels > max_voxels:
        msg = f"the grid has {grid.n_voxels} voxels, more than the limit {max_voxels}"
        raise LimitExceeded(msg, "max_grid_voxels")
    created = time.time() if now is None else now
    if not math.isfinite(created):
        msg = "creation time must be finite"
        raise InvalidInput(msg, "now")
    return Session(
        id=session_id or uuid.uuid4().hex,
        robot_id=robot_id,
        scene_graph=scene_graph,
        grid=grid,
        target_label=target_label,
        sensor_model=sensor_model or SensorModel(),
        label_map=dict(label_map or {}),
        created_at=created,
        updated_at=created,
        belief=BeliefState(grid, limits),
    )
