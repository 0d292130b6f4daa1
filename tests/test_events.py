"""The push stream (Server-Sent Events) on real servers on loopback: every version of a session once and in
order, resumed with Last-Event-ID, a client that does not read cut off without harming the writers or the
other streams, access by key, and two `vlmap serve` replicas on one Redis.

In-process servers are `create_app` under uvicorn in a thread (as `vlmap serve` runs it), with the memory
store or a Redis store of a prefix of its own; the replicas are `vlmap serve` processes. Clients are
`app.client`'s, except the one that never reads (a raw socket). A step that does not come within `WAIT_S`
fails the test: a guard against hanging, not a measure of time.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn

from app.api.app import create_app
from app.api.auth import digest, new_key
from app.api.routes.events import BeliefEvent, StreamSync
from app.api.server import guarded_protocol
from app.client import StreamEvent, VLMapClient, VLMapHTTPError
from app.sessions.events import EventHub
from app.settings import Settings
from app.sim.service import MODEL_FREE_ENV, start_service, wait_ready
from app.stores.base import SessionStore
from tests.conftest import load_resource_json, model_free_settings

SCENE = load_resource_json("scenes/two_rooms.json")
LABELS = {"0": "chair", "1": "backpack"}
WAIT_S = 30.0
STREAM_ROUTE = "/v1/sessions/{session_id}/events"


@dataclass
class Served:
    app: Any
    url: str

    @property
    def hub(self) -> EventHub:
        hub: EventHub = self.app.state.services.sessions.events
        return hub

    def streams_opened(self, route: str = STREAM_ROUTE) -> float:
        """Event streams this server answered with a 200 (its request counter)."""
        counter = self.app.state.services.metrics.requests.labels(method="GET", route=route, status="200")
        return float(counter._value.get())


@contextlib.contextmanager
def served(
    settings: Settings, store: SessionStore | None = None, sndbuf: int | None = None, port: int = 0
) -> Iterator[Served]:
    """The service under uvicorn on a loopback port (a free one unless given: a restart on the same port),
    in a thread; `sndbuf`: its sockets' send buffer (bytes, fixed: no autotuning), a slow network's."""
    app = create_app(settings, store=store)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # the port again while old connections linger
    if sndbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)  # accepted connections inherit it
    sock.bind(("127.0.0.1", port))
    config = uvicorn.Config(
        app,
        log_config=None,
        http=guarded_protocol(settings.header_timeout_s, settings.max_header_bytes),
        timeout_graceful_shutdown=1,
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    ready = threading.Event()
    while not server.started and thread.is_alive():
        ready.wait(0.01)
    assert server.started, "the server did not start"
    try:
        yield Served(app, f"http://127.0.0.1:{sock.getsockname()[1]}")
    finally:
        server.should_exit = True
        thread.join(WAIT_S)
        sock.close()


class Reader:
    """A client following a stream on a thread of its own, keeping its events (until the stream is over,
    or `until` says so)."""

    def __init__(
        self, events: Callable[[], Iterator[StreamEvent]], until: Callable[[StreamEvent], bool] | None = None
    ) -> None:
        self.events: list[StreamEvent] = []
        self.error: BaseException | None = None
        self._changed = threading.Condition()
        self._events, self._until = events, until
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for event in self._events():
                with self._changed:
                    self.events.append(event)
                    self._changed.notify_all()
                if self._until is not None and self._until(event):
                    break
        except BaseException as exc:  # reported by `wait`
            self.error = exc
        finally:
            with self._changed:
                self._changed.notify_all()

    def wait(self, condition: Callable[[list[StreamEvent]], bool], what: str) -> list[StreamEvent]:
        with self._changed:
            held = self._changed.wait_for(
                lambda: condition(self.events) or self.error is not None or not self._thread.is_alive(),
                WAIT_S,
            )
            if self.error is not None:
                raise self.error
            assert held and condition(self.events), f"never got {what}; got {self.summary()}"
            return list(self.events)

    def done(self) -> list[StreamEvent]:
        self._thread.join(WAIT_S)
        assert not self._thread.is_alive(), f"the stream did not end; got {self.summary()}"
        if self.error is not None:
            raise self.error
        return list(self.events)

    def summary(self) -> list[tuple[Any, ...]]:
        return [(e.event, e.data.get("version"), e.data.get("cause", {}).get("kind")) for e in self.events]


def beliefs(events: list[StreamEvent], session_id: str | None = None) -> list[StreamEvent]:
    return [e for e in events if e.event == "belief" and session_id in (None, e.data["session_id"])]


def versions(events: list[StreamEvent], session_id: str | None = None) -> list[int]:
    return [e.data["version"] for e in beliefs(events, session_id)]


def has_version(version: int, session_id: str | None = None) -> Callable[[list[StreamEvent]], bool]:
    return lambda events: version in versions(events, session_id)


def is_deletion(session_id: str) -> Callable[[StreamEvent], bool]:
    return lambda e: (
        e.event == "belief" and e.data["session_id"] == session_id and e.data["cause"]["kind"] == "deleted"
    )


def all_deleted(session_ids: list[str]) -> Callable[[StreamEvent], bool]:
    """True at the event that deletes the last of `session_ids` still standing, in whatever order the
    deletions come: a Redis Cluster keeps each master's publishes in order, not those of different masters."""
    left = set(session_ids)

    def until(event: StreamEvent) -> bool:
        if event.event == "belief" and event.data["cause"]["kind"] == "deleted":
            left.discard(event.data["session_id"])
        return not left

    return until


