"""`vlmap hydra-bridge` with real parts on loopback: a `spark_dsg.zmq.DsgSender` publishing, the bridge on a
thread, the service under uvicorn (`tests.test_events.served`) with a memory store the test reads.

PUB/SUB drops what is published before the subscriber has connected ("slow joiner"), so a publisher here
re-sends its graph until the effect is seen, never sleeps for a guessed time. A step that does not come
within `WAIT_S` fails the test: a guard against hanging, not a measure of time. The policy's timing (rate,
backoff) is tested on its own, with the clock passed in.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import spark_dsg as dsg
import zmq
from spark_dsg.zmq import DsgSender

from app.api.auth import digest, new_key
from app.cli import build_parser
from app.client import VLMapClient
from app.hydra_bridge import (
    BridgeConfig,
    BridgeStopped,
    Change,
    HydraBridge,
    SendPolicy,
    Snapshot,
    config_of,
    normalised,
)
from app.scene_graph.hydra import parse_spark_dsg_binary
from app.scene_graph.model import SceneGraph
from app.sim.service import free_port
from app.stores import MemorySessionStore
from tests.conftest import model_free_settings
from tests.test_events import served

WAIT_S = 60.0
Objects = dict[int, tuple[str, tuple[float, float, float]]]

FIRST: Objects = {1: ("table", (1.5, 1.0, 0.4)), 2: ("chair", (6.0, 2.0, 0.45))}
# The table moved, a backpack added.
SECOND: Objects = {**FIRST, 1: ("table", (2.5, 1.2, 0.4)), 3: ("backpack", (7.0, 1.0, 0.3))}
# The chair gone (as from a restarted Hydra that no longer sees it).
THIRD: Objects = {k: v for k, v in SECOND.items() if k != 2}
GRID = {"voxel_size": 0.25, "min_corner": [-0.5, -0.5, 0.0], "max_corner": [10.5, 3.5, 2.5]}


def two_rooms(objects: Objects) -> Any:
    """Kitchen R0 (x 0-4) and bedroom R1 (x 4-10), each object O<i> under the room it stands in."""
    graph = dsg.DynamicSceneGraph()
    for index, (name, x0, x1) in enumerate([("kitchen", 0.0, 4.0), ("bedroom", 4.0, 10.0)]):
        room = dsg.RoomNodeAttributes()
        room.name = name
        room.position = np.array([(x0 + x1) / 2, 1.5, 1.25])
        room.bounding_box = dsg.BoundingBox(
            np.array([x1 - x0, 3.0, 2.5], dtype=np.float32),
            np.array([(x0 + x1) / 2, 1.5, 1.25], dtype=np.float32),
        )
        graph.add_node(dsg.DsgLayers.ROOMS, dsg.NodeSymbol("R", index), room)
    for index, (label, center) in objects.items():
        attrs = dsg.ObjectNodeAttributes()
        attrs.name = label
        attrs.position = np.array(center)
        attrs.bounding_box = dsg.BoundingBox(
            np.array([0.6, 0.6, 0.8], dtype=np.float32), np.array(center, dtype=np.float32)
        )
        graph.add_node(dsg.DsgLayers.OBJECTS, dsg.NodeSymbol("O", index), attrs)
        graph.insert_edge(dsg.NodeSymbol("R", 0 if center[0] < 4.0 else 1), dsg.NodeSymbol("O", index))
    return graph


def expected(objects: Objects) -> SceneGraph:
    """What the service makes of the graph: its own sandboxed reader of the binary."""
    return parse_spark_dsg_binary(bytes(two_rooms(objects).to_binary()))


class Publisher:
    """A DsgSender on a port of 127.0.0.1, in a ZMQ context of its own (so that closing it frees the port)."""

    def __init__(self, port: int) -> None:
        self.context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self.sender = DsgSender(f"tcp://127.0.0.1:{port}", context=self.context)

    def send(self, objects: Objects) -> None:
        self.sender.send(two_rooms(objects))

    def close(self) -> None:
        self.context.destroy(linger=0)


class Session:
    """A session in the test's memory store, read directly (the service has no GET of a scene graph)."""

    def __init__(self, store: MemorySessionStore, session_id: str) -> None:
        self.store, self.id = store, session_id

    def scene_graph(self) -> SceneGraph:
        return asyncio.run(self.store.head_and_scene_graph(self.id))[1]

    def version(self) -> int:
        return asyncio.run(self.store.head(self.id)).version

    def holds(self, objects: Objects) -> Callable[[], bool]:
        want = expected(objects)

        def check() -> bool:
            held = self.scene_graph()
            return held.objects == want.objects and held.regions == want.regions

        return check


