"""/v1/sessions in process: life cycle, fusion, encodings, ETags, and errors that leave beliefs alone."""

from __future__ import annotations

import json
from typing import Any

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.sessions.batch import encode_msgpack_batch
from app.stores import MemorySessionStore
from app.stores.base import DEFAULT_IDEMPOTENCY_WINDOW_S, pack_array
from tests.conftest import load_resource_json, model_free_settings


@pytest.fixture
def two_rooms() -> dict[str, Any]:
    """Two tables (kitchen t1, living room t2), a counter and a sofa."""
    return load_resource_json("scenes/two_rooms.json")


def _create(client: TestClient, scene_graph: dict, **fields: Any) -> dict[str, Any]:
    response = client.post("/v1/sessions", json={"robot_id": "r7", "scene_graph": scene_graph, **fields})
    assert response.status_code == 201, response.text
    return response.json()


def _grid(client: TestClient, session_id: str, layers: bool = False) -> dict[str, Any]:
    response = client.get(f"/v1/sessions/{session_id}/belief", params={"format": "grid", "layers": layers})
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/msgpack"
    data = msgpack.unpackb(response.content, raw=False)
    out = {"version": data["version"], "etag": response.headers["etag"]}
    for name in ("posterior", "lang", "vis"):
        if name in data:
            packed = data[name]
            out[name] = np.frombuffer(packed["data"], dtype=packed["dtype"]).reshape(packed["shape"])
    return out


def _voxel_of(session: dict[str, Any], point: list[float]) -> list[int]:
    grid = session["grid"]
    return [int((p - o) // grid["voxel_size"]) for p, o in zip(point, grid["min_corner"], strict=True)]


def test_life_cycle(client: TestClient, two_rooms: dict) -> None:
    session = _create(client, two_rooms, target_label="backpack")
    sid = session["id"]
    assert session["version"] == 0 and session["robot_id"] == "r7" and session["target_label"] == "backpack"
    assert session["grid"]["voxel_size"] == 0.1
    assert session["grid"]["n_voxels"] == int(np.prod(session["grid"]["shape"]))
    assert client.get(f"/v1/sessions/{sid}").json() == session
    assert [s["id"] for s in client.get("/v1/sessions", params={"robot_id": "r7"}).json()["sessions"]] == [
        sid
    ]
    assert client.get("/v1/sessions", params={"robot_id": "other"}).json()["sessions"] == []
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
    assert client.get(f"/v1/sessions/{sid}").status_code == 404
    assert client.get(f"/v1/sessions/{sid}/belief").json()["code"] == "not_found"


def test_uniform_prior_then_an_utterance_puts_mass_on_the_tables(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms)["id"]
    prior = client.get(f"/v1/sessions/{sid}/belief").json()
    assert prior["version"] == 0
    assert prior["summary"]["information_gain_nats"] == pytest.approx(0.0, abs=1e-6)
    response = client.post(
        f"/v1/sessions/{sid}/utterances", json={"utterance": "I left my backpack on the table"}
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert {h["anchor_ids"][0] for h in body["grounding"]["hypotheses"]} == {"t1", "t2"}
    belief = body["belief"]
    assert belief["version"] == 1  # the utterance and the target class learnt from it: one update
    assert belief["target_label"] == "backpack"
    assert belief["summary"]["information_gain_nats"] > 2.0
    top_places = {p["id"] for p in belief["summary"]["objects"][:2]}
    assert top_places == {"t1", "t2"}


def test_region_mention_and_repeated_utterances_add_up(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "the backpack is on the table"})
    once = _grid(client, sid, layers=True)
    client.post(
        f"/v1/sessions/{sid}/utterances", json={"utterance": "the backpack is on the table in the kitchen"}
    )
    twice = _grid(client, sid, layers=True)
    assert twice["version"] == 2
    summary = client.get(f"/v1/sessions/{sid}/belief").json()["summary"]
    assert summary["objects"][0]["id"] == "t1"  # the kitchen table now dominates
    assert twice["posterior"].max() > once["posterior"].max()


def test_vision_moves_mass_to_an_observed_target_and_away_from_other_labels(
    client: TestClient, two_rooms: dict
) -> None:
    session = _create(client, two_rooms, target_label="backpack")
    sid = session["id"]
    client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "my backpack is on the table"})
    before = _grid(client, sid)["posterior"]
    on_t1 = _voxel_of(session, [1.5, 0.5, 0.85])
    on_t2 = _voxel_of(session, [-2.0, 1.0, 0.55])
    batch = {"voxels": [on_t1, on_t2], "labels": ["backpack", "table"]}
    response = client.post(f"/v1/sessions/{sid}/observations", json=batch)
    assert response.status_code == 200, response.text
    after = _grid(client, sid)["posterior"]
    shape = tuple(session["grid"]["shape"])
    i1, i2 = np.ravel_multi_index(tuple(on_t1), shape), np.ravel_multi_index(tuple(on_t2), shape)
    assert after[i1] > before[i1]
    assert after[i2] < before[i2]
    assert response.json()["voxels_updated"] == 2


