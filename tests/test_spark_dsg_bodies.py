"""Spark-DSG binary bodies on PUT .../scene-graph, POST /v1/sessions and POST /v1/ground: the same answers as
the JSON form of the same graph, the other fields from the query string, the decoder's rate shared with
/normalize, and a malformed binary a 4xx that leaves the session as it was."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.client import VLMapClient
from app.scene_graph.hydra import parse_spark_dsg_binary
from app.scene_graph.model import SceneGraph
from tests.conftest import model_free_settings
from tests.test_events import served
from tests.test_scene_graph_formats import hydra_binary

BINARY = {"content-type": "application/x-spark-dsg"}
GRID = {"voxel_size": 0.25}
# Not the session's own fields: the ones that differ between any two sessions.
_OWN = ("id", "created_at", "updated_at")


def normalised(client: TestClient, payload: bytes) -> dict[str, Any]:
    response = client.post("/v1/scene-graphs/normalize", content=payload, headers=BINARY)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


def stored(client: TestClient, session_id: str) -> SceneGraph:
    store = client.app.state.services.store  # type: ignore[attr-defined]
    graph: SceneGraph = client.portal.call(store.head_and_scene_graph, session_id)[1]
    return graph


def without(answer: dict[str, Any], *names: str) -> dict[str, Any]:
    return {k: v for k, v in answer.items() if k not in names}


def test_the_three_endpoints_answer_a_binary_body_as_its_json_form(client: TestClient) -> None:
    payload = hydra_binary()
    native = normalised(client, payload)
    assert native == parse_spark_dsg_binary(payload).model_dump(mode="json")

    as_json = client.post("/v1/sessions", json={"robot_id": "r7", "scene_graph": native, "grid": GRID})
    as_binary = client.post(
        "/v1/sessions", content=payload, headers=BINARY, params={"robot_id": "r7", "grid": json.dumps(GRID)}
    )
    assert as_json.status_code == as_binary.status_code == 201, as_binary.text
    assert without(as_binary.json(), *_OWN) == without(as_json.json(), *_OWN)
    json_id, binary_id = as_json.json()["id"], as_binary.json()["id"]
    assert stored(client, binary_id) == stored(client, json_id) == SceneGraph.model_validate(native)

    put_json = client.put(f"/v1/sessions/{json_id}/scene-graph", json=native)
    put_binary = client.put(f"/v1/sessions/{binary_id}/scene-graph", content=payload, headers=BINARY)
    assert put_json.status_code == put_binary.status_code == 200, put_binary.text
    assert without(put_binary.json(), *_OWN) == without(put_json.json(), *_OWN)
    assert stored(client, binary_id) == stored(client, json_id)

    options = {"grounder": "geometric"}
    fields = {"utterance": "the mug near the table", "options": options, "query_points": [[1.6, 0.4, 1.0]]}
    ground_json = client.post("/v1/ground", json={"scene_graph": native, **fields})
    query = {**fields, "options": json.dumps(options), "query_points": json.dumps(fields["query_points"])}
    ground_binary = client.post("/v1/ground", content=payload, headers=BINARY, params=query)
    assert ground_json.status_code == ground_binary.status_code == 200, ground_binary.text
    assert ground_binary.json()["hypotheses"], "the utterance should ground in this graph"
    assert without(ground_binary.json(), "timings_ms") == without(ground_json.json(), "timings_ms")


def session_state(client: TestClient, session_id: str) -> tuple[int, SceneGraph]:
    return client.get(f"/v1/sessions/{session_id}").json()["version"], stored(client, session_id)


@pytest.mark.parametrize(
    "payload",
    [
        hydra_binary()[:-40],  # truncated: spark_dsg refuses it
        bytes([0xDD, 0xFF, 0xFF, 0, 0]) + b"\0" * 64,  # declares more layers than it holds
        b"\x00garbage",
    ],
    ids=["truncated", "bad-length", "not-spark-dsg"],
)
def test_a_malformed_binary_is_a_4xx_and_changes_nothing(client: TestClient, payload: bytes) -> None:
    session = client.post("/v1/sessions", content=hydra_binary(), headers=BINARY, params={"robot_id": "r7"})
    assert session.status_code == 201, session.text
    sid = session.json()["id"]
    before = session_state(client, sid)

    put = client.put(f"/v1/sessions/{sid}/scene-graph", content=payload, headers=BINARY)
    assert put.status_code == 422 and "Spark-DSG" in put.json()["message"], put.text
    assert session_state(client, sid) == before
    create = client.post("/v1/sessions", content=payload, headers=BINARY, params={"robot_id": "r7"})
    assert create.status_code == 422
    assert [s["id"] for s in client.get("/v1/sessions").json()["sessions"]] == [sid]
    ground = client.post("/v1/ground", content=payload, headers=BINARY, params={"utterance": "the mug"})
    assert ground.status_code == 422


def test_query_fields_go_with_a_binary_body_only_and_are_checked_like_the_json_ones(
    client: TestClient,
) -> None:
    native = normalised(client, hydra_binary())
    beside_json = client.post(
        "/v1/sessions", json={"robot_id": "r7", "scene_graph": native}, params={"grid": "{}"}
    )
    assert beside_json.status_code == 422 and beside_json.json()["field"] == "grid"
    not_json = client.post(
        "/v1/sessions", content=hydra_binary(), headers=BINARY, params={"robot_id": "r7", "grid": "{voxel"}
    )
    assert not_json.status_code == 422 and not_json.json()["field"] == "grid"
    bad_id = client.post("/v1/sessions", content=hydra_binary(), headers=BINARY, params={"robot_id": "r 7"})
    assert bad_id.status_code == 422 and bad_id.json()["field"] == "robot_id"
    missing = client.post("/v1/ground", content=hydra_binary(), headers=BINARY)
    assert missing.status_code == 422 and missing.json()["field"] == "utterance"
    text = client.post("/v1/sessions", content=b"x", headers={"content-type": "text/plain"})
    assert text.status_code == 415


def test_every_binary_body_spends_the_same_decode_rate_as_normalize() -> None:
    settings = model_free_settings(decode_rate_per_s=0.001, decode_rate_burst=2)
    with TestClient(create_app(settings)) as client:
        payload = hydra_binary()
        normalised(client, payload)
        session = client.post("/v1/sessions", content=payload, headers=BINARY, params={"robot_id": "r7"})
        assert session.status_code == 201
        sid = session.json()["id"]
        refused = client.put(f"/v1/sessions/{sid}/scene-graph", content=payload, headers=BINARY)
        assert refused.status_code == 429 and refused.json()["field"] == "decode_rate"
        ground = client.post("/v1/ground", content=payload, headers=BINARY, params={"utterance": "the mug"})
        assert ground.status_code == 429
        # A bad field is refused before any decode: a 422, not the 429 that a decode would get now.
        bad = client.post("/v1/sessions", content=payload, headers=BINARY, params={"robot_id": "r 7"})
        assert bad.status_code == 422


def test_the_client_sends_bytes_as_a_binary_body() -> None:
    payload = hydra_binary()
    native = parse_spark_dsg_binary(payload).model_dump(mode="json")
    with served(model_free_settings()) as server, VLMapClient(server.url) as vl:
        session = vl.create_session("r7", payload, grid=GRID, target_label="mug")
        twin = vl.create_session("r7", native, grid=GRID, target_label="mug")
        assert without(session, *_OWN) == without(twin, *_OWN)
        assert vl.replace_scene_graph(session["id"], payload)["version"] == session["version"] + 1
        grounded = vl.ground(payload, "the mug", options={"grounder": "geometric"})
        assert without(grounded, "timings_ms") == without(
            vl.ground(native, "the mug", options={"grounder": "geometric"}), "timings_ms"
        )