def documented(event: StreamEvent) -> None:
    """The event is what the OpenAPI documents (the models forbid any other field)."""
    model = BeliefEvent if event.event == "belief" else StreamSync
    assert event.event in ("belief", "sync") and event.id
    model.model_validate(event.data)


def create(client: VLMapClient, robot_id: str = "r1") -> str:
    session = client.create_session(robot_id, SCENE, target_label="backpack", label_map=LABELS)
    return str(session["id"])


def batch(client: VLMapClient, session_id: str, k: int) -> None:
    """One labelled voxel: a version of its own."""
    client.send_observations(
        session_id, summary=False, voxels=np.array([[k % 7, 1, 1]]), labels=np.array([1])
    )


# -- one session, in order -----------------------------------------------------------------------------------


def test_a_session_stream_has_every_version_once_and_in_order() -> None:
    """Four robots' threads write one session at once, then an utterance fused, one not fused, a new scene
    graph and the deletion: both streams have each version once, in version order, and end with it."""
    robot = f"robot-{uuid.uuid4().hex[:6]}"
    with served(model_free_settings()) as server, VLMapClient(server.url) as client:
        fleet = Reader(lambda: VLMapClient(server.url).fleet_events(robot), until=None)
        fleet.wait(lambda events: bool(events), "the fleet stream's sync")
        sid = create(client, robot)
        stream = Reader(lambda: VLMapClient(server.url).session_events(sid))
        first = stream.wait(lambda events: bool(events), "the session stream's sync")[0]
        assert first.event == "sync" and first.data["reason"] == "start" and first.data["version"] == 0

        def write(k: int) -> None:
            with VLMapClient(server.url) as writer:
                for i in range(15):
                    batch(writer, sid, 15 * k + i)

        with ThreadPoolExecutor(4) as pool:
            list(pool.map(write, range(4)))
        fused = client.send_utterance(sid, "the backpack is on the table")
        refused = client.send_utterance(sid, "my keys are on the sofa")
        assert fused["fused"] and not refused["fused"]
        client.replace_scene_graph(sid, SCENE)
        client.delete_session(sid)
        events = stream.done()  # the session's stream ends with its deletion
        fleet.wait(
            lambda events: any(is_deletion(sid)(e) for e in events), "the deletion on the fleet stream"
        )

    assert versions(events) == [*range(1, 61), 61, 61, 62, 62]
    kinds = [e.data["cause"]["kind"] for e in beliefs(events)]
    assert kinds == ["observations"] * 60 + ["utterance", "utterance", "scene_graph", "deleted"]
    utterances = [e.data["cause"] for e in beliefs(events) if e.data["cause"]["kind"] == "utterance"]
    assert [(c["utterance"], c["fused"]) for c in utterances] == [
        ("the backpack is on the table", True),
        ("my keys are on the sofa", False),
    ]
    assert "not fused" in utterances[1]["reason"]
    assert beliefs(events)[62].data["cause"] == {"kind": "scene_graph", "objects": 4, "regions": 2}
    assert all(e.data["cause"]["voxels_updated"] == 1 for e in beliefs(events)[:60])
    assert all(e.data["summary_url"] == f"/v1/sessions/{sid}/belief" for e in beliefs(events))
    for event in events:
        documented(event)
    assert len({e.id for e in events}) == len(events)
    # The fleet stream: its sync, the creation, then the very same events.
    fleet_events = fleet.events
    assert fleet_events[0].event == "sync" and fleet_events[0].data["robot_id"] == robot
    assert versions(fleet_events) == [0, *versions(events)]
    assert [(e.id, e.data) for e in beliefs(fleet_events)[1:]] == [(e.id, e.data) for e in beliefs(events)]