def test_json_and_msgpack_batches_give_identical_beliefs(client: TestClient, two_rooms: dict) -> None:
    rng = np.random.default_rng(3)
    a = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})
    b = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})
    shape = np.array(a["grid"]["shape"])
    voxels = rng.integers(0, shape, size=(500, 3))
    labels = rng.integers(0, 2, size=500)
    points = np.asarray(a["grid"]["min_corner"]) + (voxels + 0.5) * a["grid"]["voxel_size"]
    json_body = {"stamp": 1.5, "voxels": voxels.tolist(), "labels": labels.tolist()}
    r1 = client.post(f"/v1/sessions/{a['id']}/observations", json=json_body)
    packed = encode_msgpack_batch(points=points, labels=labels, stamp=1.5)
    r2 = client.post(
        f"/v1/sessions/{b['id']}/observations",
        content=packed,
        headers={"content-type": "application/msgpack"},
    )
    assert r1.status_code == r2.status_code == 200, (r1.text, r2.text)
    assert r1.json()["stamp"] == r2.json()["stamp"] == 1.5
    np.testing.assert_array_equal(_grid(client, a["id"], True)["vis"], _grid(client, b["id"], True)["vis"])


def test_points_on_voxel_faces_give_the_same_belief_as_json_and_through_the_client_encoder(
    client: TestClient, two_rooms: dict
) -> None:
    """Points on voxel faces, as float64: rounded to float32 some would fall in the neighbouring voxel."""
    rng = np.random.default_rng(5)
    a = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})
    b = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})
    shape = np.array(a["grid"]["shape"])
    faces = rng.integers(1, shape, size=(500, 3))
    points = np.asarray(a["grid"]["min_corner"]) + faces * a["grid"]["voxel_size"]
    labels = rng.integers(0, 2, size=500)
    assert not np.array_equal(points.astype(np.float32).astype(np.float64), points)
    r1 = client.post(
        f"/v1/sessions/{a['id']}/observations", json={"points": points.tolist(), "labels": labels.tolist()}
    )
    r2 = client.post(
        f"/v1/sessions/{b['id']}/observations",
        content=encode_msgpack_batch(points=points, labels=labels),
        headers={"content-type": "application/msgpack"},
    )
    assert r1.status_code == r2.status_code == 200, (r1.text, r2.text)
    np.testing.assert_array_equal(_grid(client, a["id"], True)["vis"], _grid(client, b["id"], True)["vis"])


def test_a_batch_sensor_model_overrides_only_the_rates_it_gives(client: TestClient, two_rooms: dict) -> None:
    """{"tp": 0.9} keeps the session's fp, in JSON as in msgpack."""
    voxels, labels = [[4, 4, 4], [5, 5, 5], [6, 6, 6]], [1, 0, 1]
    beliefs = []
    for encoding, sensor_model in (
        ("json", {"tp": 0.9}),
        ("msgpack", {"tp": 0.9}),
        ("json", {"tp": 0.9, "fp": 0.3}),
    ):
        session = _create(
            client,
            two_rooms,
            target_label="backpack",
            label_map={"0": "floor", "1": "backpack"},
            sensor_model={"tp": 0.8, "fp": 0.3},
        )
        url = f"/v1/sessions/{session['id']}/observations"
        if encoding == "json":
            answer = client.post(url, json={"voxels": voxels, "labels": labels, "sensor_model": sensor_model})
        else:
            packed = encode_msgpack_batch(voxels=np.array(voxels), labels=np.array(labels), **sensor_model)
            answer = client.post(url, content=packed, headers={"content-type": "application/msgpack"})
        assert answer.status_code == 200, answer.text
        beliefs.append(_grid(client, session["id"], True)["vis"])
    np.testing.assert_array_equal(beliefs[0], beliefs[2])
    np.testing.assert_array_equal(beliefs[1], beliefs[2])


