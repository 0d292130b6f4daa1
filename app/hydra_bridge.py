"""`vlmap hydra-bridge`: keep a session's scene graph equal to the one a Hydra publisher streams.

Hydra publishes its scene graph over ZMQ with spark_dsg's `DsgSender`: PUB/SUB of whole
``DynamicSceneGraph.to_binary()`` messages. The bridge subscribes as `spark_dsg.zmq.DsgReceiver` does
(conflated to the newest message; the first read with ``from_binary``, each later one applied with
``update_from_binary``, which also drops the nodes a message no longer holds) and PUTs the graph to
``/v1/sessions/{id}/scene-graph`` as a Spark-DSG binary body when its objects or regions changed:

- What changed is judged on the normalised `SceneGraph` (the service's own reader), by id, not on bytes:
  Hydra re-sends its graph with new places, mesh and timestamps while no object or room moved.
- At most `max_rate` PUTs a second: a change that comes sooner waits and is replaced by any newer one (the
  newest graph wins), and a graph whose objects and regions equal what the service holds is not sent.
- A PUT that fails (the service restarting or refusing: no connection, a timeout, a 429 or 5xx) is retried
  with the newest graph after an exponential backoff capped at `max_backoff_s`. A graph the service rejects
  (a 4xx such as a 422 for too many objects) is logged and not sent again; a key that is refused or a
  session that is gone (401, 403, 404) ends the bridge, since no retry can mend either.
- A message that does not decode is logged and dropped, keeping the last good graph: each message is applied
  to a copy. It is decoded in this process, not in a sandbox as the service decodes: the publisher is the
  robot's own Hydra. The service's cheap check of the opening bytes still keeps random bytes from the
  decoder, and the service decodes what the bridge sends in its sandbox.
- A publisher that restarts: the SUB socket reconnects by itself, heartbeats notice a publisher that went
  away without closing its connection, and the restarted publisher's first message is a whole graph, which
  ``update_from_binary`` applies like any other.

`Change` and `SendPolicy` decide what to send and when, without I/O (time is passed in); `GraphFeed` applies
messages; `HydraBridge.run` is the loop.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import tempfile
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import httpx
import spark_dsg
import zmq

from app.client import VLMapClient, VLMapHTTPError, read_api_key
from app.errors import InvalidInput
from app.scene_graph.hydra import check_binary_prefix, parse_spark_dsg_json
from app.scene_graph.model import SceneGraph

log = logging.getLogger(__name__)

#: Answers after which the bridge stops: no retry mends a refused key or a deleted session.
FATAL_STATUSES = frozenset({401, 403, 404})
#: Answers after which the same graph may be accepted later (anything else refuses the graph itself).
RETRIED_STATUSES = frozenset({408, 409, 425, 429}) | frozenset(range(500, 600))
#: The first retry's delay (seconds); each further failure doubles it, up to `max_backoff_s`.
FIRST_BACKOFF_S = 0.5
#: Longest wait for a message before the loop looks at its stop flag again (milliseconds).
POLL_MS = 200
# ZMQ heartbeats: a publisher silent for this long after a ping is taken as gone and connected to again.
_HEARTBEAT_IVL_MS = 1000
_HEARTBEAT_TIMEOUT_MS = 3000
_RECONNECT_IVL_MAX_MS = 5000


class BadMessage(Exception):
    """A message that is not a Spark-DSG graph (or update) that this bridge can use."""


class BridgeStopped(Exception):
    """The service refused the bridge for good (its key, or the session is gone)."""


# --- what changed ---------------------------------------------------------------------------------------


class _Identified(Protocol):
    @property
    def id(self) -> str: ...


@dataclass(frozen=True)
class Diff:
    """Ids added, removed and changed (any field) from one list of objects or regions to another."""

    added: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    changed: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.added or self.removed or self.changed)

    def __str__(self) -> str:
        if not self:
            return "unchanged"
        parts = zip(("added", "removed", "changed"), (self.added, self.removed, self.changed), strict=True)
        return ", ".join(f"{len(ids)} {what}" for what, ids in parts if ids)


def diff(old: Sequence[_Identified], new: Sequence[_Identified]) -> Diff:
    before, after = {item.id: item for item in old}, {item.id: item for item in new}
    return Diff(
        added=tuple(i for i in after if i not in before),
        removed=tuple(i for i in before if i not in after),
        changed=tuple(i for i, item in after.items() if i in before and before[i] != item),
    )


@dataclass(frozen=True)
class Change:
    """How one scene graph's objects and regions differ from another's (the order of the lists aside)."""

    objects: Diff
    regions: Diff

    @classmethod
    def between(cls, old: SceneGraph | None, new: SceneGraph) -> Change:
        if old is None:
            return cls(diff([], new.objects), diff([], new.regions))
        return cls(diff(old.objects, new.objects), diff(old.regions, new.regions))

    def __bool__(self) -> bool:
        return bool(self.objects or self.regions)

    def __str__(self) -> str:
        return f"objects {self.objects}; regions {self.regions}"


# --- when to send ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Snapshot:
    """One received graph: its normalised form (compared) and its binary (the PUT's body). Retries of it
    carry its Idempotency-Key, so that a PUT whose answer was lost is applied once."""

    scene_graph: SceneGraph
    payload: bytes
    key: str = field(default_factory=lambda: uuid.uuid4().hex)


@dataclass
class SendPolicy:
    """Which graph to PUT and when: the newest one that differs from what the service holds, at most once
    per `min_interval_s`, after a capped exponential backoff once a PUT failed."""

    min_interval_s: float
    max_backoff_s: float
    #: The last graph the service acknowledged (None before the first, or once a PUT failed and what the
    #: service holds is unknown), and the last one it refused.
    acknowledged: SceneGraph | None = None
    refused: SceneGraph | None = None
    pending: Snapshot | None = None
    #: Earliest time (the clock passed in) of the next PUT.
    not_before: float = -math.inf
    failures: int = 0

    def offer(self, snapshot: Snapshot) -> Change | None:
        """Take the newest graph; its change from what the service holds, or None when there is none to send
        (then any older graph waiting is dropped too: the newest wins). While what the service holds is
        unknown (before the first PUT, after a failed one) every graph is sent, the empty one included."""
        change = Change.between(self.acknowledged, snapshot.scene_graph)
        known = self.acknowledged is not None
        unsendable = self.refused is not None and not Change.between(self.refused, snapshot.scene_graph)
        if self.pending is not None and not Change.between(self.pending.scene_graph, snapshot.scene_graph):
            # The graph waiting (maybe for the retry of a PUT whose answer was lost) came again: it keeps its
            # Idempotency-Key, so that the service applies it once.
            snapshot = self.pending
        self.pending = snapshot if (change or not known) and not unsendable else None
        return change if self.pending is not None else None

    def due(self, now: float) -> Snapshot | None:
        """The graph to PUT now, if any."""
        return self.pending if self.pending is not None and now >= self.not_before else None

    def wait_s(self, now: float) -> float | None:
        """Seconds until a PUT is due; None while nothing waits to be sent."""
        return None if self.pending is None else max(0.0, self.not_before - now)

    def sent(self, snapshot: Snapshot, now: float) -> None:
        self.acknowledged, self.pending, self.failures = snapshot.scene_graph, None, 0
        self.not_before = now + self.min_interval_s

    def rejected(self, snapshot: Snapshot, now: float) -> None:
        """The service refused this graph itself: not sent again (a later, different one is)."""
        self.refused, self.pending, self.failures = snapshot.scene_graph, None, 0
        self.not_before = now + self.min_interval_s

    def failed(self, now: float) -> float:
        """A PUT failed for a reason that may pass: the delay (seconds) before the next try."""
        # A timeout or a 5xx may come after the service applied the graph: what it holds is no longer
        # known, so the next graph is sent even if it equals the last acknowledged one.
        self.acknowledged = None
        delay = max(self.min_interval_s, min(self.max_backoff_s, FIRST_BACKOFF_S * 2.0**self.failures))
        self.failures += 1
        self.not_before = now + delay
        return delay


# --- the received graph ---------------------------------------------------------------------------------


class GraphFeed:
    """The graph as `spark_dsg.zmq.DsgReceiver` keeps it, except that a message that fails leaves it as it
    was (DsgReceiver applies an update in place)."""

    def __init__(self) -> None:
        self.graph: Any = None  # a spark_dsg.DynamicSceneGraph once a message decoded

    def apply(self, message: bytes) -> Snapshot:
        """Apply one message; the graph it makes, normalised. BadMessage (the graph as it was) if it fails."""
        try:
            check_binary_prefix(message)  # random bytes can make spark_dsg allocate gigabytes
        except InvalidInput as exc:
            raise BadMessage(str(exc)) from exc
        try:
            if self.graph is None:
                graph = spark_dsg.DynamicSceneGraph.from_binary(message)
            else:
                graph = self.graph.clone()
                graph.update_from_binary(message)
        except Exception as exc:  # the bindings raise ValueError, or whatever a malformed buffer provokes
            msg = f"not a Spark-DSG graph ({len(message)} bytes): {str(exc)[:300]}"
            raise BadMessage(msg) from exc
        snapshot = normalised(graph)
        self.graph = graph
        return snapshot


def normalised(graph: Any) -> Snapshot:
    """A spark_dsg graph as the service reads it: saved as Spark-DSG JSON, then read by its reader."""
    with tempfile.TemporaryDirectory(prefix="vlmap-bridge-") as tmp:
        path = Path(tmp) / "graph.json"
        graph.save(str(path), include_mesh=False)
        document = json.loads(path.read_text(encoding="utf-8"))
    try:
        scene_graph = parse_spark_dsg_json(document)
    except InvalidInput as exc:
        msg = f"the graph does not normalise: {exc}"
        raise BadMessage(msg) from exc
    return Snapshot(scene_graph, bytes(graph.to_binary(include_mesh=False)))


# --- the loop -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BridgeConfig:
    zmq_url: str
    url: str
    session_id: str
    api_key: str | None = None
    max_rate: float = 1.0
    max_backoff_s: float = 30.0
    timeout_s: float = 30.0


def subscribe(context: zmq.Context[zmq.Socket[bytes]], url: str) -> zmq.Socket[bytes]:
    """A SUB socket on a DsgSender's URL, set up as DsgReceiver's (all topics, the newest message only:
    each is a whole graph), with heartbeats and a cap on the reconnection backoff."""
    socket = context.socket(zmq.SUB)
    socket.setsockopt(zmq.CONFLATE, 1)
    socket.setsockopt(zmq.HEARTBEAT_IVL, _HEARTBEAT_IVL_MS)
    socket.setsockopt(zmq.HEARTBEAT_TIMEOUT, _HEARTBEAT_TIMEOUT_MS)
    socket.setsockopt(zmq.RECONNECT_IVL_MAX, _RECONNECT_IVL_MAX_MS)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.SUBSCRIBE, b"")
    socket.connect(url)
    return socket


class HydraBridge:
    """The loop: read messages, PUT what `SendPolicy` says, until `stop` is set (or BridgeStopped).
    `handled`, `bad_messages` and `puts` count what it did (for logs and tests)."""

    def __init__(self, config: BridgeConfig) -> None:
        if not config.max_rate > 0:
            msg = f"max_rate must be above 0, got {config.max_rate}"
            raise ValueError(msg)
        self.config = config
        self.feed = GraphFeed()
        self.policy = SendPolicy(min_interval_s=1.0 / config.max_rate, max_backoff_s=config.max_backoff_s)
        self.handled = self.bad_messages = self.puts = 0

    def run(self, stop: threading.Event) -> None:
        config = self.config
        context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        socket = subscribe(context, config.zmq_url)
        # The bridge retries itself, so that a retry sends the newest graph rather than the one that failed.
        client = VLMapClient(config.url, api_key=config.api_key, timeout_s=config.timeout_s, retries=0)
        log.info("bridging %s to session %s at %s", config.zmq_url, config.session_id, config.url)
        try:
            while not stop.is_set():
                wait = self.policy.wait_s(time.monotonic())
                timeout_ms = POLL_MS if wait is None else min(POLL_MS, math.ceil(wait * 1000))
                if socket.poll(timeout_ms):
                    self._receive(socket.recv())
                snapshot = self.policy.due(time.monotonic())
                if snapshot is not None:
                    self._put(client, snapshot)
        finally:
            client.close()
            socket.close()
            context.term()

    def _receive(self, message: bytes) -> None:
        try:
            snapshot = self.feed.apply(message)
        except BadMessage as exc:
            self.bad_messages += 1
            log.error("dropped a message, keeping the last good graph: %s", exc)
        else:
            change = self.policy.offer(snapshot)
            log.debug("graph received: %s", "unchanged" if change is None else change)
        self.handled += 1

    def _put(self, client: VLMapClient, snapshot: Snapshot) -> None:
        session_id = self.config.session_id
        try:
            session = client.replace_scene_graph(session_id, snapshot.payload, idempotency_key=snapshot.key)
        except VLMapHTTPError as exc:
            if exc.status in FATAL_STATUSES:
                raise BridgeStopped(str(exc)) from exc
            if exc.status not in RETRIED_STATUSES:
                self.policy.rejected(snapshot, time.monotonic())
                log.error("the service refused this scene graph, waiting for another: %s", exc)
                return
            delay = self.policy.failed(time.monotonic())
            log.warning("PUT failed (%s); retrying in %.1f s", exc, delay)
        except httpx.TransportError as exc:
            delay = self.policy.failed(time.monotonic())
            log.warning("cannot reach %s (%s); retrying in %.1f s", self.config.url, exc, delay)
        else:
            change = Change.between(self.policy.acknowledged, snapshot.scene_graph)
            self.policy.sent(snapshot, time.monotonic())
            self.puts += 1
            log.info("session %s, version %s: scene graph sent (%s)", session_id, session["version"], change)


# --- the command ----------------------------------------------------------------------------------------


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        msg = f"must be above 0, got {text}"
        raise argparse.ArgumentTypeError(msg)
    return value


def add_parser(sub: Any) -> None:
    parser = sub.add_parser(
        "hydra-bridge", help="keep a session's scene graph equal to a Hydra publisher's (spark_dsg over ZMQ)"
    )
    parser.add_argument(
        "--zmq", required=True, metavar="URL", help="the DsgSender's, e.g. tcp://127.0.0.1:8001"
    )
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the VL-Map service")
    parser.add_argument("--session", required=True, metavar="ID", help="the session to keep up to date")
    parser.add_argument(
        "--api-key-file",
        type=Path,
        metavar="F",
        help="a file holding the API key (the session's robot's, or an admin's)",
    )
    parser.add_argument(
        "--max-rate",
        type=_positive,
        default=1.0,
        metavar="N",
        help="at most N PUTs a second (default 1, the service's default binary-decode rate per key)",
    )
    parser.add_argument(
        "--max-backoff", type=_positive, default=30.0, metavar="S", help="longest wait between retries (s)"
    )
    parser.set_defaults(func=bridge_command)


def config_of(args: argparse.Namespace) -> BridgeConfig:
    return BridgeConfig(
        zmq_url=args.zmq,
        url=args.url,
        session_id=args.session,
        api_key=read_api_key(args.api_key_file) if args.api_key_file is not None else None,
        max_rate=args.max_rate,
        max_backoff_s=args.max_backoff,
    )


def bridge_command(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())  # finish the step in progress, then close
    try:
        HydraBridge(config_of(args)).run(stop)
    except KeyboardInterrupt:
        pass
    except BridgeStopped as exc:
        log.error("stopped: %s", exc)
        return 1
    return 0
