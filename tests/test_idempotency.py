"""Idempotency-Key on every state-changing session endpoint, on every store: the same key with the same
request is answered again and applied once; with another request it is a 422; keys survive a restart of the
memory store (its log and snapshots) and are bounded in number and age. The kill -9 and Redis failover runs
are in tests/test_sessions_processes.py and tests/test_redis_cluster.py."""

from __future__ import annotations

import hashlib
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.errors import AlreadyApplied
from app.sessions.batch import encode_msgpack_batch
from app.stores import MemorySessionStore
from app.stores.base import Idempotency, IdempotencyLog, IdempotencyRecord
from tests.conftest import load_resource_json, model_free_settings
from tests.store_ops import StoreOps
from tests.test_stores import make_session, redis_store, wide_mixture

MSGPACK = {"content-type": "application/msgpack"}


@pytest.fixture(params=["memory", pytest.param("redis", marks=pytest.mark.redis)])
def client(request: pytest.FixtureRequest) -> Iterator[TestClient]:
    store = (
        MemorySessionStore()
        if request.param == "memory"
        else redis_store(request.getfixturevalue("redis_url")).store
    )
    with TestClient(create_app(model_free_settings(), store=store)) as test_client:
        yield test_client
    store.close()


def key() -> dict[str, str]:
    return {"Idempotency-Key": uuid.uuid4().hex}


def create(client: TestClient, headers: dict[str, Any] | None = None, robot: str = "r") -> Any:
    body = {
        "robot_id": robot,
        "scene_graph": load_resource_json("scenes/two_rooms.json"),
        "target_label": "backpack",
        "label_map": {"0": "floor", "1": "backpack"},
        "grid": {"voxel_size": 0.25},
    }
    return client.post("/v1/sessions", json=body, headers=headers or {})


def layers(client: TestClient, sid: str) -> tuple[int, str]:
    grid = client.get(f"/v1/sessions/{sid}/belief", params={"format": "grid", "layers": "true"})
    return msgpack.unpackb(grid.content)["version"], hashlib.sha256(grid.content).hexdigest()


def test_a_batch_sent_twice_with_its_key_is_applied_once(client: TestClient) -> None:
    sid = create(client).json()["id"]
    batch = encode_msgpack_batch(voxels=np.array([[1, 1, 1], [2, 2, 2]]), labels=np.array([1, 0]), stamp=7.0)
    headers = {**MSGPACK, **key()}
    first = client.post(f"/v1/sessions/{sid}/observations", content=batch, headers=headers)
    after_first = layers(client, sid)
    again = client.post(f"/v1/sessions/{sid}/observations", content=batch, headers=headers)
    assert first.status_code == again.status_code == 200
    assert "idempotent-replayed" not in first.headers and again.headers["idempotent-replayed"] == "true"
    for field in ("version", "stamp", "voxels_updated", "voxels_outside"):
        assert again.json()[field] == first.json()[field]
    assert layers(client, sid) == after_first  # not applied twice
    other = encode_msgpack_batch(voxels=np.array([[3, 3, 3]]), labels=np.array([1]))
    reused = client.post(f"/v1/sessions/{sid}/observations", content=other, headers=headers)
    assert reused.status_code == 422 and reused.json()["code"] == "idempotency_key_reused"
    assert layers(client, sid) == after_first


def test_json_batches_and_utterances_are_applied_once(client: TestClient) -> None:
    sid = create(client).json()["id"]
    headers = key()
    batch = {"voxels": [[1, 2, 3]], "labels": ["backpack"]}
    first = client.post(f"/v1/sessions/{sid}/observations", json=batch, headers=headers)
    again = client.post(f"/v1/sessions/{sid}/observations", json=batch, headers=headers)
    assert again.json()["version"] == first.json()["version"] == 1
    said = key()
    utterance = {"utterance": "the backpack is on the table"}
    one = client.post(f"/v1/sessions/{sid}/utterances", json=utterance, headers=said)
    two = client.post(f"/v1/sessions/{sid}/utterances", json=utterance, headers=said)
    assert one.status_code == two.status_code == 200 and two.headers["idempotent-replayed"] == "true"
    assert one.json()["grounding"] == two.json()["grounding"]
    assert two.json()["fused"] and two.json()["belief"]["version"] == 2  # once
    assert layers(client, sid)[0] == 2