@contextlib.contextmanager
def bridging(
    config: BridgeConfig, ended: list[BaseException] | None = None
) -> Iterator[tuple[HydraBridge, threading.Thread]]:
    """The bridge on a thread; what ended it, if anything did, is appended to `ended`."""
    bridge, stop, failures = HydraBridge(config), threading.Event(), [] if ended is None else ended

    def run() -> None:
        try:
            bridge.run(stop)
        except BaseException as exc:
            failures.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield bridge, thread
    finally:
        stop.set()
        thread.join(WAIT_S)
        assert not thread.is_alive(), "the bridge did not stop"
    assert ended is not None or not failures, f"the bridge failed: {failures}"


def until(
    condition: Callable[[], bool], what: str, thread: threading.Thread, step: Callable[[], None]
) -> None:
    """Run `step` (a re-send) until `condition` holds; fails if the bridge died or `WAIT_S` passed."""
    pause, deadline = threading.Event(), time.monotonic() + WAIT_S
    while not condition():
        assert thread.is_alive(), f"the bridge died before {what}"
        assert time.monotonic() < deadline, f"never saw {what}"
        step()
        pause.wait(0.05)


def create_session(url: str, store: MemorySessionStore, api_key: str | None = None) -> Session:
    with VLMapClient(url, api_key=api_key) as client:
        # The rooms only: the session's graph is the bridge's from the first PUT on.
        created = client.create_session("robot-7", expected({}).model_dump(mode="json"), grid=GRID)
    session = Session(store, created["id"])
    assert session.version() == 0
    return session


def test_the_bridge_follows_the_graph_puts_only_changes_and_survives_restarts_and_garbage() -> None:
    store, port = MemorySessionStore(None), free_port()
    zmq_url = f"tcp://127.0.0.1:{port}"
    with served(model_free_settings(decode_rate_per_s=0), store) as server:
        session = create_session(server.url, store)
        config = BridgeConfig(zmq_url, server.url, session.id, max_rate=20.0, max_backoff_s=0.5)
        publisher = Publisher(port)
        with bridging(config) as (bridge, thread):
            until(session.holds(FIRST), "the first graph", thread, lambda: publisher.send(FIRST))
            assert session.version() == 1  # one PUT, however often the graph was re-sent
            held = session.scene_graph()
            assert [(o.id, o.label, o.region_id) for o in held.objects] == [
                ("O1", "table", "R0"),
                ("O2", "chair", "R1"),
            ]
            assert [(r.id, r.name) for r in held.regions] == [("R0", "kitchen"), ("R1", "bedroom")]

            handled = bridge.handled
            until(
                lambda: bridge.handled > handled, "the re-sent graph", thread, lambda: publisher.send(FIRST)
            )
            assert bridge.policy.pending is None and session.version() == 1  # unchanged: no PUT

            until(session.holds(SECOND), "the second graph", thread, lambda: publisher.send(SECOND))
            assert session.version() == 2
            table, _, backpack = session.scene_graph().objects
            assert table.center == pytest.approx([2.5, 1.2, 0.4]) and table.size == pytest.approx(
                [0.6, 0.6, 0.8]
            )
            assert (backpack.id, backpack.label, backpack.region_id) == ("O3", "backpack", "R1")

            # The publisher goes, another on its port sends garbage, then a third restarts Hydra's stream.
            publisher.close()
            context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
            garbage = context.socket(zmq.PUB)
            garbage.bind(zmq_url)
            # Refused by the check of the opening bytes, and by spark_dsg, in turn.
            bad = itertools.cycle([b"\xdd garbage", bytes(two_rooms(THIRD).to_binary())[:-40]])
            until(lambda: bridge.bad_messages > 1, "bad messages", thread, lambda: garbage.send(next(bad)))
            context.destroy(linger=0)
            assert normalised(bridge.feed.graph).scene_graph == expected(SECOND)  # the last good graph

            publisher = Publisher(port)
            until(
                session.holds(THIRD), "the restarted publisher's graph", thread, lambda: publisher.send(THIRD)
            )
            assert session.version() == 3  # each graph PUT once: the version counts the PUTs applied
            publisher.close()


