"""Belief summaries by (session, creation time, version, top_k): an unchanged belief is not summarised twice;
and the other views a dashboard reads of a session (its top-down mass, its utterances).

Versions are the store's, so entries stay right across replicas; an update makes a new key. A session
deleted and made again under its id restarts its versions: its creation time tells the two apart. Watched
sessions are summarised ahead of their next poll: when a session's belief was read within the last
`watch_s` seconds, `SessionService` summarises each new version in the background (one job per session at
a time; updates that land during a job make it run once more), so that a dashboard's poll finds the
summary ready instead of paying for a pass over the whole grid.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.belief.grid import VoxelGrid
from app.belief.summary import PosteriorSummary
from app.stores.events import StoredEvent


@dataclass(frozen=True)
class Belief:
    """A session's posterior summary at one version, and the target class it was computed for."""

    session_id: str
    version: int
    target_label: str  # "" = not known yet
    summary: PosteriorSummary
    created_at: float  # the session's: with its id, names the incarnation the version is of


@dataclass(frozen=True)
class TopDown:
    """A session's belief seen from above at one version: the posterior mass of each (x, y) column of
    voxels of `grid` (`app.belief.summary.column_mass`)."""

    session_id: str
    version: int
    grid: VoxelGrid
    mass: np.ndarray  # (nx, ny) float32, sums to one
    created_at: float  # the session's (`Belief.created_at`)


@dataclass(frozen=True)
class UtteranceLog:
    """A session's utterance events (`app.stores.events`) that its history still holds, oldest first;
    `complete`: the history reaches back to the session's creation (no event of any kind was dropped)."""

    session_id: str
    events: tuple[StoredEvent, ...]
    complete: bool


class SummaryCache:
    """The most recent `maxsize` summaries, and which sessions are watched with which top_k."""

    def __init__(
        self, maxsize: int = 1024, watch_s: float = 30.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.maxsize = maxsize
        self.watch_s = watch_s
        self._clock = clock
        self._items: OrderedDict[tuple[str, float, int, int], Belief] = OrderedDict()
        self._lock = threading.Lock()
        self._watched: dict[str, tuple[float, set[int]]] = {}  # session -> (last read, top_k values read)
        self._running: set[str] = set()
        self._again: set[str] = set()

    def get(self, session_id: str, created_at: float, version: int, top_k: int) -> Belief | None:
        key = (session_id, created_at, version, top_k)
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, top_k: int, belief: Belief) -> None:
        with self._lock:
            self._items[(belief.session_id, belief.created_at, belief.version, top_k)] = belief
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

    def start_job(self, session_id: str) -> list[int] | None:
        """The top_k values to summarise ahead if the session is watched and no job runs for it (a running
        job is told to run once more); None otherwise."""
        with self._lock:
            seen, top_ks = self._watched.get(session_id, (-math.inf, set()))
            if self._clock() - seen > self.watch_s:
                self._watched.pop(session_id, None)
                return None
            if session_id in self._running:
                self._again.add(session_id)
                return None
            self._running.add(session_id)
            return sorted(top_ks)

    def end_job(self, session_id: str) -> bool:
        """Whether the job must run once more (an update landed while it ran); else it is over."""
        with self._lock:
            if session_id in self._again:
                self._again.discard(session_id)
                return True
            self._running.discard(session_id)
            return False
