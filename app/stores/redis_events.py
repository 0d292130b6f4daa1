"""The Redis store's events (`app.stores.events`): a stream per session, and a channel that every replica
listens to.

`<prefix>:s:{S}:events` (a stream in the session's hash tag, so in its cluster slot) gets one entry per
version, written by the same script call that commits the version (`app.stores.redis_scripts`), so it
holds every version exactly once and in order; it is trimmed to about `history` entries (Redis trims whole
stream nodes: up to 100 more stay) and expires with the session (a minute after its deletion). The same
script publishes the entry ("<id> <JSON>") on `<prefix>:events`: each replica keeps one subscription
(`watch`) and hands what arrives to its `EventSink`. A publish is atomic with its commit, so a crash
loses none; what a cut subscription misses is told to the sink as a gap, and a session's stream is then
replayed from its history. On a cluster the subscription is to the node the URL names (every node relays
every publish); `replay` and `tail` read the session's own slot.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import Awaitable, Callable
from typing import Any

from app.errors import StoreUnavailable
from app.stores.events import DEFAULT_HISTORY, EventSink, StoredEvent

log = logging.getLogger(__name__)

_ENTRY_ID = re.compile(r"(\d{1,20})-(\d{1,20})")
_ID_PART_END = 2**64
_LAST_ID = (_ID_PART_END - 1, _ID_PART_END - 1)
#: How long a new subscription may take to be confirmed before a stream is refused (seconds).
_SUBSCRIBE_WAIT_S = 5.0
#: Pause before the subscription connects again after losing Redis (seconds; doubled up to the last).
_RECONNECT_S = (0.05, 2.0)
#: How long a deleted session's events stream stays (ms): what a gap's replay may still need.
DELETED_STREAM_MS = 60_000


def entry_order(entry_id: str) -> tuple[int, int] | None:
    """A stream entry id as the pair it is ordered by; None if it is not one. Redis's ids are two 64-bit
    parts, and the largest has nothing after it (an exclusive range from it is refused): neither is one."""
    match = _ENTRY_ID.fullmatch(entry_id)
    if not match:
        return None
    order = (int(match[1]), int(match[2]))
    return order if max(order) < _ID_PART_END and order != _LAST_ID else None


def parse_message(payload: bytes) -> StoredEvent:
    """A published "<id> <JSON>"."""
    text = payload.decode()
    entry_id, _, data = text.partition(" ")
    order = entry_order(entry_id)
    if order is None:
        msg = f"not an events message: {text[:80]!r}"
        raise ValueError(msg)
    return StoredEvent.of(entry_id, order, data)


class _Subscription:
    """One replica's subscription on one event loop: reconnects until stopped, telling the sink of a gap
    each time it had to."""

    def __init__(self, url: str, channel: str, sink: EventSink) -> None:
        self.url, self.channel, self.sink = url, channel, sink
        self.ready = asyncio.Event()
        self.task: asyncio.Task[None] | None = None

    async def run(self) -> None:
        import redis.asyncio
        from redis.exceptions import RedisError

        pause, connected_once = _RECONNECT_S[0], False
        while True:
            client: Any = redis.asyncio.Redis.from_url(
                self.url, socket_connect_timeout=_SUBSCRIBE_WAIT_S, socket_keepalive=True
            )
            try:
                async with client.pubsub() as pubsub:
                    await pubsub.subscribe(self.channel)
                    while True:  # the confirmation: from here on every publish reaches us
                        message = await pubsub.get_message(timeout=_SUBSCRIBE_WAIT_S)
                        if message is not None and message["type"] == "subscribe":
                            break
                    if connected_once:
                        self.sink.gap()
                    connected_once, pause = True, _RECONNECT_S[0]
                    self.ready.set()
                    while True:
                        message = await pubsub.get_message(timeout=None)
                        if message is not None and message["type"] == "message":
                            self._deliver(message["data"])
            except (RedisError, OSError) as exc:
                self.ready.clear()
                log.warning("events subscription lost; reconnecting", extra={"error": str(exc)})
            finally:
                with contextlib.suppress(RedisError, OSError):
                    await client.aclose()
            await asyncio.sleep(pause)
            pause = min(2 * pause, _RECONNECT_S[1])

    def _deliver(self, payload: bytes) -> None:
        try:
            event = parse_message(payload)
        except (ValueError, KeyError, TypeError) as exc:  # not ours: another writer on the channel
            log.warning("events message ignored", extra={"error": str(exc)})
            return
        self.sink.event(event)


class RedisEventLog:
    """`EventLog` of a `RedisSessionStore` (module docstring). `key(session_id)` names a session's stream,
    `client()` gives the running loop's redis.asyncio client."""

    def __init__(
        self,
        url: str,
        channel: str,
        key: Callable[[str], str],
        client: Callable[[], Awaitable[Any]],
    ) -> None:
        self.history = DEFAULT_HISTORY
        self.url, self.channel = url, channel
        self._key, self._client = key, client

    async def watch(self, sink: EventSink) -> Callable[[], Awaitable[None]]:
        subscription = _Subscription(self.url, self.channel, sink)
        loop = asyncio.get_running_loop()
        task = subscription.task = loop.create_task(subscription.run(), name="vlmap-events-subscription")
        try:
            await asyncio.wait_for(subscription.ready.wait(), _SUBSCRIBE_WAIT_S)
        except TimeoutError:
            task.cancel()
            wait = f"{_SUBSCRIBE_WAIT_S:g} s"
            msg = f"the session store (Redis) did not confirm the events subscription within {wait}"
            raise StoreUnavailable(msg) from None

        async def stop() -> None:
            if asyncio.get_running_loop() is loop:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            elif not loop.is_closed():
                loop.call_soon_threadsafe(task.cancel)

        return stop

    async def replay(self, session_id: str, after: str) -> list[StoredEvent] | None:
        from redis.exceptions import RedisError, ResponseError

        order = entry_order(after)
        if order is None:
            return None
        key = self._key(session_id)
        try:
            client = await self._client()
            entries = await client.xrange(key, f"({after}", "+")
            try:  # read after the entries: if nothing after `after` was trimmed by now, none was before
                info = await client.xinfo_stream(key)
            except ResponseError:  # no stream (a session from before events): nothing to replay
                return [] if order == (0, 0) else None
        except RedisError as exc:
            msg = f"the session store (Redis) is unavailable: {type(exc).__name__}: {exc}"
            raise StoreUnavailable(msg) from exc
        newest = entry_order(info["last-generated-id"].decode())
        if newest is None or order > newest:  # no id this stream gave: following it would skip every event
            return None
        first = entry_order(info["first-entry"][0].decode()) if info.get("first-entry") else None
        never_trimmed = int(info["entries-added"]) == int(info["length"])
        if not (never_trimmed and order == (0, 0)) and (first is None or order < first):
            return None
        return [self._event(raw_id, fields) for raw_id, fields in entries]

    async def retained(self, session_id: str) -> list[StoredEvent]:
        from redis.exceptions import RedisError

        try:
            client = await self._client()
            entries = await client.xrange(self._key(session_id), "-", "+")
        except RedisError as exc:
            msg = f"the session store (Redis) is unavailable: {type(exc).__name__}: {exc}"
            raise StoreUnavailable(msg) from exc
        return [self._event(raw_id, fields) for raw_id, fields in entries]

    @staticmethod
    def _event(raw_id: bytes, fields: dict[bytes, bytes]) -> StoredEvent:
        entry_id = raw_id.decode()
        return StoredEvent.of(entry_id, entry_order(entry_id) or (0, 0), fields[b"e"].decode())

    def order(self, event_id: str) -> tuple[int, int] | None:
        return entry_order(event_id)

    async def tail(self, session_id: str) -> str:
        from redis.exceptions import RedisError

        try:
            client = await self._client()
            last = await client.xrevrange(self._key(session_id), "+", "-", count=1)
        except RedisError as exc:
            msg = f"the session store (Redis) is unavailable: {type(exc).__name__}: {exc}"
            raise StoreUnavailable(msg) from exc
        return str(last[0][0].decode()) if last else "0-0"
