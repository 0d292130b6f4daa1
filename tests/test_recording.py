"""Session recordings (`app.sessions.recording`): the MCAP of `GET .../recording.mcap` read back with the
`mcap` package (topics, Foxglove schemas, one message per version, monotonic times), its decimation, and
the log on the memory store and on a real Redis."""

from __future__ import annotations

import io
import itertools
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from mcap.reader import make_reader

from app.api.app import create_app
from app.foxglove.messages import Topics
from app.foxglove.preview import decoded_messages, last_messages, render_png
from app.sessions.recording import Frame, merged
from app.stores.base import SessionStore
from app.stores.recording import KEEP, THIN, thin
from app.stores.redis_store import RedisSessionStore
from tests.conftest import load_resource_json, model_free_settings

SCENE = load_resource_json("scenes/two_rooms.json")
LABELS = {"0": "chair", "1": "backpack"}
UTTERANCES = ("my backpack is on the table", "the backpack is next to the chair")
PER_VERSION = ("belief", "estimate", "summary")


def a_session(client: TestClient) -> str:
    """A session with two utterances and five observation batches: versions 0 to 7."""
    body = {"robot_id": "r1", "scene_graph": SCENE, "target_label": "backpack", "label_map": LABELS}
    created = client.post("/v1/sessions", json=body)
    assert created.status_code == 201, created.text
    sid = str(created.json()["id"])
    for utterance in UTTERANCES:
        said = client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": utterance})
        assert said.status_code == 200 and said.json()["fused"], said.text
    for k in range(5):
        batch = {"voxels": [[k, 1, 1], [k, 2, 1]], "labels": [1, 0]}
        seen = client.post(f"/v1/sessions/{sid}/observations", json=batch)
        assert seen.status_code == 200, seen.text
    assert client.get(f"/v1/sessions/{sid}").json()["version"] == 7
    return sid


def messages(data: bytes) -> list[tuple[str, str, str, int]]:
    """(topic, schema name, schema encoding, log time) of each message, in file order."""
    reader = make_reader(io.BytesIO(data))
    return [
        (c.topic, s.name, s.encoding, m.log_time) for s, c, m in reader.iter_messages(log_time_order=False)
    ]


@pytest.fixture
def served() -> Iterator[TestClient]:
    with TestClient(create_app(model_free_settings())) as client:
        yield client


def test_the_mcap_of_a_session_has_its_topics_foxglove_schemas_and_a_message_per_version(
    served: TestClient,
) -> None:
    sid = a_session(served)
    response = served.get(f"/v1/sessions/{sid}/recording.mcap")
    assert response.status_code == 200 and response.headers["content-type"] == "application/x-mcap"
    read = messages(response.content)
    topics = Topics(sid)
    schemas = {topic: (name, encoding) for topic, name, encoding, _ in read}
    assert schemas == {
        topics.scene_graph: ("foxglove.SceneUpdate", "protobuf"),
        topics.belief: ("foxglove.PointCloud", "protobuf"),
        topics.estimate: ("foxglove.SceneUpdate", "protobuf"),
        topics.summary: ("vlmap.BeliefSummary", "jsonschema"),
        topics.mixture: ("foxglove.SceneUpdate", "protobuf"),
        topics.utterances: ("foxglove.Log", "protobuf"),
    }
    counts = Counter(topic for topic, *_ in read)
    for name in PER_VERSION:
        assert counts[f"/vlmap/{sid}/{name}"] == 8  # versions 0..7
    assert counts[topics.mixture] == counts[topics.utterances] == 2
    assert counts[topics.scene_graph] == 1
    times = [t for *_, t in read]
    assert times == sorted(times) and times[0] > 0


def test_the_messages_decode_as_foxglove_types_with_the_session_content(served: TestClient) -> None:
    sid = a_session(served)
    data = served.get(f"/v1/sessions/{sid}/recording.mcap").content
    last = last_messages(data)
    logs = [m.message for topic, _, m in decoded_messages(data) if topic.endswith("/utterances")]
    labels = {t.text for e in last["scene_graph"].entities for t in e.texts}
    assert {f"{o['label']} {o['id']}" for o in SCENE["objects"]} <= labels
    cloud = last["belief"]
    assert cloud.point_stride == 20 and len(cloud.data) == 20 * 100  # the 100 top voxels
    assert [f.name for f in cloud.fields][:4] == ["x", "y", "z", "probability"]
    assert any("(w=" in t.text for e in last["mixture"].entities for t in e.texts)
    assert {e.id for e in last["estimate"].entities} == {"map_voxel", "posterior"}
    assert last["summary"]["version"] == 7 and len(last["summary"]["top_voxels"]) == 100
    assert [line.split('"')[1] for line in logs] == list(UTTERANCES)


