"""The push stream's delivery in one process: every stream a subscription of one `EventHub`, fed by the
store's `EventLog` (`app.stores.events`), with a bounded queue of its own.

One hub per `SessionService` listens to the store once (lazily, on the first stream) and hands each event,
in the order it arrives, to the subscriptions that want it: the session's streams, and the fleet streams
whose caller may read the event's robot (and that asked for it, if they named one). A hand-over never
waits: a subscription holding `capacity` events that its client has not taken is dropped there and then
(its connection is cut, `app.api.routes.events`), so a client that does not read costs a bounded amount
of memory and slows neither the writers nor the other streams.

Resuming (`Last-Event-ID`): a session stream replays the session's events after the id from the store's
history (`EventLog.replay`: its own stream on Redis, so from any replica); a fleet stream replays from the
hub's ring buffer of the last `fleet_history` events it saw (a replica that saw the id; every replica sees
every event). When the history does not reach back to the id, the stream starts with a `sync` event
("expired") instead, which tells the client to read the current state again; "start" opens a stream that
resumes nothing, "gap" marks events lost since (the Redis subscription was cut: a session stream replays
what it missed when its history still holds it, and says "gap" otherwise).

Guarantee: a session stream delivers each of the session's events once, in version order, across
reconnections resumed within the history (else `sync`); a fleet stream delivers each event once, in
version order per session, as this replica received them (`sync` "gap" after a cut subscription).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from app.errors import LimitExceeded, ModelUnavailable, VLMapError
from app.stores.events import EventLog, StoredEvent

log = logging.getLogger("vlmap.events")


class _Gap:
    """In a subscription's queue: events may have been lost here."""


GAP = _Gap()


@dataclass(frozen=True)
class Sync:
    """A `sync` event: read the current state now; events after it follow (`reason` in the module
    docstring); `id` resumes from here."""

    reason: Literal["start", "expired", "gap"]
    id: str | None
    fields: dict[str, Any] = field(default_factory=dict)

    @property
    def data(self) -> str:
        return json.dumps({"reason": self.reason, **self.fields}, separators=(",", ":"))


#: What a stream yields: an event of a session, or a `sync`.
Item = StoredEvent | Sync


class StreamEnded(Exception):
    """The stream is over: its session was deleted or is gone, its client was too slow, or the service is
    closing."""


class Subscription:
    """A stream's live events: at most `capacity` wait; one more and the subscription is dropped (`ended`
    set, `dropped` true) instead of waiting or growing."""

    def __init__(
        self, hub: EventHub, key: tuple[str, ...], capacity: int, accepts: Callable[[StoredEvent], bool]
    ) -> None:
        self.hub, self.key, self.capacity, self.accepts = hub, key, capacity, accepts
        self.ended = asyncio.Event()
        self.cut = asyncio.Event()  # dropped: its connection must be closed, whatever it is waiting for
        self.dropped = False
        self._items: deque[StoredEvent | _Gap] = deque()
        self._ready = asyncio.Event()

    def offer(self, item: StoredEvent | _Gap) -> None:
        if self.ended.is_set():
            return
        if isinstance(item, _Gap):
            if self._items and self._items[-1] is GAP:
                return
        elif len(self._items) >= self.capacity:
            self.dropped = True
            self.cut.set()
            self.hub.drops += 1
            log.warning(
                "dropping an event stream whose client does not read",
                extra={"stream": ":".join(self.key), "buffered_events": len(self._items)},
            )
            self.end()
            return
        self._items.append(item)
        self._ready.set()

    def end(self) -> None:
        if not self.ended.is_set():
            self._items.clear()
            self.ended.set()
            self._ready.set()
            self.hub.remove(self)

    async def get(self, timeout: float) -> StoredEvent | _Gap | None:
        """The next live item; None after `timeout` s without one, or once ended."""
        if not self._items and not self.ended.is_set():
            self._ready.clear()
            try:
                async with asyncio.timeout(timeout):
                    await self._ready.wait()
            except TimeoutError:
                return None
        if self.ended.is_set() or not self._items:
            return None
        return self._items.popleft()