def test_a_stream_answers_what_the_key_may_read() -> None:
    keys = {role: new_key() for role in ("admin", "viewer", "a", "b")}
    records = [
        {"name": "ops", "role": "admin", "sha256": digest(keys["admin"])},
        {"name": "dashboard", "role": "viewer", "sha256": digest(keys["viewer"])},
        {"name": "robot-a", "role": "robot", "sha256": digest(keys["a"]), "robot_ids": ["ra"]},
        {"name": "robot-b", "role": "robot", "sha256": digest(keys["b"]), "robot_ids": ["rb"]},
    ]
    settings = model_free_settings(api_keys=json.dumps(records), max_event_streams=3)
    with served(settings) as server, VLMapClient(server.url, api_key=keys["admin"]) as admin:
        sa, sb = create(admin, "ra"), create(admin, "rb")
        with VLMapClient(server.url, api_key=keys["a"]) as robot_a, VLMapClient(server.url) as anonymous:
            for call in (
                lambda: next(robot_a.session_events(sb)),
                lambda: next(robot_a.fleet_events("rb")),
                lambda: next(anonymous.fleet_events()),
            ):
                with pytest.raises(VLMapHTTPError) as refused:
                    call()
                assert refused.value.status in (401, 403)
        viewer = Reader(
            lambda: VLMapClient(server.url, api_key=keys["viewer"]).fleet_events(), is_deletion(sa)
        )
        own = Reader(lambda: VLMapClient(server.url, api_key=keys["a"]).fleet_events(), is_deletion(sa))
        one = Reader(lambda: VLMapClient(server.url, api_key=keys["viewer"]).session_events(sa))
        for reader in (viewer, own, one):
            reader.wait(lambda events: bool(events), "the sync")
        with pytest.raises(VLMapHTTPError) as busy:  # the fourth stream of a replica serving three
            next(VLMapClient(server.url, api_key=keys["viewer"], retries=0).fleet_events())
        assert busy.value.status == 429 and busy.value.code == "limit_exceeded"
        for k in range(3):  # b's first: a stream leaking them would have them before a's deletion
            batch(admin, sb, k)
        batch(admin, sa, 0)
        admin.delete_session(sb)
        admin.delete_session(sa)
        seen_by = {name: reader.done() for name, reader in (("viewer", viewer), ("own", own), ("one", one))}
    assert {e.data["session_id"] for e in beliefs(seen_by["viewer"])} == {sa, sb}
    assert [(e.data["session_id"], e.data["version"]) for e in beliefs(seen_by["own"])] == [(sa, 1), (sa, 1)]
    assert beliefs(seen_by["one"]) == beliefs(seen_by["own"])


# -- resuming ------------------------------------------------------------------------------------------------


def until_version(version: int) -> Callable[[StreamEvent], bool]:
    return lambda e: e.event == "belief" and e.data["version"] == version