def test_the_json_recording_pages_by_version_and_the_endpoints_answer_like_the_session(
    served: TestClient,
) -> None:
    sid = a_session(served)
    frames = served.get(f"/v1/sessions/{sid}/recording").json()["frames"]
    assert [f["version"] for f in frames] == list(range(8))
    assert [f["cause"]["kind"] for f in frames[:3]] == ["created", "utterance", "utterance"]
    assert frames[0]["scene_graph"]["objects"] and frames[1]["utterance"]["mixture"]["components"]
    later = served.get(f"/v1/sessions/{sid}/recording", params={"after": 5}).json()["frames"]
    assert [f["version"] for f in later] == [6, 7]
    served.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "the mug is on the desk"})
    unfused = served.get(f"/v1/sessions/{sid}/recording", params={"after": 7}).json()["frames"]
    assert [(f["version"], f["summary"], f["utterance"]["fused"]) for f in unfused] == [(7, None, False)]
    assert served.get("/v1/sessions/nope/recording.mcap").status_code == 404
    assert served.delete(f"/v1/sessions/{sid}").status_code == 204
    assert served.get(f"/v1/sessions/{sid}/recording").status_code == 404


def test_a_long_session_is_thinned_keeping_its_first_frame_and_utterances() -> None:
    frames: list[bytes] = []
    for i in range(1000):
        kind = KEEP if i == 0 or i % 100 == 50 else THIN
        frames = thin([*frames, kind + i.to_bytes(2, "big")], 64)
        assert len(frames) <= 64
    numbers = [int.from_bytes(f[1:], "big") for f in frames]
    assert numbers == sorted(numbers) and numbers[0] == 0 and numbers[-1] == 999
    assert {50, 150, 950} <= set(numbers)
    assert numbers[-5:] == list(range(995, 1000))  # the newest at full rate


@pytest.mark.parametrize(("arrivals", "limit"), [(200, 16), (3000, 256), (20000, 256)])
def test_a_recording_spans_the_whole_session_at_a_resolution_that_halves_with_age(
    arrivals: int, limit: int
) -> None:
    """Re-thinning the same older half at every arrival had left a hole of all but the first and the last
    frames (versions 2-2458 of 3000 gone)."""
    frames: list[bytes] = []
    for i in range(arrivals):
        frames = thin([*frames, (KEEP if i == 0 else THIN) + i.to_bytes(4, "big")], limit)
    numbers = [int.from_bytes(f[1:], "big") for f in frames]
    assert len(numbers) <= limit and numbers[-1] == arrivals - 1
    for older, newer in itertools.pairwise(numbers[1:]):
        age = arrivals - newer
        assert newer - older <= max(4.0, 16 * age / limit * math.log2(arrivals)), (older, newer)


def test_a_replaced_scene_graph_outlives_the_thinning() -> None:
    """The replacement's frame is the only one holding the new graph: thinned away, the recording (and the
    MCAP) showed the first graph for the whole session."""
    client = TestClient(create_app(model_free_settings(recording_frames=8)))
    with client:
        sid = a_session(client)
        replaced = {**SCENE, "objects": [*SCENE["objects"], {**SCENE["objects"][0], "id": "new-desk"}]}
        assert client.put(f"/v1/sessions/{sid}/scene-graph", json=replaced).status_code == 200
        for k in range(40):
            batch = {"voxels": [[k % 5, 1, 1]], "labels": [1]}
            assert client.post(f"/v1/sessions/{sid}/observations", json=batch).status_code == 200
        frames = client.get(f"/v1/sessions/{sid}/recording").json()["frames"]
    graphs = [f["scene_graph"] for f in frames if f["scene_graph"] is not None]
    assert len(graphs) == 2 and "new-desk" in {o["id"] for o in graphs[-1]["objects"]}


