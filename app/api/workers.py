"""Grounding in worker processes, off the request process's interpreter lock.

One grounding is tens of milliseconds of Python-driven CPU work: the proposer's features, the MiniLM pass,
the LSM's many small torch operations. On the request process's threads it holds the interpreter lock for
most of that time, and every request that arrives meanwhile (a robot's observation batch, a dashboard's
poll) waits behind it. Worker processes each load the local models once and ground whole requests; the
request process only pickles the scene graph in and the grounding out. Parts that call an LLM endpoint stay
on the request process's threads: they wait on the network, not the CPU.

Each worker is one process at the end of one pipe, read by the event loop (`add_reader`): a request is one
write and one read on the loop's own thread. (A `ProcessPoolExecutor` moves each call and each answer
through threads of its own, whose hand-offs of the interpreter lock the loop waits on while it serves HTTP;
docs/performance.md has the measurements.)
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import pickle
import threading
import time
from collections import deque
from collections.abc import Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from app.api.observability import Metrics
from app.errors import ModelUnavailable
from app.grounding.hypotheses import Hypothesis
from app.grounding.sensor import Grounding
from app.scene_graph.model import SceneGraph
from app.settings import Settings

log = logging.getLogger("vlmap.workers")

#: Proposers a worker loads (the LLM one needs the network and stays in the request process).
LOCAL_PROPOSERS = frozenset({"builtin"})
#: The 503's message when a worker's pipe breaks.
DIED = "a worker process died; the next request starts a new one"
#: How long `close` waits for a worker to exit after its pipe is closed before it is terminated (seconds).
EXIT_WAIT_S = 5.0

# -- inside a worker process --------------------------------------------------------------------------------

_sensors = None  # the worker's `Sensors`, loaded once by `_load`


def _load(settings: Settings, parent_pid: int) -> None:
    """Exit with the service, tune the allocator as every `vlmap` command does, then load the local models."""
    global _sensors
    from app.allocator import keep_freed_buffers
    from app.api.bootstrap import build_sensors, freeze_startup_objects

    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()
    keep_freed_buffers()
    _sensors = build_sensors(settings.model_copy(update={"llm_url": None}), Metrics())
    freeze_startup_objects()


def _exit_with_parent(parent_pid: int, poll_s: float = 0.5) -> None:
    """A service killed with SIGKILL cannot stop its workers; they notice that they were orphaned."""
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(0)


def _ground(
    grounder: str, proposer: str, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis] | None
) -> Grounding:
    assert _sensors is not None, "the worker did not load its models"
    return _sensors.get(grounder, proposer).ground(scene_graph, utterance, hypotheses)


def _serve(conn: Connection, settings: Settings, parent_pid: int) -> None:
    """A worker's life: load the models, then answer each request on `conn` (a pickled tuple of
    `_ground`'s arguments, or None: "are you ready?") with a pickled (ok, grounding or exception), until
    the request process closes the pipe."""
    _load(settings, parent_pid)
    while True:
        try:
            request = conn.recv_bytes()
        except EOFError:
            return
        arguments = pickle.loads(request)
        reply: tuple[bool, Any]
        try:
            reply = (True, None if arguments is None else _ground(*arguments))
        except Exception as exc:  # domain errors are raised again in the request process
            reply = (False, exc)
        try:
            answer = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:
            answer = pickle.dumps((False, RuntimeError(f"a worker's answer could not be pickled: {exc!r}")))
        conn.send_bytes(answer)


# -- in the request process ---------------------------------------------------------------------------------


class _Worker:
    """One worker process and the request process's end of its pipe."""

    def __init__(self, settings: Settings) -> None:
        # spawn: a fork of a process with running threads (and torch's pools) is not safe.
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe(duplex=True)
        self.process: BaseProcess = context.Process(
            target=_serve, args=(child, settings, os.getpid()), name="vlmap-grounding-worker", daemon=True
        )
        self.process.start()
        child.close()

    def call_blocking(self, arguments: tuple[Any, ...] | None) -> tuple[bool, Any]:
        """One request and its answer, waiting on the calling thread (start-up)."""
        self.conn.send_bytes(pickle.dumps(arguments, protocol=pickle.HIGHEST_PROTOCOL))
        reply: tuple[bool, Any] = pickle.loads(self.conn.recv_bytes())
        return reply

    def send(self, arguments: tuple[Any, ...] | None) -> asyncio.Future[bytes]:
        """Write one request (None: "are you ready?"); the future gets the answer's bytes when the loop sees
        them arrive (or the error that reading them raised: EOFError when the worker died). Callers await it
        shielded: a cancelled request must not cancel the read of its worker's answer."""
        loop = asyncio.get_running_loop()
        answer: asyncio.Future[bytes] = loop.create_future()
        fd = self.conn.fileno()

        def readable() -> None:
            loop.remove_reader(fd)
            os.set_blocking(fd, True)  # an answer longer than the pipe's buffer arrives in parts
            try:
                answer.set_result(self.conn.recv_bytes())
            except (EOFError, OSError) as exc:
                answer.set_exception(exc)

        # uvloop's add_reader leaves the descriptor non-blocking, where a request longer than the pipe's
        # buffer would fail part-way (EAGAIN): the worker is waiting for it, so a blocking write is brief.
        os.set_blocking(fd, True)
        self.conn.send_bytes(pickle.dumps(arguments, protocol=pickle.HIGHEST_PROTOCOL))
        loop.add_reader(fd, readable)
        return answer

    def stop(self) -> None:
        """Close the pipe (the worker's loop ends), then wait for the process, terminating it if it hangs."""
        self.conn.close()
        self.process.join(EXIT_WAIT_S)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(EXIT_WAIT_S)