def test_resuming_with_last_event_id_replays_exactly_what_was_missed() -> None:
    with served(model_free_settings(events_history=8)) as server, VLMapClient(server.url) as client:

        def follow(last: str | None = None, until: int = 3, fleet: bool = False) -> Reader:
            follower = VLMapClient(server.url)
            if fleet:
                return Reader(
                    lambda: follower.fleet_events(None, last, reconnect=False), until_version(until)
                )
            return Reader(lambda: follower.session_events(sid, last, reconnect=False), until_version(until))

        sid = create(client)
        reader, fleet = follow(), follow(fleet=True)
        for stream in (reader, fleet):
            stream.wait(lambda events: bool(events), "the sync")
        for k in range(3):
            batch(client, sid, k)
        seen, fleet_seen = reader.done(), fleet.done()  # disconnected after version 3
        assert fleet_seen[-1].id == seen[-1].id  # one id per event, whichever stream carries it
        for k in range(3, 8):  # versions 4-8, written while nobody listens
            batch(client, sid, k)
        again = follow(seen[-1].id, until=8).done()
        assert versions(again) == [4, 5, 6, 7, 8] and all(e.event == "belief" for e in again)
        fleet_again = follow(fleet_seen[-1].id, until=8, fleet=True).done()
        assert [(e.id, e.data) for e in fleet_again] == [(e.id, e.data) for e in again]

        for k in range(8, 18):  # versions 9-18: the history (8 events) no longer reaches back to 8
            batch(client, sid, k)
        version = 18
        past_the_newest = again[-1].id.rsplit(".", 1)[0] + ".999999999"  # an id no event had: never followed
        for stale in (again[-1].id, "nonsense", f"{sid}:0.1", past_the_newest):
            late = follow(stale, until=version + 1)
            first = late.wait(lambda events: bool(events), "the sync")[0]
            assert first.event == "sync" and first.data["reason"] == "expired", stale
            assert first.data["version"] == version
            batch(client, sid, version)
            version += 1
            assert versions(late.done()) == [version]  # live after the sync
        client.delete_session(sid)


def test_a_client_follows_across_streams_the_server_ends() -> None:
    """Each stream lasts 0.2 s here; the client resumes each time with Last-Event-ID and misses nothing."""
    with served(model_free_settings(events_max_stream_s=0.2)) as server, VLMapClient(server.url) as client:
        sid = create(client)
        reader = Reader(lambda: VLMapClient(server.url).session_events(sid))
        reader.wait(lambda events: bool(events), "the sync")
        pause = threading.Event()
        for k in range(6):
            batch(client, sid, k)
            reader.wait(has_version(k + 1), f"version {k + 1}")
            pause.wait(0.1)  # some versions a stream apart
        client.delete_session(sid)
        events = reader.done()
        assert server.streams_opened() >= 3
    assert [e.event for e in events] == ["sync"] + ["belief"] * 7  # one sync: the resumptions replayed
    assert versions(events) == [1, 2, 3, 4, 5, 6, 6]


# -- a client that does not read -----------------------------------------------------------------------------


def test_a_client_that_does_not_read_is_cut_off_without_slowing_anyone() -> None:
    """A client asks for a session's stream and never reads it; a robot keeps writing, other clients follow
    the session and the fleet. Once 64 events wait for the idle client (past what its connection holds:
    4 kB of socket at the server here, 64 kB at the client, uvicorn's 64 kB), its stream is dropped and its
    connection closed; every write was answered, and the other streams have every version."""
    settings = model_free_settings(events_buffer=64)
    with served(settings, sndbuf=4096) as server, VLMapClient(server.url) as robot:
        sid = create(robot)
        good = Reader(lambda: VLMapClient(server.url).session_events(sid))
        fleet = Reader(lambda: VLMapClient(server.url).fleet_events(), is_deletion(sid))
        for stream in (good, fleet):
            stream.wait(lambda events: bool(events), "the sync")
        followers = set(server.hub._subs[("session", sid)])
        idle = socket.create_connection(("127.0.0.1", int(server.url.rsplit(":", 1)[1])))
        idle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)
        request = (
            f"GET /v1/sessions/{sid}/events HTTP/1.1\r\nHost: vlmap\r\nAccept: text/event-stream\r\n\r\n"
        )
        idle.sendall(request.encode())
        eventually(lambda: len(server.hub._subs[("session", sid)]) == 2, "the idle client's stream")
        (idle_stream,) = server.hub._subs[("session", sid)] - followers
        written = 0
        while not idle_stream.dropped:
            assert written < 20_000, "the idle client was never cut off"
            batch(robot, sid, written)  # answered every time: the idle client slows no writer
            written += 1
        for k in range(5):  # and the others go on
            batch(robot, sid, written + k)
        robot.delete_session(sid)
        events, fleet_events = good.done(), fleet.done()
        received = b""
        idle.settimeout(WAIT_S)
        while chunk := idle.recv(1 << 16):  # what the kernel held for it, then the end: closed by the server
            received += chunk
        idle.close()
    total = written + 5
    assert versions(events) == [*range(1, total + 1), total]
    assert versions(fleet_events, sid) == [*range(1, total + 1), total]
    assert received.startswith(b"HTTP/1.1 200 OK")
    assert f'"version":{total},'.encode() not in received  # cut off before the end