def test_merged_frames_keep_one_per_version() -> None:
    summary: dict[str, Any] = {"top_voxels": []}
    first = Frame(3, 1.0, {"kind": "utterance"}, "b", summary, utterance={"text": "x"})
    again = Frame(3, 1.1, {"kind": "observations"}, "b", summary)
    unfused = Frame(3, 1.2, {"kind": "utterance"}, "b", None, utterance={"text": "y"})
    out = merged([again, unfused, first, Frame(2, 0.5, {"kind": "created"}, "b", summary)])
    assert [(f.version, f.summary is None) for f in out] == [(2, False), (3, False), (3, True)]
    assert out[1].utterance == {"text": "x"} and out[1].cause == {"kind": "utterance"}


@pytest.mark.parametrize("store_kind", ["memory", "redis"])
def test_a_store_keeps_the_recording_with_the_session(
    store_kind: str, request: pytest.FixtureRequest
) -> None:
    store: SessionStore | None = None
    if store_kind == "redis":
        url = request.getfixturevalue("redis_url")
        store = RedisSessionStore(url, prefix=f"vlmap-test-rec-{id(request)}")
    settings = model_free_settings(recording_frames=4)
    with TestClient(create_app(settings, store=store)) as client:
        sid = a_session(client)
        frames = client.get(f"/v1/sessions/{sid}/recording").json()["frames"]
        versions = [f["version"] for f in frames]
        assert versions[0] == 0 and versions[-1] == 7 and len(versions) <= 8
        assert {1, 2} <= set(versions)  # the utterances are kept
        assert client.delete(f"/v1/sessions/{sid}").status_code == 204
        if store is not None:
            assert not store._client.exists(store._key(sid, "rec"))
    if store is not None:
        store.close()


def test_the_redis_script_thins_as_the_memory_store_does(redis_url: str) -> None:
    store = RedisSessionStore(redis_url, prefix="vlmap-test-thin")
    try:
        key, meta = store._key("t", "rec"), store._key("t", "meta")
        store._client.delete(key)
        store._client.hset(meta, "version", 0)
        expected: list[bytes] = []
        for i in range(300):
            frame = (KEEP if i % 37 == 0 else THIN) + i.to_bytes(2, "big")
            store._record("t", frame, 16)
            expected = thin([*expected, frame], 16)
        assert store._client.lrange(key, 0, -1) == expected
        store._client.delete(meta)
        store._record("t", THIN + b"late", 16)  # the session is gone: nothing appended
        assert store._client.lrange(key, 0, -1) == expected
    finally:
        store._client.delete(key, meta)
        store.close()


def test_the_preview_draws_the_last_frame(served: TestClient, tmp_path: Path) -> None:
    sid = a_session(served)
    recording = tmp_path / "r.mcap"
    recording.write_bytes(served.get(f"/v1/sessions/{sid}/recording.mcap").content)
    render_png(recording, tmp_path / "r.png")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def batch_frames(client: TestClient, sid: str) -> list[int]:
    frames = client.get(f"/v1/sessions/{sid}/recording").json()["frames"]
    return [f["version"] for f in frames if f["cause"]["kind"] == "observations"]


def streamed_session(client: TestClient, batches: int) -> str:
    """A session sent `batches` observation batches without a summary (the fleet's path): versions 1..n."""
    body = {"robot_id": "r1", "scene_graph": SCENE, "target_label": "backpack", "label_map": LABELS}
    sid = str(client.post("/v1/sessions", json=body).json()["id"])
    for k in range(batches):
        batch = {"voxels": [[k, 1, 1]], "labels": [1]}
        assert client.post(f"/v1/sessions/{sid}/observations?summary=false", json=batch).status_code == 200
    return sid


def eventually(check: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"never: {what}"
        time.sleep(0.05)


def test_batches_without_a_summary_share_one_frame_per_interval() -> None:
    with TestClient(create_app(model_free_settings(recording_interval_s=3600))) as client:
        sid = streamed_session(client, 6)
        eventually(lambda: len(batch_frames(client, sid)) > 0, "the first batch's frame")
        # The first batch is recorded at once; the five after it wait for the next frame, an hour away.
        assert len(batch_frames(client, sid)) == 1


def test_the_frame_that_falls_due_records_the_latest_version() -> None:
    with TestClient(create_app(model_free_settings(recording_interval_s=0.2))) as client:
        sid = streamed_session(client, 6)
        eventually(lambda: batch_frames(client, sid)[-1:] == [6], "a frame of the last version")
        assert batch_frames(client, sid) == sorted(set(batch_frames(client, sid)))