def test_a_msgpack_sensor_model_that_is_no_map_is_refused(client: TestClient, two_rooms: dict) -> None:
    session = _create(client, two_rooms, target_label="backpack", label_map={"1": "backpack"})
    points = np.asarray(session["grid"]["min_corner"]) + 0.5 * session["grid"]["voxel_size"]
    envelope = msgpack.unpackb(encode_msgpack_batch(points=points[None], labels=np.array([1])))
    for sensor_model, status in ((None, 200), (False, 422), (0, 422)):
        packed = msgpack.packb(envelope | {"sensor_model": sensor_model})
        answer = client.post(
            f"/v1/sessions/{session['id']}/observations",
            content=packed,
            headers={"content-type": "application/msgpack"},
        )
        assert answer.status_code == status, (sensor_model, answer.text)


def test_an_observation_batch_in_a_json_based_media_type_is_json(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    answer = client.post(
        f"/v1/sessions/{sid}/observations",
        content=json.dumps({"voxels": [[1, 1, 1]], "labels": ["chair"]}),
        headers={"content-type": "application/vnd.robot.batch+json"},
    )
    assert answer.status_code == 200 and answer.json()["voxels_updated"] == 1


def test_etag_and_not_modified(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    first = client.get(f"/v1/sessions/{sid}/belief")
    etag = first.headers["etag"]
    again = client.get(f"/v1/sessions/{sid}/belief", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.content == b""
    client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[1, 1, 1]], "labels": ["chair"]})
    changed = client.get(f"/v1/sessions/{sid}/belief", headers={"If-None-Match": etag})
    assert changed.status_code == 200
    assert changed.headers["etag"] != etag
    assert changed.json()["version"] == 1


def test_if_none_match_compares_weakly_and_star_matches_any_version(
    client: TestClient, two_rooms: dict
) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    etag = client.get(f"/v1/sessions/{sid}/belief").headers["etag"]
    for path in ("belief", "belief/topdown"):
        for given in (f"W/{etag}", "*", f'"other", W/{etag}'):
            answer = client.get(f"/v1/sessions/{sid}/{path}", headers={"If-None-Match": given})
            assert answer.status_code == 304, (path, given)
        other = client.get(f"/v1/sessions/{sid}/{path}", headers={"If-None-Match": 'W/"v9"'})
        assert other.status_code == 200


def test_a_summary_etag_names_its_top_k_so_another_top_k_is_not_a_304(
    client: TestClient, two_rooms: dict
) -> None:
    """The default top_k keeps the documented "v<version>"; a tag held for one top_k is no 304 for another."""
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "I left my backpack on the table"})
    belief = f"/v1/sessions/{sid}/belief"
    assert (
        client.get(belief).headers["etag"]
        == client.get(belief, params={"top_k": 5}).headers["etag"]
        == '"v1"'
    )
    one = client.get(belief, params={"top_k": 1})
    assert one.headers["etag"] == '"v1-k1"' and len(one.json()["summary"]["top_voxels"]) == 1
    ten = client.get(belief, params={"top_k": 10}, headers={"If-None-Match": one.headers["etag"]})
    assert ten.status_code == 200 and len(ten.json()["summary"]["top_voxels"]) == 10
    for held, top_k in (('"v1"', 10), ('"v1-k10"', 5)):
        assert client.get(belief, params={"top_k": top_k}, headers={"If-None-Match": held}).status_code == 200
    for given in ('"v1-k10"', 'W/"v1-k10"', "*"):
        again = client.get(belief, params={"top_k": 10}, headers={"If-None-Match": given})
        assert (again.status_code, again.headers["etag"]) == (304, '"v1-k10"'), given