class EventHub:
    """The subscriptions of one process to one store's events (module docstring); an `EventSink`."""

    def __init__(self, log: EventLog, *, capacity: int, fleet_history: int, max_streams: int) -> None:
        self.log = log
        self.capacity, self.max_streams = capacity, max_streams
        self.drops = 0  # subscriptions dropped for not reading
        self._subs: dict[tuple[str, ...], set[Subscription]] = {}
        self._open = 0
        self._fleet: deque[StoredEvent] = deque(maxlen=max(1, fleet_history))
        self._first = 0  # the position of _fleet[0] among all the events this hub has seen
        self._positions: dict[str, int] = {}  # stream id -> position, of the events in _fleet
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock: asyncio.Lock | None = None
        self._stop: Callable[[], Awaitable[None]] | None = None
        self._closing = False

    @property
    def streams(self) -> int:
        """Open subscriptions."""
        return self._open

    # -- the store's feed -----------------------------------------------------------------------------------

    async def _listening(self) -> None:
        """Listen to the store on the running loop. One loop serves a process; a test client may start a
        loop per request, and then the streams of the last one are gone with it."""
        loop = asyncio.get_running_loop()
        if self._loop is loop and self._stop is not None:
            return
        if self._loop is not loop:
            stop, self._stop = self._stop, None
            self._loop, self._lock = loop, asyncio.Lock()
            self._subs.clear()
            self._open = 0
            self.gap()
            if stop is not None:
                await stop()
        assert self._lock is not None
        async with self._lock:
            if self._stop is None:
                self._stop = await self.log.watch(self)

    def event(self, event: StoredEvent) -> None:
        if len(self._fleet) == self._fleet.maxlen:
            self._positions.pop(self._fleet[0].stream_id, None)
            self._first += 1
        self._positions[event.stream_id] = self._first + len(self._fleet)
        self._fleet.append(event)
        for sub in tuple(self._subs.get(("session", event.session_id), ())):
            sub.offer(event)
        for sub in tuple(self._subs.get(("robot", event.robot_id), ())):
            sub.offer(event)
        for sub in tuple(self._subs.get(("fleet",), ())):
            if sub.accepts(event):
                sub.offer(event)

    def gap(self) -> None:
        self._fleet.clear()
        self._positions.clear()
        for subs in tuple(self._subs.values()):
            for sub in tuple(subs):
                sub.offer(GAP)

    # -- subscriptions --------------------------------------------------------------------------------------

    def _add(self, key: tuple[str, ...], accepts: Callable[[StoredEvent], bool]) -> Subscription:
        if self._closing:
            msg = "the service is shutting down; connect to another replica"
            raise ModelUnavailable(msg)
        if self._open >= self.max_streams:
            msg = f"this replica serves {self.max_streams} event streams already; retry shortly or elsewhere"
            raise LimitExceeded(msg, limit_name="max_event_streams", retry_after_s=5.0)
        sub = Subscription(self, key, self.capacity, accepts)
        self._subs.setdefault(key, set()).add(sub)
        self._open += 1
        return sub

    def remove(self, sub: Subscription) -> None:
        subs = self._subs.get(sub.key)
        if subs is not None and sub in subs:
            subs.discard(sub)
            self._open -= 1
            if not subs:
                del self._subs[sub.key]

    async def session(self, session_id: str) -> Subscription:
        """A subscription to the session's live events, from now on."""
        await self._listening()
        return self._add(("session", session_id), lambda _: True)

    async def fleet(
        self, accepts: Callable[[StoredEvent], bool], robot_id: str | None, after: str | None
    ) -> tuple[Subscription, list[StoredEvent] | None, str | None]:
        """A subscription to every live event `accepts` takes (those of `robot_id` only, if given, which
        the caller may read), the events after the stream id `after` that it takes (None: not held), and
        the stream id of the last event seen (to resume from)."""
        await self._listening()
        if robot_id is not None:
            sub = self._add(("robot", robot_id), lambda _: True)
            wanted = accepts

            def accepts(event: StoredEvent) -> bool:
                return event.robot_id == robot_id and wanted(event)

        else:
            sub = self._add(("fleet",), accepts)
        last = next((e.stream_id for e in reversed(self._fleet) if accepts(e)), None)
        if after is None or after not in self._positions:
            return sub, None, last
        start = self._positions[after] - self._first + 1
        return sub, [e for e in itertools.islice(self._fleet, start, None) if accepts(e)], last

    def _end_all(self) -> None:
        for subs in tuple(self._subs.values()):
            for sub in tuple(subs):
                sub.end()

    def shut(self) -> None:
        """End every stream (each answer then ends as it would after `events_max_stream_s`), and open no
        more: the process is stopping."""
        self._closing = True
        self._end_all()

    async def close(self) -> None:
        """End every stream and stop listening (a later stream listens again: an app's lifespan may run
        more than once)."""
        self._end_all()
        stop, self._stop = self._stop, None
        if stop is not None:
            await stop()


