"""Each kind of session update as a pure function of the session's state: `Change`s for the stores.

A change computes the named delta (`app.stores.base.Delta`) an update makes from a `SessionView`, with the
fusion equations of `app.belief.fusion` (through `app.belief.session`'s observation model): the language
term of an utterance (3), the vision increments of labels (4) or detector probabilities (5), and the
metadata a scene-graph replacement or a named target changes. Whoever may write is checked against the
view's owner inside the change, so that the check and the update see the same state.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from app.belief.grid import VoxelGrid
from app.belief.session import Labels, check_target_label, mapped_look_alikes
from app.errors import Conflict
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph
from app.sessions.batch import ObservationBatch
from app.stores.base import Change, Delta, LanguageDelta, MetaDelta, SessionView, float64_mixture

#: Observation batches up to this many voxels (a camera view) are cheap enough to compute on the event
#: loop when the store holds the session in memory: the thread switches an update would take cost more
#: than its few milliseconds of numpy on a busy 2-vCPU host (docs/performance.md).
INLINE_BATCH_VOXELS = 16_384


class Caller(Protocol):
    """Who asks (`app.api.auth.Principal`): raises `Forbidden` for a robot it may not read or write."""

    def can_read(self, robot_id: str) -> bool: ...

    def require_read(self, robot_id: str) -> None: ...

    def require_write(self, robot_id: str) -> None: ...


def _writable(view: SessionView, caller: Caller | None) -> None:
    if caller is not None:
        caller.require_write(view.robot_id)


def _same_grid(view: SessionView, grid: VoxelGrid) -> None:
    """Conflict unless the session still has the grid a term was computed on (a session deleted and made
    again under its id may have another)."""
    if view.grid != grid:
        msg = "the session was replaced while the utterance was grounded; send it again"
        raise Conflict(msg)


def utterance(
    mixture: GaussianMixture,
    log_likelihood: np.ndarray,
    grid: VoxelGrid,
    *,
    names_target: str | None = None,
    target_read: str | None = None,
    caller: Caller | None = None,
) -> Change:
    """Fuse one utterance (equation (3)): its mixture's `log_likelihood` on `grid` (the session's, from
    `app.belief.session.language_log_likelihood` at the session's span; sessions made through the API all
    have the default one). `names_target` names the target class in the same
    update if the session has none yet. `target_read`: the target class the decision to fuse was made
    against, if one was (Conflict when the session's is another by now)."""
    mixture = float64_mixture(mixture)

    def compute(view: SessionView) -> Delta:
        _writable(view, caller)
        _same_grid(view, grid)
        if target_read is not None and view.target_label != target_read:
            # Another utterance named the target meantime: this one may be of another class.
            msg = "the session's target class changed while the utterance was grounded; send it again"
            raise Conflict(msg)
        meta = None
        if names_target and not view.target_label:
            check_target_label(names_target, view.label_map)
            look_alikes = mapped_look_alikes(view.grid, view.scene_graph(), names_target)
            meta = MetaDelta(target_label=names_target, look_alikes=look_alikes)
        return Delta(language=LanguageDelta(mixture, log_likelihood), meta=meta)

    return Change(compute)


def labels(
    labels: Labels,
    *,
    points: np.ndarray | None = None,
    flat_idx: np.ndarray | None = None,
    voxels: np.ndarray | None = None,
    tp: float | None = None,
    fp: float | None = None,
    max_voxels: int,
    caller: Caller | None = None,
    inline: bool = False,
) -> Change:
    """Fuse labelled voxels (equation (4)) given as exactly one of points (n, 3), flat indices (n,) or voxel
    coordinates (n, 3); points and coordinates outside the grid are counted, not fused. tp/fp override the
    session's sensor model."""

    def compute(view: SessionView) -> Delta:
        _writable(view, caller)
        where = {"points": points, "flat_idx": flat_idx, "voxels": voxels}
        return Delta(
            vision=view.observer().observation_batch(labels, tp=tp, fp=fp, max_voxels=max_voxels, **where)
        )

    return Change(compute, inline=inline)


def detections(
    p_target: np.ndarray,
    *,
    points: np.ndarray | None = None,
    flat_idx: np.ndarray | None = None,
    voxels: np.ndarray | None = None,
    prior: float = 0.5,
    max_voxels: int,
    caller: Caller | None = None,
    inline: bool = False,
) -> Change:
    """Fuse detector probabilities computed under `prior` (equation (5)); the voxels as in `labels`."""

    def compute(view: SessionView) -> Delta:
        _writable(view, caller)
        where = {"points": points, "flat_idx": flat_idx, "voxels": voxels}
        return Delta(
            vision=view.observer().detection_batch(p_target, prior=prior, max_voxels=max_voxels, **where)
        )

    return Change(compute, inline=inline)


def observations(batch: ObservationBatch, max_voxels: int, *, caller: Caller | None = None) -> Change:
    """A robot's batch of labels or detections (`labels`, `detections`), inline (`Change.inline`) up to
    `INLINE_BATCH_VOXELS`."""
    where = {"points": batch.points, "voxels": batch.voxels, "max_voxels": max_voxels, "caller": caller}
    inline = len(batch) <= INLINE_BATCH_VOXELS
    if batch.p_target is not None:
        return detections(batch.p_target, inline=inline, **where)  # type: ignore[arg-type]
    assert batch.labels is not None  # an ObservationBatch holds exactly one of labels and p_target
    return labels(batch.labels, tp=batch.tp, fp=batch.fp, inline=inline, **where)  # type: ignore[arg-type]


def scene_graph(replacement: SceneGraph, *, caller: Caller | None = None) -> Change:
    """Use a new scene graph for later utterances and look-alikes (the grid and the layers stay)."""

    def compute(view: SessionView) -> Delta:
        _writable(view, caller)
        look_alikes = mapped_look_alikes(view.grid, replacement, view.target_label)
        return Delta(meta=MetaDelta(scene_graph=replacement, look_alikes=look_alikes))

    return Change(compute)


def target(label: str, *, caller: Caller | None = None) -> Change:
    """Name the target class (`app.belief.session.check_target_label`). Vision evidence fused before stays
    in the layers: it was about the previous class, if any."""

    def compute(view: SessionView) -> Delta:
        _writable(view, caller)
        check_target_label(label, view.label_map)
        look_alikes = mapped_look_alikes(view.grid, view.scene_graph(), label)
        return Delta(meta=MetaDelta(target_label=label, look_alikes=look_alikes))

    return Change(compute)