def test_out_of_grid_voxels_are_counted_not_fatal(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    batch = {"voxels": [[0, 0, 0], [-1, 0, 0], [10_000, 0, 0]], "labels": ["chair"] * 3}
    body = client.post(f"/v1/sessions/{sid}/observations", json=batch).json()
    assert (body["voxels_updated"], body["voxels_outside"]) == (1, 2)
    points = {"points": [[100.0, 0, 0], [1.5, 0.5, 0.9]], "labels": ["chair", "chair"]}
    body = client.post(f"/v1/sessions/{sid}/observations", json=points).json()
    assert (body["voxels_updated"], body["voxels_outside"]) == (1, 1)


def test_detector_probabilities_need_no_target_class(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms)["id"]
    refused = client.post(
        f"/v1/sessions/{sid}/observations", json={"voxels": [[2, 2, 2]], "labels": ["chair"]}
    )
    assert refused.status_code == 409
    assert "target" in refused.json()["message"]
    ok = client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[2, 2, 2]], "p_target": [0.9]})
    assert ok.status_code == 200, ok.text


def _bad_msgpack(**overrides: Any) -> bytes:
    envelope: dict[str, Any] = {
        "voxels": pack_array(np.zeros((2, 3), dtype=np.int32)),
        "labels": pack_array(np.zeros(2, dtype=np.uint32)),
    }
    envelope.update(overrides)
    return msgpack.packb(envelope, use_bin_type=True)


@pytest.mark.parametrize(
    ("content_type", "body", "status", "field"),
    [
        ("application/json", b'{"voxels": [[1, 1, 1]], "labels": ["a", "b"]}', 422, "labels"),
        ("application/json", b'{"points": [[1, NaN, 1]], "labels": ["a"]}', 422, "points"),
        ("application/json", b'{"voxels": [[1, 1, 1]]}', 422, "labels"),
        ("application/json", b'{"voxels": [[1, 1, 1]], "labels": [0], "p_target": [0.2]}', 422, "labels"),
        ("application/json", b'{"voxels": [[1, 1]], "labels": ["a"]}', 422, "voxels.0"),
        ("application/json", b'{"voxels": [[1, 1, 1]], "p_target": [1.5]}', 422, "p_target.0"),
        ("application/json", b"not json", 422, "body"),
        ("application/msgpack", b"\xc1\xc1", 422, "body"),
        ("application/msgpack", _bad_msgpack(labels=pack_array(np.zeros(3, dtype=np.uint32))), 422, "labels"),
        (
            "application/msgpack",
            _bad_msgpack(voxels=pack_array(np.zeros((2, 3), dtype=np.float64))),
            422,
            "voxels.dtype",
        ),
        (
            "application/msgpack",
            _bad_msgpack(voxels={"dtype": "<i4", "shape": [2, 3], "data": b"\x00" * 7}),
            422,
            "voxels.data",
        ),
        (
            "application/msgpack",
            _bad_msgpack(points=pack_array(np.full((2, 3), np.nan, dtype=np.float32))),
            422,
            "voxels",
        ),
        ("application/msgpack", msgpack.packb([1, 2]), 422, "body"),
        ("text/plain", b"hello", 415, "content-type"),
    ],
)
def test_bad_batches_are_rejected_and_leave_the_belief_untouched(
    client: TestClient, two_rooms: dict, content_type: str, body: bytes, status: int, field: str
) -> None:
    sid = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})["id"]
    client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[3, 3, 3]], "labels": [1]})
    before = _grid(client, sid, layers=True)
    response = client.post(
        f"/v1/sessions/{sid}/observations", content=body, headers={"content-type": content_type}
    )
    assert response.status_code == status, response.text
    assert response.json()["field"] == field
    after = _grid(client, sid, layers=True)
    assert after["version"] == before["version"]
    np.testing.assert_array_equal(after["vis"], before["vis"])
    np.testing.assert_array_equal(after["lang"], before["lang"])