def test_creation_scene_graph_and_deletion_are_applied_once(client: TestClient) -> None:
    headers = key()
    first, again = create(client, headers), create(client, headers)
    assert first.status_code == again.status_code == 201 and first.json()["id"] == again.json()["id"]
    assert again.headers["idempotent-replayed"] == "true"
    assert len(client.get("/v1/sessions", params={"robot_id": "r"}).json()["sessions"]) == 1
    assert create(client, headers, robot="r-other").json()["id"] != first.json()["id"]  # keys are per robot
    sid = first.json()["id"]
    graph = load_resource_json("scenes/two_rooms.json")
    put = key()
    assert client.put(f"/v1/sessions/{sid}/scene-graph", json=graph, headers=put).json()["version"] == 1
    replayed = client.put(f"/v1/sessions/{sid}/scene-graph", json=graph, headers=put)
    assert replayed.headers["idempotent-replayed"] == "true" and replayed.json()["version"] == 1
    gone = key()
    assert client.delete(f"/v1/sessions/{sid}", headers=gone).status_code == 204
    repeat = client.delete(f"/v1/sessions/{sid}", headers=gone)
    assert repeat.status_code == 204 and repeat.headers["idempotent-replayed"] == "true"
    assert (
        client.delete(f"/v1/sessions/{sid}", headers=key()).status_code == 404
    )  # a new delete: nothing there


def test_a_key_an_update_used_is_refused_for_an_utterance_that_is_not_fused(client: TestClient) -> None:
    sid = create(client).json()["id"]
    said = key()
    first = {"utterance": "the backpack is on the table"}
    assert client.post(f"/v1/sessions/{sid}/utterances", json=first, headers=said).json()["fused"]
    other = {"utterance": "the mug is on the desk"}  # names another class than the target: not fused
    reused = client.post(f"/v1/sessions/{sid}/utterances", json=other, headers=said)
    assert reused.status_code == 422 and reused.json()["code"] == "idempotency_key_reused"
    assert client.post(f"/v1/sessions/{sid}/utterances", json=other, headers=key()).json()["fused"] is False
    said = [u["utterance"] for u in client.get(f"/v1/sessions/{sid}/utterances").json()["utterances"]]
    assert said == ["the backpack is on the table", "the mug is on the desk"]  # the refused one not announced


@pytest.mark.parametrize("keyed_delete", [False, True])
def test_a_creation_retried_after_its_session_was_deleted_is_not_applied_again(
    client: TestClient, keyed_delete: bool
) -> None:
    made = key()
    sid = create(client, made).json()["id"]
    batch = {"voxels": [[1, 2, 3]], "labels": ["backpack"]}
    assert client.post(f"/v1/sessions/{sid}/observations", json=batch).json()["version"] == 1
    assert client.delete(f"/v1/sessions/{sid}", headers=key() if keyed_delete else {}).status_code == 204
    again = create(client, made)
    assert again.status_code == 404 and again.json()["code"] == "not_found"
    assert client.get(f"/v1/sessions/{sid}").status_code == 404  # not made again


@pytest.mark.parametrize("kind", ["memory", pytest.param("redis", marks=pytest.mark.redis)])
def test_a_retried_creation_of_a_deleted_session_takes_none_of_the_robots_slots(
    request: pytest.FixtureRequest, kind: str
) -> None:
    """The retry is a 404, even when the robot is at its limit, and leaves the limit's slots free."""
    store = (
        MemorySessionStore() if kind == "memory" else redis_store(request.getfixturevalue("redis_url")).store
    )
    with TestClient(create_app(model_free_settings(max_sessions_per_robot=2), store=store)) as client:
        made = key()
        sid = create(client, made).json()["id"]
        assert client.delete(f"/v1/sessions/{sid}").status_code == 204
        assert create(client, made).status_code == 404
        assert [create(client).status_code for _ in range(2)] == [201, 201]
        assert create(client, made).status_code == 404  # at the limit: still the final answer
    store.close()


