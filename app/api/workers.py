"""Grounding in worker processes, off the request process's interpreter lock.

One grounding is tens of milliseconds of Python-driven CPU work: the proposer's features, the MiniLM pass,
the LSM's many small torch operations. On the request process's threads it holds the interpreter lock for
most of that time, and every request that arrives meanwhile (a robot's observation batch, a dashboard's
poll) waits behind it. Worker processes each load the local models once and ground whole requests; the
request process only pickles the scene graph in and the grounding out. Parts that call an LLM endpoint stay
on the request process's threads: they wait on the network, not the CPU.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from app.api.observability import Metrics
from app.errors import ModelUnavailable
from app.grounding.hypotheses import Hypothesis
from app.grounding.sensor import Grounding
from app.scene_graph.model import SceneGraph
from app.settings import Settings

log = logging.getLogger("vlmap.workers")

#: Proposers a worker loads (the LLM one needs the network and stays in the request process).
LOCAL_PROPOSERS = frozenset({"builtin"})

# -- inside a worker process --------------------------------------------------------------------------------

_sensors = None  # the worker's `Sensors`, loaded once by `_load`


def _load(settings: Settings, parent_pid: int) -> None:
    """Worker initializer: exit with the service, tune the allocator as every `vlmap` command does, then
    load the local models."""
    global _sensors
    from app.allocator import keep_freed_buffers
    from app.api.bootstrap import build_sensors, freeze_startup_objects

    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()
    keep_freed_buffers()
    _sensors = build_sensors(settings.model_copy(update={"llm_url": None}), Metrics())
    freeze_startup_objects()


def _exit_with_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """A service killed with SIGKILL cannot stop its pool; its workers notice that they were orphaned."""
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(0)


def _ground(
    grounder: str, proposer: str, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis] | None
) -> Grounding:
    assert _sensors is not None, "the worker's initializer did not run"
    return _sensors.get(grounder, proposer).ground(scene_graph, utterance, hypotheses)


def _ready() -> bool:
    return _sensors is not None


# -- in the request process ---------------------------------------------------------------------------------


class WorkerProcesses:
    """A pool of `processes` worker processes that ground with the service's local grounders and proposers.

    A worker that dies (killed, out of memory) breaks the pool: the requests in flight fail with
    `ModelUnavailable` (503) and the next request gets a fresh pool.
    """

    def __init__(self, settings: Settings, processes: int) -> None:
        if processes < 1:
            msg = f"a grounding pool needs at least one process, got {processes}"
            raise ValueError(msg)
        self.settings = settings
        self.processes = processes
        self.grounders = frozenset([settings.grounder, *settings.grounders])
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = None

    def serves(self, grounder: str, proposer: str) -> bool:
        """Whether the workers have loaded this grounder and proposer."""
        return grounder in self.grounders and proposer in LOCAL_PROPOSERS

    def start(self) -> None:
        """Start every worker and wait until each has loaded its models (blocks: call it off the loop)."""
        pool = self._current_pool()
        # With the spawn start method the pool starts a process per job submitted while none is idle.
        for ready in [pool.submit(_ready) for _ in range(self.processes)]:
            ready.result()
        log.info("grounding workers ready", extra={"processes": self.processes})

    def _current_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=self.processes,
                    # spawn: a fork of a process with running threads (and torch's pools) is not safe.
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_load,
                    initargs=(self.settings, os.getpid()),
                )
            return self._pool

    def _discard(self, pool: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is pool:
                self._pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    async def ground(
        self,
        grounder: str,
        proposer: str,
        scene_graph: SceneGraph,
        utterance: str,
        hypotheses: Sequence[Hypothesis] | None,
    ) -> Grounding:
        """`LanguageSensor.ground` in a worker; its domain errors are raised here as they were there."""
        pool = self._current_pool()
        try:
            given = None if hypotheses is None else list(hypotheses)
            future = pool.submit(_ground, grounder, proposer, scene_graph, utterance, given)
            return await asyncio.wrap_future(future)
        except BrokenProcessPool as exc:
            self._discard(pool)
            msg = "a worker process died; the next request starts a new one"
            raise ModelUnavailable(msg) from exc

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