def test_unknown_label_ids_are_rejected(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack", label_map={"0": "floor", "1": "backpack"})["id"]
    response = client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[1, 1, 1]], "labels": [7]})
    assert response.status_code == 422
    assert response.json()["field"] == "labels"


def test_replacing_the_scene_graph_affects_later_utterances(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    grown = {
        **two_rooms,
        "objects": [
            *two_rooms["objects"],
            {
                "id": "d1",
                "label": "desk",
                "center": [0.5, -1.5, 0.4],
                "size": [1.0, 0.6, 0.8],
                "region_id": "kitchen",
            },
        ],
    }
    response = client.put(f"/v1/sessions/{sid}/scene-graph", json=grown)
    assert response.status_code == 200, response.text
    assert response.json()["version"] == 1
    body = client.post(
        f"/v1/sessions/{sid}/utterances", json={"utterance": "the backpack is on the desk"}
    ).json()
    assert body["grounding"]["hypotheses"][0]["anchor_ids"] == ["d1"]


def test_session_limits(two_rooms: dict, settings: Any) -> None:
    from app.api.app import create_app

    tight = settings.model_copy(
        update={"max_sessions_per_robot": 2, "max_grid_voxels": 50_000, "max_batch_voxels": 4}
    )
    with TestClient(create_app(tight)) as client:
        coarse = {"voxel_size": 0.2}
        _create(client, two_rooms, grid=coarse)
        _create(client, two_rooms, grid=coarse)
        third = client.post("/v1/sessions", json={"robot_id": "r7", "scene_graph": two_rooms, "grid": coarse})
        assert third.status_code == 429
        assert third.json()["field"] == "max_sessions_per_robot"
        fine = client.post("/v1/sessions", json={"robot_id": "r8", "scene_graph": two_rooms})
        assert fine.status_code == 422
        assert fine.json()["field"] == "max_grid_voxels"  # the setting, as for a grid given by corners
        sid = client.get("/v1/sessions").json()["sessions"][0]["id"]
        batch = {"voxels": [[0, 0, 0]] * 5, "labels": ["a"] * 5}
        big = client.post(f"/v1/sessions/{sid}/observations", json=batch)
        assert big.status_code == 422
        assert big.json()["field"] == "max_batch_voxels"


def test_explicit_grid_bounds(client: TestClient, two_rooms: dict) -> None:
    session = _create(
        client, two_rooms, grid={"voxel_size": 0.25, "min_corner": [-4, -2, 0], "max_corner": [4, 2, 2]}
    )
    assert session["grid"]["shape"] == [32, 16, 8]
    bad = client.post(
        "/v1/sessions",
        json={
            "robot_id": "r7",
            "scene_graph": two_rooms,
            "grid": {"min_corner": [0, 0, 0], "max_corner": [1, -1, 1]},
        },
    )
    assert bad.status_code == 422 and bad.json()["field"] == "grid.max_corner"


def test_method_not_allowed_names_every_allowed_method(client: TestClient) -> None:
    response = client.put("/v1/sessions")
    assert response.status_code == 405
    assert response.headers["allow"] == "GET, POST"
    assert client.post("/v1/sessions/abc").headers["allow"] == "DELETE, GET"
    # Every method named is one the path answers: HEAD is not, so it is not named.
    assert client.head("/v1/sessions").status_code == 405


def test_idle_sessions_expire_and_are_purged(two_rooms: dict, settings: Any) -> None:
    import time

    from app.api.app import create_app

    with TestClient(create_app(settings.model_copy(update={"session_ttl_s": 0.4}))) as client:
        sid = _create(client, two_rooms, target_label="backpack")["id"]
        assert client.get(f"/v1/sessions/{sid}").status_code == 200
        time.sleep(1.2)  # three TTLs: the purge task (every TTL/2) has run several times
        assert client.get(f"/v1/sessions/{sid}").status_code == 404
        assert client.get("/v1/sessions").json()["sessions"] == []
        store = client.app.state.services.store  # type: ignore[attr-defined]
        assert client.portal.call(store.purge_expired) == 0  # type: ignore[union-attr]  # already freed


def test_sensor_rate_batches_may_skip_the_summary(client: TestClient, two_rooms: dict) -> None:
    sid = _create(client, two_rooms, target_label="backpack")["id"]
    batch = {"voxels": [[1, 1, 1]], "labels": ["chair"]}
    body = client.post(f"/v1/sessions/{sid}/observations", params={"summary": "false"}, json=batch).json()
    assert body["belief"] is None and body["version"] == 1
    assert client.post(f"/v1/sessions/{sid}/observations", json=batch).json()["belief"]["version"] == 2


def test_a_watched_session_is_summarised_in_the_background_before_the_next_poll(
    client: TestClient, two_rooms: dict
) -> None:
    import time

    from app.api.schemas import BeliefOut

    sid = _create(client, two_rooms, target_label="backpack")["id"]
    summaries = client.app.state.services.sessions.summaries  # type: ignore[attr-defined]
    batch = {"voxels": [[1, 1, 1]], "labels": ["chair"]}
    client.post(f"/v1/sessions/{sid}/observations", params={"summary": "false"}, json=batch)
    time.sleep(0.2)  # a job, had one started, would have finished
    created_at = client.get(f"/v1/sessions/{sid}").json()["created_at"]
    assert summaries.get(sid, created_at, 1, 5) is None  # nobody reads this belief: nothing summarised
    assert client.get(f"/v1/sessions/{sid}/belief").json()["version"] == 1  # a dashboard starts polling
    for version in (2, 3):
        client.post(f"/v1/sessions/{sid}/observations", params={"summary": "false"}, json=batch)
        deadline = time.monotonic() + 10.0
        while (ready := summaries.get(sid, created_at, version, 5)) is None and time.monotonic() < deadline:
            time.sleep(0.01)  # the background job runs on the app's event loop
        assert ready is not None and ready.version == version
        polled = client.get(f"/v1/sessions/{sid}/belief").json()
        assert polled == BeliefOut.of(ready).model_dump(mode="json")


def test_summary_jobs_run_once_more_for_updates_during_a_job_and_stop_when_unwatched() -> None:
    from app.sessions.summaries import SummaryCache

    now = [0.0]
    cache = SummaryCache(watch_s=10.0, clock=lambda: now[0])
    assert cache.start_job("s") is None  # never read
    cache.watch("s", 5)
    cache.watch("s", 7)
    assert cache.start_job("s") == [5, 7]
    assert cache.start_job("s") is None and cache.start_job("s") is None  # two updates during the job
    assert cache.end_job("s")  # ...make it run once more
    assert not cache.end_job("s")  # and then it is over
    assert cache.start_job("s") == [5, 7]
    assert not cache.end_job("s")
    now[0] = 11.0  # no read for longer than watch_s
    assert cache.start_job("s") is None


def _say(client: TestClient, session_id: str, utterance: str) -> dict[str, Any]:
    response = client.post(f"/v1/sessions/{session_id}/utterances", json={"utterance": utterance})
    assert response.status_code == 200, response.text
    return response.json()


def test_an_utterance_about_another_class_is_answered_not_fused(
    client: TestClient, scene_graph_dict: dict
) -> None:
    sid = _create(client, scene_graph_dict, target_label="keys")["id"]
    first = _say(client, sid, "my keys are on the desk")
    assert (first["fused"], first["reason"]) == (True, None)
    before = _grid(client, sid, layers=True)
    body = _say(client, sid, "the mug is on the desk")
    assert body["fused"] is False
    assert "'mug'" in body["reason"] and "'keys'" in body["reason"]
    # The grounding is there for inspection; the belief is the one before, to the bit.
    assert body["grounding"]["grounded"] is True and body["grounding"]["target"] == {"label": "mug"}
    desk = next(o["id"] for o in scene_graph_dict["objects"] if o["label"] == "desk")
    assert body["grounding"]["hypotheses"][0]["anchor_ids"] == [desk]
    assert body["belief"]["version"] == before["version"] == 1
    assert body["belief"]["target_label"] == "keys"
    after = _grid(client, sid, layers=True)
    assert after["version"] == before["version"]
    np.testing.assert_array_equal(after["lang"], before["lang"])
    np.testing.assert_array_equal(after["vis"], before["vis"])
    assert client.get(f"/v1/sessions/{sid}").json()["version"] == 1


@pytest.mark.parametrize(
    ("target_label", "utterance"),
    [
        ("backpack", "my bag is on the table"),  # a generic word naming the target's class loosely
        ("keychain", "the keys are on the table"),  # a synonym
        ("backpack", "my black backpack is on the table"),  # the same head noun
        ("backpack", "it is on the table"),  # names no object
        ("backpack", "something is on the table"),
    ],
)
def test_namings_of_the_target_class_and_phrases_naming_no_object_fuse(
    client: TestClient, two_rooms: dict, target_label: str, utterance: str
) -> None:
    sid = _create(client, two_rooms, target_label=target_label)["id"]
    before = _grid(client, sid, layers=True)
    body = _say(client, sid, utterance)
    assert (body["fused"], body["reason"]) == (True, None)
    assert body["belief"]["version"] == 1 and body["belief"]["target_label"] == target_label
    assert {h["anchor_ids"][0] for h in body["grounding"]["hypotheses"]} == {"t1", "t2"}
    assert not np.array_equal(_grid(client, sid, layers=True)["lang"], before["lang"])


def test_an_ungroundable_utterance_fuses_its_broad_prior_and_says_so(
    client: TestClient, two_rooms: dict
) -> None:
    sid = _create(client, two_rooms, target_label="keys")["id"]
    before = _grid(client, sid, layers=True)
    body = _say(client, sid, "the keys are next to the spaceship")
    grounding = body["grounding"]
    assert grounding["grounded"] is False and "spaceship" in grounding["reason"]
    assert grounding["hypotheses"] == []
    assert all(c["hypothesis"] is None for c in grounding["mixture"]["components"])
    assert body["fused"] is True
    assert "broad prior" in body["reason"] and "spaceship" in body["reason"]
    assert body["belief"]["version"] == 1
    assert not np.array_equal(_grid(client, sid, layers=True)["lang"], before["lang"])


def test_a_replayed_utterance_repeats_its_first_verdict(client: TestClient, two_rooms: dict) -> None:
    """Retried after another utterance named the session's target, a fused utterance is still told fused."""
    sid = _create(client, two_rooms, label_map={"1": "backpack"})["id"]
    url, key = f"/v1/sessions/{sid}/utterances", {"Idempotency-Key": "utterance-1"}
    first = client.post(url, json={"utterance": "the mug is on the table"}, headers=key).json()
    assert first["fused"] is True and first["belief"]["version"] == 1
    assert _say(client, sid, "my backpack is on the sofa")["belief"]["target_label"] == "backpack"
    retry = client.post(url, json={"utterance": "the mug is on the table"}, headers=key)
    assert retry.headers["idempotent-replayed"] == "true"
    assert (retry.json()["fused"], retry.json()["reason"]) == (True, first["reason"])


def test_a_generic_naming_of_the_target_fuses(client: TestClient, two_rooms: dict) -> None:
    """People say "the chair" for an armchair and "the blue bin" for a trash can: a looser naming."""
    for target, utterance in (
        ("armchair", "the chair is next to the table"),
        ("trash can", "the blue bin is by the table"),
    ):
        sid = _create(client, two_rooms, target_label=target)["id"]
        body = _say(client, sid, utterance)
        assert body["fused"] is True, (target, body["reason"])


def test_an_unset_target_is_still_learnt_from_the_first_utterance_naming_a_class(
    client: TestClient, two_rooms: dict
) -> None:
    sid = _create(client, two_rooms)["id"]
    body = _say(client, sid, "the mug is on the table")
    assert (body["fused"], body["reason"]) == (True, None)
    assert body["belief"]["target_label"] == "mug" and body["belief"]["version"] == 1
    refused = _say(client, sid, "my backpack is on the sofa")
    assert refused["fused"] is False and refused["belief"]["version"] == 1


def test_the_belief_fuses_exactly_the_served_density_boxes_included(two_rooms: dict) -> None:
    from app.api.app import create_app
    from app.belief.fusion import LayerLimits
    from app.belief.grid import VoxelGrid
    from app.grounding.mixture import GaussianMixture
    from tests.conftest import model_free_settings
    from tests.test_api_ground import boxed_sensors, served_mixture

    with TestClient(create_app(model_free_settings(), sensors=boxed_sensors())) as client:
        session = _create(client, two_rooms, target_label="backpack")
        body = _say(client, session["id"], "my backpack is on the table")
        mixture = body["grounding"]["mixture"]
        assert len(mixture["uniform"]) == 4 and body["fused"] is True  # the hypotheses' two, the broad term's
        lang = _grid(client, session["id"], layers=True)["lang"]
    grid = session["grid"]
    centers = VoxelGrid(tuple(grid["min_corner"]), tuple(grid["shape"]), grid["voxel_size"]).centers()
    log_likelihood = served_mixture(mixture).logpdf(centers)
    expected = np.maximum(log_likelihood - log_likelihood.max(), -LayerLimits().lang_span)
    np.testing.assert_allclose(lang, expected, atol=1e-4)
    # Not the Gaussians' alone: somewhere the boxes raise the density by more than a factor e.
    served = served_mixture(mixture)
    gaussians = GaussianMixture(served.weights, served.means, served.covariances).logpdf(centers)
    assert np.max(log_likelihood - gaussians) > 1.0


def test_a_session_made_again_under_its_id_is_not_served_the_earlier_ones_summary(two_rooms: dict) -> None:
    now = [1000.0]
    store = MemorySessionStore(clock=lambda: now[0])
    body = {"robot_id": "r7", "scene_graph": two_rooms, "target_label": "backpack"}
    made = {"Idempotency-Key": "mission-1"}
    with TestClient(create_app(model_free_settings(), store=store)) as client:
        sid = client.post("/v1/sessions", json=body, headers=made).json()["id"]
        client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[1, 1, 1]], "labels": ["backpack"]})
        first = client.get(f"/v1/sessions/{sid}/belief")
        assert client.delete(f"/v1/sessions/{sid}").status_code == 204
        now[0] += 2 * DEFAULT_IDEMPOTENCY_WINDOW_S  # the creation's key is forgotten: the same id again
        assert client.post("/v1/sessions", json=body, headers=made).json()["id"] == sid
        client.post(f"/v1/sessions/{sid}/observations", json={"voxels": [[9, 9, 9]], "labels": ["backpack"]})
        second = client.get(f"/v1/sessions/{sid}/belief")
        assert second.json()["version"] == first.json()["version"] == 1
        map_voxel = second.json()["summary"]["map_voxel"]
        assert map_voxel != first.json()["summary"]["map_voxel"]
        posterior = _grid(client, sid)["posterior"]
        assert map_voxel["index"] == int(np.argmax(posterior))


@pytest.mark.parametrize("limit", [20, 2000])
def test_utterances_are_as_long_as_the_setting_allows(two_rooms: dict, limit: int) -> None:
    with TestClient(create_app(model_free_settings(max_utterance_chars=limit))) as client:
        sid = _create(client, two_rooms, target_label="backpack")["id"]
        for length, allowed in ((limit, True), (limit + 1, False)):
            text = ("the backpack is on the table " * 100)[:length]
            said = client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": text})
            grounded = client.post("/v1/ground", json={"utterance": text, "scene_graph": two_rooms})
            for answer in (said, grounded):
                assert (answer.status_code == 200) is allowed, answer.text
                if not allowed:
                    assert answer.status_code == 422 and answer.json()["field"] == "utterance"


def test_a_label_id_given_twice_in_two_spellings_is_a_422(client: TestClient, two_rooms: dict) -> None:
    body = {"robot_id": "r7", "scene_graph": two_rooms, "target_label": "floor"}
    answer = client.post("/v1/sessions", json={**body, "label_map": {"7": "backpack", "007": "floor"}})
    assert answer.status_code == 422 and answer.json()["field"] == "label_map.007"
    assert client.get("/v1/sessions").json()["sessions"] == []