class WorkerProcesses:
    """`processes` worker processes that ground with the service's local grounders and proposers.

    A request takes an idle worker (or waits for one), writes to it and reads its answer on the event loop.
    A worker that dies (killed, out of memory) fails the request it was serving, or the next one sent to
    it, with `ModelUnavailable` (503), and is replaced by a new process for the next request. A request
    cancelled while its worker computes leaves the worker busy until its answer has been read.
    """

    def __init__(self, settings: Settings, processes: int) -> None:
        if processes < 1:
            msg = f"a grounding pool needs at least one process, got {processes}"
            raise ValueError(msg)
        self.settings = settings
        self.processes = processes
        self.grounders = frozenset([settings.grounder, *settings.grounders])
        # Requests take and give back workers on the event loop's thread; `start`, `close` and `pids` run on
        # others, before, after and beside them.
        self._lock = threading.Lock()
        self._idle: list[_Worker | None] = []  # None: the slot of a worker that died, refilled when taken
        self._waiting: deque[asyncio.Future[_Worker | None]] = deque()
        self._all: list[_Worker] = []

    def serves(self, grounder: str, proposer: str) -> bool:
        """Whether the workers have loaded this grounder and proposer."""
        return grounder in self.grounders and proposer in LOCAL_PROPOSERS

    def pids(self) -> list[int]:
        """The process ids of the live workers."""
        with self._lock:
            return [w.process.pid for w in self._all if w.process.pid is not None]

    def start(self) -> None:
        """Start every worker and wait until each has loaded its models (blocks: call it off the loop)."""
        workers = [_Worker(self.settings) for _ in range(self.processes)]
        with self._lock:
            self._all += workers
        for worker in workers:
            try:
                worker.call_blocking(None)
            except (EOFError, OSError) as exc:
                msg = "a grounding worker exited while loading the models"
                raise ModelUnavailable(msg) from exc
        with self._lock:
            self._idle += workers
        log.info("grounding workers ready", extra={"processes": self.processes})

    async def ground(
        self,
        grounder: str,
        proposer: str,
        scene_graph: SceneGraph,
        utterance: str,
        hypotheses: Sequence[Hypothesis] | None,
    ) -> Grounding:
        """`LanguageSensor.ground` in a worker; its domain errors are raised here as they were there."""
        worker = await self._take()
        given = None if hypotheses is None else list(hypotheses)
        try:
            answer = worker.send((grounder, proposer, scene_graph, utterance, given))
        except OSError as exc:  # the worker died while idle: its pipe is broken
            self._replace(worker)
            raise ModelUnavailable(DIED) from exc
        answer.add_done_callback(lambda done: self._finished(worker, done))
        try:
            ok, value = pickle.loads(await asyncio.shield(answer))
        except (EOFError, OSError) as exc:
            raise ModelUnavailable(DIED) from exc
        if not ok:
            raise value
        assert isinstance(value, Grounding)
        return value

    async def _take(self) -> _Worker:
        """An idle worker, waiting for one when all are busy; the slot of a dead one gets a new process."""
        if self._idle:
            slot = self._idle.pop()
        else:
            waiter: asyncio.Future[_Worker | None] = asyncio.get_running_loop().create_future()
            self._waiting.append(waiter)
            try:
                slot = await waiter
            except asyncio.CancelledError:
                if waiter.done() and not waiter.cancelled():  # handed a slot just as it was cancelled
                    self._give_back(waiter.result())
                raise
        if slot is None:
            slot = await self._new_worker()
        return slot

    async def _new_worker(self) -> _Worker:
        """A new process for a dead worker's slot, once it has loaded the models: a request larger than the
        pipe's buffer, written at once, would hold the loop until then."""
        worker = _Worker(self.settings)
        with self._lock:
            self._all.append(worker)
        ready = worker.send(None)
        try:
            await asyncio.shield(ready)
        except (EOFError, OSError) as exc:
            self._replace(worker)
            msg = "a new grounding worker exited while loading the models"
            raise ModelUnavailable(msg) from exc
        except asyncio.CancelledError:  # handed on once it has answered
            ready.add_done_callback(lambda done: self._finished(worker, done))
            raise
        return worker

    def _finished(self, worker: _Worker, answer: asyncio.Future[bytes]) -> None:
        """The worker's answer was read (or the worker died): hand the worker, or its slot, on."""
        if answer.cancelled() or answer.exception() is not None:
            self._replace(worker)
        else:
            self._give_back(worker)

    def _replace(self, dead: _Worker) -> None:
        with self._lock:
            if dead in self._all:
                self._all.remove(dead)
        dead.conn.close()
        dead.process.join(0)  # reaped if it has exited
        self._give_back(None)

    def _give_back(self, slot: _Worker | None) -> None:
        while self._waiting:
            waiter = self._waiting.popleft()
            if not waiter.done():  # a waiter whose request was cancelled is skipped
                waiter.set_result(slot)
                return
        self._idle.append(slot)

    def close(self) -> None:
        with self._lock:
            workers, self._all, self._idle = self._all, [], []
        for worker in workers:
            worker.stop()