@pytest.mark.parametrize("bad", [b"", b" ", "é".encode() * 4, b"k" * 256, b'""', b"a\x7fb"])
def test_a_malformed_key_is_a_422(client: TestClient, bad: bytes) -> None:
    response = create(client, {"Idempotency-Key": bad})
    assert response.status_code == 422 and response.json()["field"] == "Idempotency-Key"


def test_the_quoted_form_of_a_key_is_the_same_key(client: TestClient) -> None:
    token = uuid.uuid4().hex
    assert (
        create(client, {"Idempotency-Key": token}).json()["id"]
        == create(client, {"Idempotency-Key": f'"{token}"'}).json()["id"]
    )


# -- the stores -------------------------------------------------------------------------------------------


def test_keys_survive_reopening_the_log_and_its_snapshots(tmp_path: Path) -> None:
    data = tmp_path / "data"
    store = StoreOps(MemorySessionStore(data, snapshot_every=3))
    store.create(make_session("s"))
    rng = np.random.default_rng(0)
    keys = [Idempotency(f"k{i}", f"fp{i}") for i in range(6)]
    for i, k in enumerate(keys[:5]):
        result = store.utter("s", wide_mixture(rng), idempotency=k)  # compactions happen in between
        assert result.version == i + 1
    store.create(make_session("gone", robot_id="robot-2"))
    store.delete("gone", idempotency=keys[5])
    store.close()
    reopened = StoreOps(MemorySessionStore(data, snapshot_every=3))
    for i, k in enumerate(keys[:5]):
        with pytest.raises(AlreadyApplied) as seen:
            reopened.utter("s", wide_mixture(rng), idempotency=k)
        record = seen.value.record
        assert isinstance(record, IdempotencyRecord)
        assert (record.fingerprint, record.version, record.robot_id) == (k.fingerprint, i + 1, "robot-1")
    with pytest.raises(AlreadyApplied) as seen:
        reopened.delete("gone", idempotency=keys[5])  # the tombstone
    assert seen.value.record.robot_id == "robot-2"  # type: ignore[attr-defined]  # the deleted session's owner
    assert reopened.get("s").version == 5
    reopened._compact()  # the tombstone is logged again before the old segments go
    reopened.close()
    again = StoreOps(MemorySessionStore(data))
    with pytest.raises(AlreadyApplied):
        again.delete("gone", idempotency=keys[5])
    again.close()


def test_tombstones_past_their_window_are_dropped_without_a_data_directory() -> None:
    now = [1000.0]
    store = StoreOps(MemorySessionStore(None, idempotency_window_s=10.0, clock=lambda: now[0]))
    for i in range(5):
        store.create(make_session(f"s{i}"), idempotency=Idempotency(f"made{i}", "fp"))
        store.delete(f"s{i}")
    assert len(store.store._tombstones) == 5
    now[0] += 11.0
    store.create(make_session("late"), idempotency=Idempotency("made-late", "fp"))
    store.delete("late")
    assert list(store.store._tombstones) == ["late"]
    with pytest.raises(AlreadyApplied):
        store.create(make_session("late"), idempotency=Idempotency("made-late", "fp"))
    store.close()


