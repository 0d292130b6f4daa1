"""Synchronous calls of an async `SessionStore`, for tests: `StoreOps(store).detect(sid, p, flat_idx=...)`.

Every call runs the store's coroutine on an event loop of its own (`asyncio.run`), so a test may call from
many threads at once, each thread's calls on its own loops, as concurrent requests would. The updates are
the service's: each builds the change of `app.sessions.changes` the service would (an observation batch is
inline up to `INLINE_BATCH_VOXELS`, as `changes.observations` makes it) and hands it to `store.update`.

Attributes the adapter does not define are the store's (`ops._client`, `ops._key`, `ops.prefix`, ...), so
that tests of a store's internals read as before; `ops.store` is the store itself.
"""

from __future__ import annotations

import asyncio
import dataclasses
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

import numpy as np

from app.belief.session import (
    BeliefState,
    Labels,
    Session,
    SessionInfo,
    UpdateResult,
    language_log_likelihood,
)
from app.belief.summary import PosteriorSummary
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph
from app.sessions import changes
from app.sessions.changes import INLINE_BATCH_VOXELS, Caller
from app.sessions.service import summary_options
from app.stores.base import Change, Idempotency, SessionStore

T = TypeVar("T")

#: The most voxels a batch may carry here (the service passes its `max_batch_voxels`).
MAX_BATCH_VOXELS = 4_000_000


class StoreOps:
    """A `SessionStore` called synchronously (module docstring)."""

    def __init__(self, store: SessionStore, *, max_voxels: int = MAX_BATCH_VOXELS) -> None:
        self.store = store
        self.max_voxels = max_voxels

    def __getattr__(self, name: str) -> Any:  # the store's own attributes (tests of its internals)
        return getattr(self.store, name)

    @staticmethod
    def run(coro: Coroutine[Any, Any, T]) -> T:
        """Run one coroutine on an event loop of its own; return once the loop's worker threads have ended.

        A worker thread (`anyio.to_thread`) lets go of its last job (which holds the store) only after the
        loop has its result: a test that drops a store to reopen its data directory, as a crash would,
        must not find the directory still locked by a store that a finishing worker keeps alive."""
        workers: list[threading.Thread] = []

        async def call() -> T:
            try:
                return await coro
            finally:
                loop = asyncio.get_running_loop()  # anyio's worker threads name their loop
                workers.extend(t for t in threading.enumerate() if getattr(t, "loop", None) is loop)

        try:
            return asyncio.run(call())
        finally:
            for worker in workers:  # told to stop when the loop's main task ended
                worker.join()

    # -- the session record ---------------------------------------------------------------------------------

    def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        return self.run(self.store.create(session, max_per_robot=max_per_robot, idempotency=idempotency))

    def get(self, session_id: str) -> Session:
        """`load`: a consistent copy of the whole session."""
        return self.run(self.store.load(session_id))

    def head(self, session_id: str) -> SessionInfo:
        return self.run(self.store.head(session_id))

    def head_and_scene_graph(self, session_id: str) -> tuple[SessionInfo, SceneGraph]:
        return self.run(self.store.head_and_scene_graph(session_id))

    def layers(self, session_id: str) -> BeliefState:
        """The belief layers and their version, of one consistent state."""
        return self.get(session_id).belief

    def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        return self.run(self.store.list(robot_id))

    def delete(self, session_id: str, *, idempotency: Idempotency | None = None) -> None:
        self.run(self.store.delete(session_id, idempotency=idempotency))

    def purge(self) -> int:
        return self.run(self.store.purge_expired())

    def close(self) -> None:
        self.store.close()

    # -- updates --------------------------------------------------------------------------------------------

    def update(
        self, session_id: str, change: Change, *, idempotency: Idempotency | None = None
    ) -> UpdateResult:
        return self.run(self.store.update(session_id, change, idempotency=idempotency))

    def utter(
        self,
        session_id: str,
        mixture: GaussianMixture,
        *,
        names_target: str | None = None,
        caller: Caller | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse an utterance's mixture, its term computed on the session's grid first (as the service
        does)."""

        async def utter() -> UpdateResult:
            grid = (await self.store.head(session_id)).grid
            log_likelihood = language_log_likelihood(grid, mixture)
            change = changes.utterance(
                mixture, log_likelihood, grid, names_target=names_target, caller=caller
            )
            return await self.store.update(session_id, change, idempotency=idempotency)

        return self.run(utter())

    def observe(
        self,
        session_id: str,
        labels: Labels,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        caller: Caller | None = None,
        inline: bool | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse labelled voxels (`changes.labels`); inline as the service makes a batch unless told."""
        change = changes.labels(
            labels,
            points=points,
            flat_idx=flat_idx,
            voxels=voxels,
            tp=tp,
            fp=fp,
            max_voxels=self.max_voxels,
            caller=caller,
            inline=len(labels) <= INLINE_BATCH_VOXELS if inline is None else inline,
        )
        return self.update(session_id, change, idempotency=idempotency)

    def detect(
        self,
        session_id: str,
        p_target: np.ndarray | list[float],
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        prior: float = 0.5,
        caller: Caller | None = None,
        inline: bool | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse detector probabilities (`changes.detections`); inline as the service makes a batch unless
        told."""
        p = np.asarray(p_target, dtype=np.float64)
        change = changes.detections(
            p,
            points=points,
            flat_idx=flat_idx,
            voxels=voxels,
            prior=prior,
            max_voxels=self.max_voxels,
            caller=caller,
            inline=p.size <= INLINE_BATCH_VOXELS if inline is None else inline,
        )
        return self.update(session_id, change, idempotency=idempotency)

    def replace_scene_graph(
        self,
        session_id: str,
        scene_graph: SceneGraph,
        *,
        caller: Caller | None = None,
        idempotency: Idempotency | None = None,
    ) -> int:
        """The new version."""
        change = changes.scene_graph(scene_graph, caller=caller)
        return self.update(session_id, change, idempotency=idempotency).version

    def set_target(
        self,
        session_id: str,
        label: str,
        *,
        caller: Caller | None = None,
        idempotency: Idempotency | None = None,
    ) -> int:
        """The new version."""
        return self.update(session_id, changes.target(label, caller=caller), idempotency=idempotency).version

    # -- summaries ------------------------------------------------------------------------------------------

    def summary(self, session_id: str, top_k: int = 5) -> PosteriorSummary:
        """The current version's summary (its `version` set) as `SessionService` gets one from a store: the
        one some process put for this version and options, else computed from `load` and put."""

        async def summary() -> PosteriorSummary:
            info = await self.store.head(session_id)
            options = summary_options(top_k, info.created_at)
            stored = await self.store.summary_get(session_id, info.version, options)
            if stored is not None:
                return PosteriorSummary.from_dict(stored, version=info.version)
            session = await self.store.load(session_id)
            computed = session.summary(top_k=top_k)
            await self.store.summary_put(session_id, session.version, options, computed.to_dict())
            return dataclasses.replace(computed, version=session.version)

        return self.run(summary())