def eventually(condition: Callable[[], bool], what: str) -> None:
    pause, deadline = threading.Event(), time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, f"never saw {what}"
        pause.wait(0.01)


# -- replicas on Redis ---------------------------------------------------------------------------------------


@pytest.fixture
def replicas(redis_url: str) -> Iterator[tuple[str, str]]:
    """Two `vlmap serve` processes on one Redis."""
    env = {**MODEL_FREE_ENV, "VLMAP_STORE": redis_url, "VLMAP_DATA_DIR": ""}
    started = [start_service(env), start_service(env)]
    try:
        for proc, url in started:
            wait_ready(url, proc)
        yield started[0][1], started[1][1]
    finally:
        for proc, _ in started:
            proc.terminate()
        for proc, _ in started:
            proc.wait(timeout=WAIT_S)


@pytest.mark.redis
def test_a_client_of_one_replica_gets_every_version_written_through_the_other(
    replicas: tuple[str, str],
) -> None:
    """Two robots write one session through replica B at once; a client of replica A follows the session and
    the robot's fleet stream: every version once, in order; resumed on B with an id from A, the stream
    goes on from Redis."""
    a, b = replicas
    robot = f"robot-{uuid.uuid4().hex[:8]}"
    fleet = Reader(lambda: VLMapClient(a).fleet_events(robot), is_deletion_of_robot(robot))
    fleet.wait(lambda events: bool(events), "the fleet stream's sync")
    with VLMapClient(b) as writer:
        sid = create(writer, robot)
        stream = Reader(lambda: VLMapClient(a).session_events(sid))
        stream.wait(lambda events: bool(events), "the sync")

        def write(k: int) -> None:
            with VLMapClient(b) as robot_client:
                for i in range(20):
                    batch(robot_client, sid, 20 * k + i)

        with ThreadPoolExecutor(2) as pool:
            list(pool.map(write, range(2)))
        writer.send_utterance(sid, "the backpack is on the table")
        halfway = stream.wait(has_version(41), "version 41")[20]
        assert halfway.data["version"] == 20
        resumed = Reader(
            lambda: VLMapClient(b).session_events(sid, halfway.id, reconnect=False), until_version(41)
        )
        assert versions(resumed.done()) == list(range(21, 42))
        writer.delete_session(sid)
    events, fleet_events = stream.done(), fleet.done()
    assert events[0].event == "sync"
    assert versions(events) == [*range(1, 42), 41]
    assert [e.data["cause"]["kind"] for e in beliefs(events)][-2:] == ["utterance", "deleted"]
    assert versions(fleet_events) == [0, *versions(events)]
    assert [e.id for e in beliefs(fleet_events)[1:]] == [e.id for e in beliefs(events)]
    for event in events:
        documented(event)


def is_deletion_of_robot(robot: str) -> Callable[[StreamEvent], bool]:
    return lambda e: (
        e.event == "belief" and e.data["robot_id"] == robot and e.data["cause"]["kind"] == "deleted"
    )


@pytest.mark.redis
def test_a_cut_subscription_loses_nothing_of_a_session_and_says_so_on_the_fleet(redis_url: str) -> None:
    """Redis closes the replica's subscription (CLIENT KILL) while a robot writes: the replica subscribes
    again, the session stream replays what it missed from the session's Redis stream, the fleet stream
    says "gap"."""
    import redis

    from app.stores.redis_store import RedisSessionStore

    store = RedisSessionStore(redis_url, prefix=f"test-{uuid.uuid4().hex[:8]}")
    killer = redis.Redis.from_url(redis_url)
    with served(model_free_settings(), store=store) as server, VLMapClient(server.url) as robot:
        sid = create(robot)
        stream = Reader(lambda: VLMapClient(server.url).session_events(sid))
        fleet = Reader(lambda: VLMapClient(server.url).fleet_events(), is_deletion(sid))
        for reader in (stream, fleet):
            reader.wait(lambda events: bool(events), "the sync")
        batch(robot, sid, 0)
        stream.wait(has_version(1), "version 1")
        assert killer.client_kill_filter(_type="pubsub") >= 1
        for k in range(1, 6):
            batch(robot, sid, k)
        fleet.wait(lambda events: any(e.data.get("reason") == "gap" for e in events), "the gap")
        batch(robot, sid, 6)
        robot.delete_session(sid)
        events, fleet_events = stream.done(), fleet.done()
    killer.close()
    store.close()
    assert versions(events) == [1, 2, 3, 4, 5, 6, 7, 7]
    assert [e.event for e in events] == ["sync"] + ["belief"] * 8
    assert any(e.data.get("reason") == "gap" for e in fleet_events if e.event == "sync")
    seen = versions(fleet_events, sid)  # what reached the fleet stream: in order, none twice (some lost)
    assert seen[-2:] == [7, 7] and seen[:-1] == sorted(set(seen[:-1]))