class EventStream:
    """What one connection reads: `first` (a replay, or a `sync`), then the subscription's live events,
    skipping those a session stream has already had, repairing a gap, ending after a session's deletion.

    `next(timeout)` returns an item, or None when there was none for `timeout` s (time for a heartbeat;
    a session stream checks then that its session still exists), and raises `StreamEnded` at the end."""

    def __init__(
        self,
        sub: Subscription,
        first: list[Item],
        *,
        resync: Callable[[], Awaitable[Sync]],
        session: SessionFollow | None = None,
    ) -> None:
        self.sub = sub
        self._pending: deque[Item] = deque(first)
        self._resync = resync
        self._session = session
        self._over = False

    @property
    def cut(self) -> asyncio.Event:
        """Set when the stream's client was too slow: its connection must be closed now."""
        return self.sub.cut

    def close(self) -> None:
        self.sub.end()

    async def next(self, timeout: float) -> Item | None:
        follow = self._session
        while True:
            if self._pending:
                item = self._pending.popleft()
                if isinstance(item, StoredEvent) and follow is not None:
                    follow.delivered(item)
                    self._over = item.kind == "deleted"
                return item
            if self._over or self.sub.ended.is_set():
                raise StreamEnded
            got = await self.sub.get(timeout)
            if self.sub.ended.is_set():
                raise StreamEnded
            if got is None:
                if follow is not None and not await follow.alive():
                    raise StreamEnded
                return None
            if isinstance(got, _Gap):
                try:
                    replayed = await follow.replay() if follow is not None else None
                    self._pending.extend(replayed if replayed is not None else [await self._resync()])
                except VLMapError as exc:  # gone, or the store is out: the client resumes when it can
                    log.info("event stream ended at a gap", extra={"error": str(exc)})
                    raise StreamEnded from exc
                continue
            if follow is None or follow.is_new(got):
                self._pending.append(got)


class SessionFollow:
    """A session stream's position: the last event delivered, what is new after it, how to replay from it."""

    def __init__(
        self,
        log: EventLog,
        session_id: str,
        last_id: str,
        alive: Callable[[], Awaitable[bool]],
    ) -> None:
        self.log, self.session_id = log, session_id
        self.last_id, self.last_order = last_id, log.order(last_id)
        self.alive = alive

    def delivered(self, event: StoredEvent) -> None:
        self.last_id, self.last_order = event.id, event.order

    def is_new(self, event: StoredEvent) -> bool:
        return self.last_order is None or event.order > self.last_order

    async def replay(self) -> list[StoredEvent] | None:
        return await self.log.replay(self.session_id, self.last_id)

    def at(self, last_id: str) -> None:
        self.last_id, self.last_order = last_id, self.log.order(last_id)