@pytest.mark.parametrize("kind", ["memory", pytest.param("redis", marks=pytest.mark.redis)])
def test_a_key_past_its_window_is_forgotten_alike_by_every_store(
    request: pytest.FixtureRequest, kind: str
) -> None:
    """Redis had kept a key until another keyed write pruned it: a late retry replayed there, applied here."""
    now = [time.time()]
    options: dict[str, Any] = {"idempotency_window_s": 10.0, "clock": lambda: now[0]}
    if kind == "memory":
        store = StoreOps(MemorySessionStore(None, **options))
    else:
        store = redis_store(request.getfixturevalue("redis_url"), **options)
    store.create(make_session("s"))
    key = Idempotency("k", "fp")
    assert store.detect("s", [0.6], flat_idx=np.array([1]), idempotency=key).version == 1
    with pytest.raises(AlreadyApplied):
        store.detect("s", [0.6], flat_idx=np.array([1]), idempotency=key)
    made = Idempotency("made", "fp")
    store.create(make_session("gone"), idempotency=made)
    store.delete("gone")
    with pytest.raises(AlreadyApplied):
        store.create(make_session("gone"), idempotency=made)  # the tombstone
    now[0] += 11.0
    assert store.detect("s", [0.6], flat_idx=np.array([1]), idempotency=key).version == 2  # forgotten
    assert store.create(make_session("gone"), idempotency=made).id == "gone"  # made again
    store.close()


def test_a_session_remembers_its_last_keys_within_the_window() -> None:
    log = IdempotencyLog(window_s=10.0, max_keys=3)
    for i in range(5):
        log.add(f"k{i}", IdempotencyRecord("fp", i, at=float(i)))
    assert [k for k, _ in log.items()] == ["k2", "k3", "k4"]
    log.add("late", IdempotencyRecord("fp", 9, at=100.0))
    assert [k for k, _ in log.items()] == ["late"]  # the others are older than the window
    log.check(Idempotency("k2", "fp"), now=100.0)  # forgotten: no AlreadyApplied
    with pytest.raises(AlreadyApplied):
        log.check(Idempotency("late", "fp"), now=105.0)


@pytest.mark.redis
def test_redis_keys_are_bounded_per_session_and_a_delete_leaves_them_and_its_own(redis_url: str) -> None:
    store = redis_store(redis_url, idempotency_keys=4)
    store.create(make_session("bounded"))
    for i in range(10):
        store.detect("bounded", [0.6], flat_idx=np.array([i]), idempotency=Idempotency(f"k{i}", "fp"))
    remembered = store._client.hkeys(store._key("bounded", "idem"))
    assert len(remembered) == 4 and b"k:k9" in remembered
    with pytest.raises(AlreadyApplied) as seen:
        store.detect("bounded", [0.6], flat_idx=np.array([9]), idempotency=Idempotency("k9", "fp"))
    assert seen.value.record.robot_id == "robot-1"  # type: ignore[attr-defined]  # the session's owner
    assert store.head("bounded").version == 10  # not applied again
    store.delete("bounded", idempotency=Idempotency("bye", "fp"))
    tombstone = {b"k:k6", b"k:k7", b"k:k8", b"k:k9", b"k:bye"}
    assert set(store._client.hkeys(store._key("bounded", "idem"))) == tombstone
    assert 0 < store._client.pttl(store._key("bounded", "idem")) <= 3600 * 1000
    with pytest.raises(AlreadyApplied) as seen:
        store.delete("bounded", idempotency=Idempotency("bye", "fp"))
    assert seen.value.record.robot_id == "robot-1"  # type: ignore[attr-defined]  # the deleted session's owner
    store.close()


@pytest.mark.redis
def test_redis_commits_without_a_key_never_push_a_clients_key_out(redis_url: str) -> None:
    store = redis_store(redis_url, idempotency_keys=3)
    store.create(make_session("crowded"))
    store.detect("crowded", [0.6], flat_idx=np.array([1]), idempotency=Idempotency("mine", "fp"))
    for i in range(5):  # keyless commits: each records its own commit id
        store.detect("crowded", [0.6], flat_idx=np.array([i]))
    with pytest.raises(AlreadyApplied):
        store.detect("crowded", [0.6], flat_idx=np.array([1]), idempotency=Idempotency("mine", "fp"))
    assert store.head("crowded").version == 6  # the retry was not applied
    assert store._client.zcard(store._key("crowded", "commits")) == 3  # commit ids are bounded too
    store.close()
