"""What the routes need, built once per app: settings, metrics, the language sensors, the store, the session
use-cases, the worker threads and processes, and the limits on costly work."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from functools import partial
from typing import Any, TypeVar

import anyio
import anyio.to_thread
from anyio import CapacityLimiter

from app.api.auth import KeyRing, RateLimiter
from app.api.bootstrap import Sensors
from app.api.observability import Metrics
from app.api.workers import WorkerProcesses
from app.errors import LimitExceeded
from app.grounding.hypotheses import Hypothesis
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.model import SceneGraph
from app.sessions import SessionService
from app.settings import Settings
from app.stores.base import SessionStore

T = TypeVar("T")


@dataclass
class Services:
    settings: Settings
    metrics: Metrics
    sensors: Sensors | None = None
    store: SessionStore | None = None
    worker_processes: WorkerProcesses | None = None
    sessions: SessionService | None = None
    startup_error: str | None = None  # why a start-up in the background failed (the service then stops)
    limiter: CapacityLimiter = field(init=False)
    keyring: KeyRing = field(init=False)
    rate_limiter: RateLimiter = field(init=False)
    # Costly work of its own kinds, each behind its own limit: Spark-DSG binary decodes (a child process
    # each) and whole-grid downloads (tens of bytes per voxel while encoded).
    decodes: CapacityLimiter = field(init=False)
    decode_rate: RateLimiter = field(init=False)
    grids: CapacityLimiter = field(init=False)

    def __post_init__(self) -> None:
        s = self.settings
        self.limiter = CapacityLimiter(s.worker_threads)
        self.keyring = KeyRing.load(s.api_keys_file, s.api_keys)
        self.rate_limiter = RateLimiter(s.rate_limit_per_s, s.rate_limit_burst)
        self.decodes = CapacityLimiter(s.max_concurrent_decodes)
        self.decode_rate = RateLimiter(
            s.decode_rate_per_s, s.decode_rate_burst, "decode_rate", "binary decodes"
        )
        self.grids = CapacityLimiter(s.max_concurrent_grids)
        if self.store is not None:
            self.use_store(self.store)

    def use_store(self, store: SessionStore) -> None:
        """Serve sessions from `store`."""
        self.store = store
        self.sessions = SessionService(store, self.settings, self.run)

    async def take_slot(self, limiter: CapacityLimiter, limit_name: str, what: str) -> Callable[[], None]:
        """Take one of `limiter`'s slots, waiting up to `busy_wait_s` for one (LimitExceeded, a 429 with
        Retry-After, when none frees up in time); returns what gives it back (from any task of the loop: a
        streamed answer gives it back when its last chunk is sent)."""
        borrower = object()
        try:
            limiter.acquire_on_behalf_of_nowait(borrower)
        except anyio.WouldBlock:
            with anyio.move_on_after(self.settings.busy_wait_s) as waited:
                await limiter.acquire_on_behalf_of(borrower)
            if waited.cancelled_caught:
                msg = f"all {limiter.total_tokens:g} slots for {what} are busy; retry shortly"
                raise LimitExceeded(msg, limit_name=limit_name, retry_after_s=1.0) from None
        return partial(limiter.release_on_behalf_of, borrower)

    async def with_slot(
        self,
        limiter: CapacityLimiter,
        limit_name: str,
        what: str,
        start: Callable[[Callable[[], None]], Awaitable[T]],
    ) -> T:
        """`start(release)` holding one of `limiter`'s slots (`take_slot`); what it starts gives the slot
        back by calling `release` (a streamed answer, after its last chunk), or it is given back at once
        if `start` fails."""
        release = await self.take_slot(limiter, limit_name, what)
        try:
            return await start(release)
        except BaseException:
            release()
            raise

    @asynccontextmanager
    async def slot(self, limiter: CapacityLimiter, limit_name: str, what: str) -> AsyncIterator[None]:
        """Hold one of `limiter`'s slots while the block runs (`take_slot`)."""
        release = await self.take_slot(limiter, limit_name, what)
        try:
            yield
        finally:
            release()

    async def run(self, func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run CPU-bound work in the worker pool so the event loop keeps serving other requests."""
        return await anyio.to_thread.run_sync(partial(func, *args, **kwargs), limiter=self.limiter)

    async def ground(
        self,
        sensors: Sensors,
        grounder: str | None,
        proposer: str | None,
        scene_graph: SceneGraph,
        utterance: str,
        hypotheses: Sequence[Hypothesis] | None = None,
    ) -> tuple[Grounding, LanguageSensor]:
        """Ground with the named parts (the defaults when None): in a worker process when one has them
        loaded, else on a worker thread. Returns the grounding and the sensor that names its model."""
        sensor = sensors.get(grounder, proposer)  # an unknown name is the caller's error, wherever it runs
        grounder, proposer = grounder or sensors.default, proposer or sensors.default_proposer
        workers = self.worker_processes
        if workers is None or not workers.serves(grounder, proposer):
            return await self.run(sensor.ground, scene_graph, utterance, hypotheses), sensor
        result = await workers.ground(grounder, proposer, scene_graph, utterance, hypotheses)
        for stage, ms in result.timings_ms.items():  # the worker's own metrics stay in the worker
            self.metrics.observe_stage(stage, ms / 1000.0)
        return result, sensor
