"""What the routes need, built once per app: settings, metrics, the language sensors, the store, a pool."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from functools import partial
from typing import Any, TypeVar

import anyio
import anyio.to_thread
from anyio import CapacityLimiter

from app.api.auth import KeyRing, RateLimiter
from app.api.observability import Metrics
from app.api.workers import WorkerProcesses
from app.errors import InvalidInput, LimitExceeded
from app.grounding.geometric import FixedGrounder, GeometricGrounder
from app.grounding.hypotheses import Hypothesis
from app.grounding.interfaces import Grounder, HypothesisProposer
from app.grounding.lexical import LexicalProposer
from app.grounding.sensor import DEFAULT_MAX_GROUNDED, Grounding, LanguageSensor, StageObserver
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from app.stores import open_store
from app.stores.base import SessionStore

log = logging.getLogger("vlmap.services")
T = TypeVar("T")


@dataclass(frozen=True)
class Sensors:
    """The grounders and proposers this service loaded; each request picks one of each, or the defaults."""

    grounders: dict[str, Grounder]
    proposers: dict[str, HypothesisProposer]
    default: str  # grounder
    default_proposer: str = "builtin"
    observer: StageObserver | None = None
    max_grounded: int = DEFAULT_MAX_GROUNDED

    def get(self, grounder: str | None = None, proposer: str | None = None) -> LanguageSensor:
        """The language sensor made of these (loaded) parts."""
        return LanguageSensor(
            _pick(self.proposers, proposer or self.default_proposer, "options.proposer"),
            _pick(self.grounders, grounder or self.default, "options.grounder"),
            observer=self.observer,
            max_grounded=self.max_grounded,
        )


def _pick(loaded: dict[str, Any], name: str, field: str) -> Any:
    if name not in loaded:
        kind = field.split(".")[-1]
        msg = f"{kind} {name!r} is not loaded in this service; available: {sorted(loaded)}"
        raise InvalidInput(msg, field=field)
    return loaded[name]


def build_proposer(settings: Settings) -> HypothesisProposer:
    """The default proposer: the calibrated built-in one, or the uniform lexical one (no model needed)."""
    if settings.proposer == "lexical":
        return LexicalProposer(max_hypotheses=settings.max_hypotheses)
    from app.grounding.builtin import BuiltinProposer
    from app.lsm.text_encoder import default_text_encoder

    return BuiltinProposer.load(default_text_encoder())


def build_sensors(settings: Settings, metrics: Metrics) -> Sensors:
    """The grounders named in `settings.grounders`, the built-in proposer and, with an endpoint, the LLM's."""
    grounders: dict[str, Grounder] = {}
    for name in dict.fromkeys([settings.grounder, *settings.grounders]):
        if name == "geometric":
            grounders[name] = GeometricGrounder()
        elif name == "fixed":
            grounders[name] = FixedGrounder()
        elif name == "lsm":
            from app.lsm.grounder import LSMGrounder
            from app.lsm.text_encoder import default_text_encoder

            grounders[name] = LSMGrounder.load(
                settings.model_dir / "lsm", threads=settings.torch_threads, encoder=default_text_encoder()
            )
    builtin = build_proposer(settings)
    proposers: dict[str, HypothesisProposer] = {"builtin": builtin}
    if settings.llm_url:
        from app.llm.baselines import LLMEndToEndGrounder, ScaffoldedLLMGrounder
        from app.llm.client import ChatClient, LLMEndpoint
        from app.llm.proposer import LLMProposer

        endpoint = LLMEndpoint(
            settings.llm_url, settings.llm_model, settings.llm_api_key, timeout_s=settings.llm_timeout_s
        )
        client = ChatClient(endpoint)
        proposers["llm"] = LLMProposer(
            client,
            builtin,
            max_hypotheses=settings.max_hypotheses,
            on_fallback=lambda reason: metrics.llm_fallbacks.labels(reason=reason).inc(),
        )
        grounders["scaffolded-llm"] = ScaffoldedLLMGrounder(client)
        grounders["llm-e2e"] = LLMEndToEndGrounder(client)
    return Sensors(
        grounders,
        proposers,
        settings.grounder,
        observer=metrics.observe_stage,
        max_grounded=settings.max_grounded_hypotheses,
    )