def test_the_bridge_retries_while_the_service_restarts(tmp_path: Path) -> None:
    key = new_key()
    records = [{"name": "robot-7", "role": "robot", "robot_ids": ["robot-7"], "sha256": digest(key)}]
    settings = model_free_settings(api_keys=json.dumps(records), decode_rate_per_s=0)
    key_file = tmp_path / "key"
    key_file.write_text(key + "\n", encoding="utf-8")
    store, service_port, zmq_port = MemorySessionStore(None), free_port(), free_port()
    publisher = Publisher(zmq_port)
    with contextlib.ExitStack() as first_run:
        server = first_run.enter_context(served(settings, store, port=service_port))
        session = create_session(server.url, store, key)
        argv = ["hydra-bridge", "--zmq", f"tcp://127.0.0.1:{zmq_port}", "--url", server.url, "--session"]
        argv += [session.id, "--api-key-file", str(key_file), "--max-rate", "20", "--max-backoff", "0.5"]
        config = config_of(build_parser().parse_args(argv))
        assert config.api_key == key
        with bridging(config) as (bridge, thread):
            until(session.holds(FIRST), "the first graph", thread, lambda: publisher.send(FIRST))
            first_run.close()  # the service stops: the bridge keeps the change and retries
            until(lambda: bridge.policy.failures > 1, "failed PUTs", thread, lambda: publisher.send(SECOND))
            with served(settings, store, port=service_port):
                until(
                    session.holds(SECOND),
                    "the graph after the restart",
                    thread,
                    lambda: publisher.send(SECOND),
                )
            # The same bridge, acknowledged (its answer may come just after the store has the graph).
            until(lambda: bridge.puts == 2, "the PUT's answer", thread, lambda: None)
    publisher.close()
    assert session.version() == 2


def test_the_bridge_stops_when_its_session_is_gone() -> None:
    store, port = MemorySessionStore(None), free_port()
    publisher, ended = Publisher(port), []
    with served(model_free_settings(decode_rate_per_s=0), store) as server:
        config = BridgeConfig(f"tcp://127.0.0.1:{port}", server.url, "0" * 32, max_rate=20.0)
        with bridging(config, ended) as (_, thread):
            pause, deadline = threading.Event(), time.monotonic() + WAIT_S
            while thread.is_alive():
                assert time.monotonic() < deadline, "the bridge kept going"
                publisher.send(FIRST)
                pause.wait(0.05)
    publisher.close()
    assert len(ended) == 1 and isinstance(ended[0], BridgeStopped) and "404" in str(ended[0])


# --- the policy, with the clock passed in ---------------------------------------------------------------


def snapshot(objects: Objects) -> Snapshot:
    return Snapshot(expected(objects), b"")


