"""Belief events, as the stores write them: one per session version (and one per deletion or refused
utterance), each with an id that orders it within its session, kept in a bounded history per session.

An event's data is one JSON object (the `belief` event of the push stream, `app.api.routes.events`):

    {"session_id", "robot_id", "created_at", "version", "updated_at", "target_label", "cause": {...},
     "summary_url"}

built here by `event_parts` as the text before and after its version, so that a Redis script can put in
the version it commits (`app.stores.redis_scripts`). `cause.kind` says what made it: "created",
"utterance", "observations", "scene_graph", "update" (a change its caller did not describe) or "deleted".

Ids are opaque to clients. The memory store's are `<epoch>.<n>`: n counts the process's events (all
sessions), the epoch names the process, so that an id from before a restart is recognised as such. The
Redis store's are the entry ids of the session's stream (`<ms>-<n>`). Either way a later event of a
session has a greater id (`StoredEvent.order`), and `replay(session, after)` answers the events of the
session after `after` only when its history still holds all of them (None otherwise).

Live events reach a process's `EventSink` in commit order per session (`EventLog.watch`); a sink is told
`gap()` when the log may have lost some on the way (the Redis subscription was cut), so that it can replay.
"""

from __future__ import annotations

import asyncio
import json
import re
import secrets
import threading
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

#: Events a session's history holds (at least): at a camera's 10 updates a second, 10 s to resume within.
DEFAULT_HISTORY = 100

_SEQ = re.compile(r"[0-9]{1,20}")


@dataclass(frozen=True, slots=True)
class StoredEvent:
    """One event: its id, its order within its session, what stream filters read, and its JSON."""

    id: str
    order: tuple[int, int]
    session_id: str
    robot_id: str
    kind: str
    version: int
    data: str

    @property
    def stream_id(self) -> str:
        """The id the push stream gives it: "<session id>:<its id>", unique across sessions (a Redis entry
        id is unique within its session's stream only)."""
        return f"{self.session_id}:{self.id}"

    @classmethod
    def of(cls, event_id: str, order: tuple[int, int], data: str) -> StoredEvent:
        """An event from its JSON (as the Redis store reads it back)."""
        fields = json.loads(data)
        return cls(
            event_id,
            order,
            str(fields["session_id"]),
            str(fields["robot_id"]),
            str(fields["cause"]["kind"]),
            int(fields["version"]),
            data,
        )


def event_parts(
    session_id: str,
    robot_id: str,
    created_at: float,
    updated_at: float,
    target_label: str,
    cause: Mapping[str, Any],
) -> tuple[str, str]:
    """The event's JSON before and after its version (module docstring); keys in a fixed order."""
    dumps = json.dumps
    head = (
        f'{{"session_id":{dumps(session_id)},"robot_id":{dumps(robot_id)},'
        f'"created_at":{dumps(created_at)},"version":'
    )
    tail = (
        f',"updated_at":{dumps(updated_at)},"target_label":{dumps(target_label)},'
        f'"cause":{dumps(dict(cause), separators=(",", ":"))},'
        f'"summary_url":{dumps(f"/v1/sessions/{session_id}/belief")}}}'
    )
    return head, tail


def describe(cause: Callable[[Any], Mapping[str, Any]] | None, result: Any) -> Mapping[str, Any]:
    """What a change's `event` says caused it (`app.stores.base.Change.event`), or a plain update."""
    return cause(result) if cause is not None else {"kind": "update"}


class EventSink(Protocol):
    """Where a process's live events go (`app.sessions.events.EventHub`), called on its event loop."""

    def event(self, event: StoredEvent) -> None: ...

    def gap(self) -> None:
        """Events may have been lost since the last one delivered."""
        ...


class EventLog(Protocol):
    """A store's events: the per-session history and the live feed (module docstring)."""

    #: Events each session's history keeps (at least; the Redis store trims in whole stream nodes).
    history: int

    async def watch(self, sink: EventSink) -> Callable[[], Awaitable[None]]:
        """Deliver every later event to `sink` on the running event loop, in order per session, from the
        moment this returns; returns what stops it."""
        ...

    async def replay(self, session_id: str, after: str) -> list[StoredEvent] | None:
        """The session's events after the one named `after`, oldest first; None if the history no longer
        holds them all (or `after` names no event this log could have written)."""
        ...

    async def retained(self, session_id: str) -> list[StoredEvent]:
        """The events of the session that its history still holds, oldest first."""
        ...

    async def tail(self, session_id: str) -> str:
        """An id to resume the session's events from: every later event of the session is after it."""
        ...

    def order(self, event_id: str) -> tuple[int, int] | None:
        """What an id of this log is ordered by (within a session); None if it is none of this log's."""
        ...


