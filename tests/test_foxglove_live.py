"""`vlmap foxglove` (`app.foxglove.live`): the SDK's WebSocket server, over the service on loopback, answers
a WebSocket client speaking the Foxglove protocol with the sessions' channel advertisements, fetches a
session's frames only once a viewer subscribes, and sends its messages."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any

import numpy as np
import pytest
import websockets

from app.client import VLMapClient
from app.foxglove.live import LiveServer
from app.foxglove.messages import Topics, _quaternion
from tests.conftest import model_free_settings
from tests.test_events import served
from tests.test_recording import LABELS, SCENE

WAIT_S = 60.0


def _wanted(topics: Topics) -> set[str]:
    return {topics.scene_graph, topics.belief, topics.mixture, topics.utterances, topics.summary}


async def _channels(ws: Any, topics: Topics) -> dict[str, Any]:
    """Read the advertisements until the session's channels are all there (they may come in several)."""
    channels: dict[str, Any] = {}
    while not _wanted(topics) <= channels.keys():
        message = json.loads(await asyncio.wait_for(ws.recv(), WAIT_S))
        if message["op"] == "advertise":
            channels |= {c["topic"]: c for c in message["channels"]}
    return channels


async def _advertised(port: int, topics: Topics) -> tuple[str | None, dict[str, Any], list[bytes]]:
    """Connect, read the session's channels, subscribe to its belief and read one binary message (a
    MessageData frame)."""
    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
        channels = await _channels(ws, topics)
        subscribe = [{"id": 1, "channelId": channels[topics.belief]["id"]}]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscribe}))
        data: list[bytes] = []
        while not data:
            frame = await asyncio.wait_for(ws.recv(), WAIT_S)
            if isinstance(frame, bytes):
                data.append(frame)
        return ws.subprotocol, channels, data


def test_the_live_server_advertises_a_sessions_topics_and_sends_its_belief_to_a_subscriber() -> None:
    with served(model_free_settings()) as service, VLMapClient(service.url) as client:
        session = client.create_session("r1", SCENE, target_label="backpack", label_map=LABELS)
        client.send_utterance(session["id"], "my backpack is on the table")
        live = LiveServer(client, robot_id="r1", port=0)
        follower = threading.Thread(target=live.run, daemon=True)
        follower.start()
        try:
            topics = Topics(session["id"])
            protocol, channels, data = asyncio.run(_advertised(live.port, topics))
            assert protocol == "foxglove.sdk.v1"
            assert channels[topics.scene_graph]["schemaName"] == "foxglove.SceneUpdate"
            assert channels[topics.belief]["schemaName"] == "foxglove.PointCloud"
            assert channels[topics.mixture]["schemaName"] == "foxglove.SceneUpdate"
            assert channels[topics.utterances]["schemaName"] == "foxglove.Log"
            assert channels[topics.summary]["encoding"] == "json"
            assert data[0][0] == 1  # the MessageData opcode, for the subscription
            assert int.from_bytes(data[0][1:5], "little") == 1
        finally:
            live.stop()


def test_a_viewer_that_comes_after_every_other_left_gets_the_last_state() -> None:
    with served(model_free_settings()) as service, VLMapClient(service.url) as client:
        session = client.create_session("r3", SCENE, target_label="backpack", label_map=LABELS)
        client.send_utterance(session["id"], "my backpack is on the table")
        live = LiveServer(client, session_id=session["id"], port=0)
        follower = threading.Thread(target=live.run, daemon=True)
        follower.start()
        try:
            topics = Topics(session["id"])
            _, _, first = asyncio.run(_advertised(live.port, topics))
            # The first viewer has gone (its disconnection unsubscribes it) and the session is unchanged.
            deadline = time.monotonic() + WAIT_S
            while live.subscriptions.watched(session["id"]):
                assert time.monotonic() < deadline, "the first viewer's subscription outlived it"
                time.sleep(0.05)
            _, _, second = asyncio.run(_advertised(live.port, topics))
            assert second == first  # the same belief message
        finally:
            live.stop()


async def _first_log_times(port: int, topics: Topics, expected: int) -> list[int]:
    """Subscribe to all of a session's topics at once; the log times of the first `expected` messages."""
    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
        channels = await _channels(ws, topics)
        subscribe = [
            {"id": k + 1, "channelId": channels[t]["id"]} for k, t in enumerate(sorted(_wanted(topics)))
        ]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscribe}))
        times: list[int] = []
        while len(times) < expected:
            frame = await asyncio.wait_for(ws.recv(), WAIT_S)
            if isinstance(frame, bytes) and frame[0] == 1:  # MessageData: op, subscription id, log time, data
                times.append(int.from_bytes(frame[5:13], "little"))
        return times


def test_a_first_viewer_gets_the_sessions_messages_in_log_time_order() -> None:
    """Every utterance's log and the latest of each other topic: the logs had come first and the other topics'
    older messages after them, so a viewer saw time go back."""
    with served(model_free_settings()) as service, VLMapClient(service.url) as client:
        sid = client.create_session("r4", SCENE, target_label="backpack", label_map=LABELS)["id"]
        client.send_utterance(sid, "my backpack is on the table")
        client.send_observations(sid, voxels=np.array([[1, 1, 1]]), labels=np.array([1]))
        client.send_utterance(sid, "the mug is on the sofa")  # not fused: the newest frame is a log
        live = LiveServer(client, session_id=sid, port=0)
        threading.Thread(target=live.run, daemon=True).start()
        try:
            times = asyncio.run(_first_log_times(live.port, Topics(sid), expected=6))
            assert times == sorted(times), times
        finally:
            live.stop()


def test_without_a_subscriber_nothing_is_fetched() -> None:
    with served(model_free_settings()) as service, VLMapClient(service.url) as client:
        session = client.create_session("r2", SCENE, target_label="backpack", label_map=LABELS)
        live = LiveServer(client, session_id=session["id"], port=0)
        try:
            live.list_sessions()
            live.publish(session["id"])  # as a new version would ask: nobody watches, so no request
            shown = live._shown[session["id"]]
            assert shown.converter is None and shown.version is None
        finally:
            live.stop()


def _rotation(quaternion: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = quaternion
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.mark.parametrize(
    "axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 2, 3), (-3, 1, 2), (1, -1, 0), (2, 1, -2), (1, 1, 1)]
)
def test_an_ellipsoids_orientation_is_its_rotation_even_at_a_half_turn(axis: tuple[int, int, int]) -> None:
    n = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    for angle in (np.pi, np.pi - 1e-9, 2.0, 0.3, 0.0):
        # Rodrigues: the rotation by `angle` about n.
        k = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
        rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        quaternion = _quaternion(rotation)
        assert np.linalg.norm(quaternion) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(_rotation(quaternion), rotation, atol=1e-9)
