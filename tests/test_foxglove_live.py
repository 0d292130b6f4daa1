"""`vlmap foxglove` (`app.foxglove.live`): the SDK's WebSocket server, over the service on loopback, answers
a WebSocket client speaking the Foxglove protocol with the sessions' channel advertisements, fetches a
session's frames only once a viewer subscribes, and sends its messages."""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

import websockets

from app.client import VLMapClient
from app.foxglove.live import LiveServer
from app.foxglove.messages import Topics
from tests.conftest import model_free_settings
from tests.test_events import served
from tests.test_recording import LABELS, SCENE

WAIT_S = 60.0


async def _advertised(port: int, topics: Topics) -> tuple[str | None, dict[str, Any], list[bytes]]:
    """Connect, read the advertisements until the session's channels are there, subscribe to its belief and
    read one binary message (a MessageData frame)."""
    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=WAIT_S) as ws:  # type: ignore[list-item]
        channels: dict[str, Any] = {}
        # A session's channels may come in more than one advertise message: wait for all of them.
        wanted = {topics.scene_graph, topics.belief, topics.mixture, topics.utterances, topics.summary}
        while not wanted <= channels.keys():
            message = json.loads(await asyncio.wait_for(ws.recv(), WAIT_S))
            if message["op"] == "advertise":
                channels |= {c["topic"]: c for c in message["channels"]}
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