class SummaryCache:
    """Belief summaries by (session, version, top_k): an unchanged belief is not summarised twice.

    Versions are global (the store's), so entries stay right across replicas; an update makes a new key.

    Watched sessions are summarised ahead of their next poll: when a session's belief was read within the
    last `watch_s` seconds, `refresh` summarises its new version on a background thread (one job per session
    at a time; updates that land during a job make it run once more), so a dashboard's poll finds the summary
    ready instead of paying for a pass over the whole grid.
    """

    def __init__(
        self, maxsize: int = 1024, watch_s: float = 30.0, clock: Callable[[], float] = time.monotonic
    ):
        self.maxsize = maxsize
        self.watch_s = watch_s
        self._clock = clock
        self._items: OrderedDict[tuple[str, int, int], Any] = OrderedDict()
        self._lock = threading.Lock()
        self._watched: dict[str, tuple[float, set[int]]] = {}  # session -> (last read, top_k values read)
        self._running: set[str] = set()
        self._again: set[str] = set()
        self._pool: ThreadPoolExecutor | None = None

    def get(self, key: tuple[str, int, int]) -> Any | None:
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key: tuple[str, int, int], value: Any) -> None:
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.maxsize:
                self._items.popitem(last=False)

    def watch(self, session_id: str, top_k: int) -> None:
        """Note that someone reads this session's summary (with this top_k)."""
        if self.watch_s <= 0:
            return
        with self._lock:
            now = self._clock()
            _, top_ks = self._watched.get(session_id, (0.0, set()))
            self._watched[session_id] = (now, top_ks | {top_k})
            if len(self._watched) > self.maxsize:  # forget sessions nobody read lately (deleted ones too)
                self._watched = {s: w for s, w in self._watched.items() if now - w[0] <= self.watch_s}

    def refresh(self, session_id: str, summarise: Callable[[int], Any]) -> bool:
        """If the session is watched, run `summarise(top_k)` for each top_k read, in the background."""
        with self._lock:
            seen, top_ks = self._watched.get(session_id, (-math.inf, set()))
            if self._clock() - seen > self.watch_s:
                self._watched.pop(session_id, None)
                return False
            if session_id in self._running:
                self._again.add(session_id)
                return True
            self._running.add(session_id)
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vlmap-summaries")
            pool = self._pool
        pool.submit(self._summarise, session_id, sorted(top_ks), summarise)
        return True

    def _summarise(self, session_id: str, top_ks: list[int], summarise: Callable[[int], Any]) -> None:
        while True:
            try:
                for top_k in top_ks:
                    summarise(top_k)
            except Exception as exc:  # e.g. the session was deleted meanwhile; the next poll will say so
                log.info("background summary of %s skipped: %s", session_id, exc)
            with self._lock:
                if session_id not in self._again:
                    self._running.discard(session_id)
                    return
                self._again.discard(session_id)

    def close(self) -> None:
        """Stop summarising: queued jobs are dropped, a running one finishes."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


@dataclass
class Services:
    settings: Settings
    metrics: Metrics
    sensors: Sensors | None = None
    store: SessionStore | None = None
    worker_processes: WorkerProcesses | None = None
    summaries: SummaryCache = field(init=False)
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
        self.summaries = SummaryCache(watch_s=s.summary_watch_s)
        self.limiter = CapacityLimiter(s.worker_threads)
        self.keyring = KeyRing.load(s.api_keys_file, s.api_keys)
        self.rate_limiter = RateLimiter(s.rate_limit_per_s, s.rate_limit_burst)
        self.decodes = CapacityLimiter(s.max_concurrent_decodes)
        self.decode_rate = RateLimiter(
            s.decode_rate_per_s, s.decode_rate_burst, "decode_rate", "binary decodes"
        )
        self.grids = CapacityLimiter(s.max_concurrent_grids)

    def open_store(self) -> SessionStore:
        """The store the settings name (the memory store replays its log from data_dir first)."""
        s = self.settings
        return open_store(
            s.store,
            data_dir=s.data_dir,
            ttl_s=s.session_ttl_s,
            mirror_mib=s.store_mirror_mib,
            idempotency_window_s=s.idempotency_window_s,
            idempotency_keys=s.idempotency_keys_per_session,
        )

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