# -- the memory store's log ---------------------------------------------------------------------------------


class _Listener:
    """A sink on an event loop: events published on any thread reach it in order, a batch per loop turn."""

    def __init__(self, loop: asyncio.AbstractEventLoop, sink: EventSink, lock: threading.Lock) -> None:
        self.loop, self.sink, self._lock = loop, sink, lock
        self.pending: list[StoredEvent] = []
        self.scheduled = False

    def push(self, event: StoredEvent) -> None:
        """Queue an event (the log's lock is held)."""
        self.pending.append(event)
        if not self.scheduled:
            self.scheduled = True
            try:
                self.loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # the loop is closed: nobody listens there any more
                self.pending.clear()

    def _drain(self) -> None:
        with self._lock:
            events, self.pending, self.scheduled = self.pending, [], False
        for event in events:
            self.sink.event(event)


class _History:
    """A session's last events, and the order below which events of the session may have been forgotten."""

    __slots__ = ("events", "forgotten")

    def __init__(self, history: int, forgotten: tuple[int, int]) -> None:
        self.events: deque[StoredEvent] = deque(maxlen=max(1, history))
        self.forgotten = forgotten


class MemoryEventLog:
    """`EventLog` of one process (`MemorySessionStore`): ids `<epoch>.<n>`; the store publishes each event
    while it holds the session's lock, so that they are numbered in commit order."""

    def __init__(self, history: int = DEFAULT_HISTORY) -> None:
        self.history = history
        self.epoch = secrets.token_hex(4)
        self._seq = 0
        self._lock = threading.Lock()
        self._sessions: dict[str, _History] = {}
        self._listeners: list[_Listener] = []

    def publish(
        self,
        session_id: str,
        robot_id: str,
        created_at: float,
        version: int,
        updated_at: float,
        target_label: str,
        cause: Mapping[str, Any],
        *,
        last: bool = False,
    ) -> StoredEvent:
        """Number the event, keep it in the session's history and hand it to the listeners; `last`: the
        session is gone, and its history with it."""
        head, tail = event_parts(session_id, robot_id, created_at, updated_at, target_label, cause)
        data = f"{head}{version}{tail}"
        with self._lock:
            self._seq += 1
            kind, order = str(cause["kind"]), (self._seq, 0)
            event = StoredEvent(f"{self.epoch}.{self._seq}", order, session_id, robot_id, kind, version, data)
            history = self._sessions.get(session_id)
            if history is None:
                history = self._sessions[session_id] = _History(self.history, (self._seq - 1, 0))
            if len(history.events) == history.events.maxlen:
                history.forgotten = history.events[0].order
            history.events.append(event)
            if last:
                del self._sessions[session_id]
            for listener in self._listeners:
                listener.push(event)
        return event

    async def watch(self, sink: EventSink) -> Callable[[], Awaitable[None]]:
        listener = _Listener(asyncio.get_running_loop(), sink, self._lock)
        with self._lock:
            self._listeners.append(listener)

        async def stop() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return stop

    def order(self, event_id: str) -> tuple[int, int] | None:
        epoch, _, seq = event_id.partition(".")
        if epoch != self.epoch or not _SEQ.fullmatch(seq):
            return None
        return (int(seq), 0)

    def forget(self, session_id: str) -> None:
        """Drop a session's history without an event: it expired (a session made again under its id must
        not inherit it)."""
        with self._lock:
            self._sessions.pop(session_id, None)

    async def replay(self, session_id: str, after: str) -> list[StoredEvent] | None:
        order = self.order(after)
        if order is None:
            return None
        with self._lock:
            if order > (self._seq, 0):  # past the newest event: no id this log gave (following it skips all)
                return None
            history = self._sessions.get(session_id)
            if history is None:  # no event of the session since this process started (or it is gone)
                return []
            if order < history.forgotten:
                return None
            return [event for event in history.events if event.order > order]

    async def retained(self, session_id: str) -> list[StoredEvent]:
        with self._lock:
            history = self._sessions.get(session_id)
            return list(history.events) if history is not None else []

    async def tail(self, session_id: str) -> str:
        with self._lock:
            return f"{self.epoch}.{self._seq}"