def test_the_policy_sends_the_newest_change_at_most_at_its_rate() -> None:
    policy = SendPolicy(min_interval_s=1.0, max_backoff_s=4.0)
    first, second = snapshot(FIRST), snapshot(SECOND)
    assert policy.offer(first) is not None and policy.due(0.0) is first
    policy.sent(first, 0.0)
    assert policy.offer(snapshot(FIRST)) is None and policy.wait_s(0.1) is None  # unchanged: nothing to send
    change = policy.offer(second)
    assert change is not None and str(change) == "objects 1 added, 1 changed; regions unchanged"
    assert policy.due(0.5) is None and policy.wait_s(0.5) == pytest.approx(0.5)  # within the rate
    third = snapshot(THIRD)
    policy.offer(third)
    assert policy.due(1.0) is third  # the newest wins
    # Back to what the service holds before it was sent: nothing to send.
    assert policy.offer(snapshot(FIRST)) is None and policy.pending is None


def test_the_policy_backs_off_exponentially_capped_and_drops_a_refused_graph() -> None:
    policy = SendPolicy(min_interval_s=0.1, max_backoff_s=4.0)
    graph = snapshot(FIRST)
    policy.offer(graph)
    delays = [policy.failed(0.0) for _ in range(6)]
    assert delays == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert (
        policy.due(3.9) is None and policy.due(4.0) is graph and policy.pending is graph
    )  # kept for the retry
    policy.rejected(graph, 4.0)
    assert policy.offer(snapshot(FIRST)) is None  # refused once: not sent again
    assert policy.offer(snapshot(SECOND)) is not None and policy.failures == 0


def test_after_a_failed_put_the_last_acknowledged_graph_is_sent_again() -> None:
    policy = SendPolicy(min_interval_s=0.1, max_backoff_s=4.0)
    first, second = snapshot(FIRST), snapshot(SECOND)
    policy.offer(first)
    policy.sent(first, 0.0)
    policy.offer(second)
    policy.failed(1.0)  # a timeout or a 5xx: the service may hold the second graph all the same
    back = snapshot(FIRST)
    assert policy.offer(back) is not None and policy.due(2.0) is back
    policy.sent(back, 2.0)
    assert policy.offer(snapshot(FIRST)) is None  # acknowledged: known again


def test_an_empty_graph_is_sent_while_what_the_service_holds_is_unknown() -> None:
    policy = SendPolicy(min_interval_s=0.1, max_backoff_s=4.0)
    empty = Snapshot(SceneGraph(frame_id="map", regions=[], objects=[]), b"")
    assert policy.offer(empty) is not None and policy.due(0.0) is empty  # the first graph, though empty
    policy.sent(empty, 0.0)
    assert policy.offer(Snapshot(empty.scene_graph, b"")) is None  # acknowledged: nothing new
    first = snapshot(FIRST)
    policy.offer(first)
    policy.failed(1.0)  # the service may hold FIRST, or still the empty graph
    emptied = Snapshot(empty.scene_graph, b"")
    assert policy.offer(emptied) is not None and policy.due(2.0) is emptied


def test_a_graph_that_comes_again_while_its_put_is_retried_keeps_its_key() -> None:
    """Hydra publishes its graph again and again: one arriving during the backoff is the same PUT."""
    policy = SendPolicy(min_interval_s=0.1, max_backoff_s=4.0)
    first = snapshot(FIRST)
    policy.offer(first)
    policy.failed(0.0)  # the answer was lost: the service may have applied it
    again = snapshot(FIRST)
    assert policy.offer(again) is not None
    due = policy.due(1.0)
    assert due is not None and due.key == first.key
    policy.offer(snapshot(SECOND))
    assert policy.pending is not None and policy.pending.key != first.key  # another graph: another key


def test_a_change_is_judged_by_id_on_objects_and_regions() -> None:
    first = expected(FIRST)
    reordered = first.model_copy(update={"objects": first.objects[::-1], "frame_id": "odom"})
    assert not Change.between(first, reordered)
    assert str(Change.between(None, first)) == "objects 2 added; regions 2 added"
    assert str(Change.between(expected(SECOND), expected(THIRD))) == "objects 1 removed; regions unchanged"
