"""`vlmap foxglove`: a Foxglove WebSocket server (the official SDK) that shows the service's sessions live,
on the topics of `app.foxglove`, in a process of its own.

It follows the push stream (a session's, or the fleet's of one robot or of every session the key may read):
each session gets its channels when the viewer may see it (a "created" event, or listed at start) and loses
them with its "deleted" event. The frames themselves (`GET .../recording?after=V`) are fetched only for a
session one of whose topics a viewer subscribed to (the SDK's `ServerListener.on_subscribe`), once per new
version: with no viewer connected the service only holds the idle push stream open. A first subscription
publishes the session's last scene graph, mixture and belief and its utterances so far.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener

from app.client import StreamEvent, VLMapClient, VLMapHTTPError
from app.foxglove.channels import SessionChannels
from app.foxglove.messages import Converter, Message, Topics

log = logging.getLogger("vlmap.foxglove")


@dataclass
class _Shown:
    """What the server holds for one session."""

    channels: SessionChannels
    converter: Converter | None = None
    version: int | None = None  # the last version published
    published: set[tuple[int, float]] = field(default_factory=set)  # unfused utterances already logged


class _Subscriptions(ServerListener):
    """The SDK's `ServerListener`: counts viewers' subscriptions per session and asks for a first
    publication when a session gets its first one (again after every viewer left: `take_first`)."""

    def __init__(self, wake: queue.Queue[str | None]) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._first: set[str] = set()  # sessions whose subscriptions went from none to one since published
        self._wake = wake

    @staticmethod
    def _session(channel: ChannelView) -> str | None:
        parts = channel.topic.split("/")
        return parts[2] if len(parts) == 4 and parts[1] == "vlmap" else None

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        session = self._session(channel)
        if session is not None:
            with self._lock:
                self._counts[session] += 1
                first = self._counts[session] == 1
                if first:
                    self._first.add(session)
            if first:
                self._wake.put(session)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        session = self._session(channel)
        if session is not None:
            with self._lock:
                self._counts[session] -= 1
                if self._counts[session] <= 0:
                    del self._counts[session]
                    self._first.discard(session)  # nobody left to publish to

    def watched(self, session_id: str) -> bool:
        with self._lock:
            return self._counts[session_id] > 0

    def take_first(self, session_id: str) -> bool:
        """Whether the session got a first subscription since this was last asked."""
        with self._lock:
            first = session_id in self._first
            self._first.discard(session_id)
            return first


class LiveServer:
    """The server and its sessions (module docstring); `run()` follows the push stream until stopped."""

    def __init__(
        self,
        client: VLMapClient,
        *,
        session_id: str | None = None,
        robot_id: str | None = None,
        host: str = "127.0.0.1",
        port: int = 8765,
    ) -> None:
        self.client, self.session_id, self.robot_id = client, session_id, robot_id
        self.context = foxglove.Context()
        self._wake: queue.Queue[str | None] = queue.Queue()
        self.subscriptions = _Subscriptions(self._wake)
        self._shown: dict[str, _Shown] = {}
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        self.server = foxglove.start_server(
            name="vlmap", host=host, port=port, context=self.context, server_listener=self.subscriptions
        )
        self._publisher = threading.Thread(target=self._publish_loop, name="vlmap-foxglove", daemon=True)
        self._publisher.start()

    @property
    def port(self) -> int:
        return int(self.server.port)

    # -- sessions and their channels ------------------------------------------------------------------------

    def show(self, session_id: str) -> None:
        """Advertise the session's topics (nothing is fetched until a viewer subscribes)."""
        with self._lock:
            if session_id not in self._shown:
                self._shown[session_id] = _Shown(SessionChannels(Topics(session_id), self.context))

    def forget(self, session_id: str) -> None:
        with self._lock:
            shown = self._shown.pop(session_id, None)
        if shown is not None:
            shown.channels.close()

    def list_sessions(self) -> None:
        """Advertise the sessions the stream follows that exist now."""
        if self.session_id is not None:
            self.show(str(self.client.get_session(self.session_id)["id"]))
            return
        for session in self.client.list_sessions(self.robot_id):
            self.show(str(session["id"]))

    # -- publishing -----------------------------------------------------------------------------------------

    def _publish_loop(self) -> None:
        while True:
            session_id = self._wake.get()
            if session_id is None:
                return
            try:
                self.publish(session_id)
            except (
                VLMapHTTPError,
                OSError,
            ) as exc:  # a gone session or an outage: the next event tries again
                log.warning("could not publish %s: %s", session_id, exc)
            except Exception:
                log.exception("could not publish %s", session_id)

    def publish(self, session_id: str) -> None:
        """Publish the session's frames since the last published version, if a viewer watches it."""
        with self._lock:
            shown = self._shown.get(session_id)
        if shown is None or not self.subscriptions.watched(session_id):
            return
        if self.subscriptions.take_first(session_id):
            # A viewer that comes after every earlier one left has seen nothing: start over, so that it
            # gets the last scene graph, mixture and belief and the utterances so far.
            shown.converter, shown.version, shown.published = None, None, set()
        after = None if shown.converter is None else shown.version
        try:
            body = self.client.get_recording(session_id, after)
        except VLMapHTTPError as exc:
            if exc.status == 404:
                self.forget(session_id)
                return
            raise
        first = shown.converter is None
        if shown.converter is None:
            shown.converter = Converter(Topics(session_id), float(body["voxel_size"]))
        for topic, message, log_time in self._messages(shown, body["frames"], latest_only=first):
            shown.channels.log(topic, message, log_time)

    def _messages(
        self, shown: _Shown, frames: list[dict[str, Any]], *, latest_only: bool
    ) -> Iterator[tuple[str, Message, int]]:
        """The frames' messages; `latest_only`: the last one per topic, but every utterance, all of them in
        log-time order (a viewer reads the order it receives as time: the utterances' logs first and the
        other topics' older messages after them went back in time)."""
        assert shown.converter is not None
        latest: dict[str, tuple[Message, int]] = {}
        said: list[tuple[str, Message, int]] = []
        for frame in frames:
            if frame["summary"] is None:
                key = (int(frame["version"]), float(frame["at"]))
                if key in shown.published:
                    continue
                shown.published.add(key)
            else:
                shown.version = max(shown.version or 0, int(frame["version"]))
            log_time = round(float(frame["at"]) * 1e9)
            for topic, message in shown.converter.messages(frame):
                if not latest_only:
                    yield topic, message, log_time
                elif topic == shown.channels.topics.utterances:
                    said.append((topic, message, log_time))
                else:
                    latest[topic] = (message, log_time)
        merged = [*said, *((topic, message, log_time) for topic, (message, log_time) in latest.items())]
        yield from sorted(merged, key=lambda item: item[2])

    # -- the push stream ------------------------------------------------------------------------------------

    def _events(self) -> Iterator[StreamEvent]:
        if self.session_id is not None:
            return self.client.session_events(self.session_id)
        return self.client.fleet_events(self.robot_id)

    def handle(self, event: StreamEvent) -> None:
        """One event of the push stream: new sessions shown, deleted ones forgotten, new versions fetched."""
        if event.event == "sync":
            self.list_sessions()
            with self._lock:
                sessions = list(self._shown)
            for session_id in sessions:
                self._wake.put(session_id)
            return
        session_id, kind = str(event.data["session_id"]), event.data["cause"]["kind"]
        if kind == "deleted":
            self.forget(session_id)
            return
        self.show(session_id)
        self._wake.put(session_id)

    def run(self) -> None:
        """Follow the push stream until `stop()` (or, for one session, its deletion)."""
        self.list_sessions()
        try:
            for event in self._events():
                if self._stopped.is_set():
                    return
                self.handle(event)
        except Exception:
            if not self._stopped.is_set():
                raise
            # Stopped meanwhile: the stream failed because its client was closed under it.

    def stop(self) -> None:
        self._stopped.set()
        self._wake.put(None)
        self._publisher.join(timeout=10)
        self.server.stop()
        with self._lock:
            sessions = list(self._shown)
        for session_id in sessions:
            self.forget(session_id)