@pytest.mark.redis
def test_on_a_redis_cluster_every_version_reaches_the_stream(redis_cluster_url: str) -> None:
    """The commit script publishes from the session's master; the subscription is to another node (the
    URL's): the cluster relays every publish, so sessions on every master reach the streams."""
    from app.stores.redis_store import RedisSessionStore

    store = RedisSessionStore(redis_cluster_url, prefix=f"test-{uuid.uuid4().hex[:8]}")
    with served(model_free_settings(), store=store) as server, VLMapClient(server.url) as robot:
        sessions = [create(robot) for _ in range(6)]  # spread over the masters
        assert len({store._client.get_node_from_key(store._key(sid, "meta")).name for sid in sessions}) > 1
        fleet = Reader(lambda: VLMapClient(server.url).fleet_events(), all_deleted(sessions))
        streams = [Reader(lambda sid=sid: VLMapClient(server.url).session_events(sid)) for sid in sessions]
        for reader in (fleet, *streams):
            reader.wait(lambda events: bool(events), "the sync")
        for k in range(3):
            for sid in sessions:
                batch(robot, sid, k)
        for sid in sessions:
            robot.delete_session(sid)
        fleet_events = fleet.done()
        for sid, reader in zip(sessions, streams, strict=True):
            assert versions(reader.done()) == [1, 2, 3, 3]
            assert versions(fleet_events, sid) == [1, 2, 3, 3]
    store.close()


def test_a_replica_told_to_stop_ends_its_streams_at_once() -> None:
    """uvicorn stops gracefully by waiting for the answers in progress: without the router's signal hook, a
    stream would hold a SIGTERMed `vlmap serve` for `events_max_stream_s` (10 minutes here)."""
    proc, url = start_service({**MODEL_FREE_ENV, "VLMAP_DATA_DIR": "", "VLMAP_EVENTS_MAX_STREAM_S": "600"})
    try:
        wait_ready(url, proc)
        fleet = Reader(lambda: VLMapClient(url).fleet_events(reconnect=False))
        fleet.wait(lambda events: bool(events), "the sync")
        proc.terminate()
        assert proc.wait(timeout=WAIT_S) == -signal.SIGTERM  # gracefully, then as told (uvicorn re-raises it)
        assert [e.event for e in fleet.done()] == ["sync"]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# -- the client against answers the service does not give ----------------------------------------------------


def test_the_client_retries_at_once_after_a_negative_retry_after() -> None:
    """A proxy's Retry-After of -1 is a retry at once, not a ValueError out of time.sleep."""
    answers = iter([httpx.Response(429, headers={"Retry-After": "-1"}, json={"code": "rate_limit"})])

    def handler(request: httpx.Request) -> httpx.Response:
        return next(answers, httpx.Response(200, json={"id": "s1"}))

    with VLMapClient("http://vlmap.test", transport=httpx.MockTransport(handler)) as client:
        assert client.get_session("s1") == {"id": "s1"}


def test_an_error_body_that_is_not_an_object_is_an_http_error_without_details() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(400, json=["bad"])

    client = VLMapClient("http://vlmap.test", transport=httpx.MockTransport(handler))
    with client, pytest.raises(VLMapHTTPError) as refused:
        client.get_session("s1")
    assert (refused.value.status, refused.value.code, refused.value.field) == (400, "http_error", None)
    assert refused.value.message == '["bad"]'


def test_a_redis_entry_id_past_what_redis_takes_is_no_id() -> None:
    """Parts of 64 bits at most, and nothing follows the largest id: Redis refuses a range from either."""
    from app.stores.redis_events import entry_order

    assert entry_order("5-3") == (5, 3)
    assert entry_order(f"{2**64 - 2}-0") == (2**64 - 2, 0)
    assert entry_order("1-99999999999999999999") is None
    assert entry_order(f"{2**64 - 1}-{2**64 - 1}") is None
