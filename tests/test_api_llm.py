"""The LLM parts through the API, against a real fake chat-completions server on 127.0.0.1."""

from __future__ import annotations

import json

from fastapi.testclient import TestClient

from app.api.app import create_app
from app.settings import Settings
from tests.conftest import load_resource_json
from tests.fake_llm_server import FakeLLMServer, Reply


def _settings(server: FakeLLMServer) -> Settings:
    return Settings(  # type: ignore[call-arg]
        _env_file=None,
        log_json=False,
        data_dir=None,
        llm_url=server.base_url,
        llm_model="fake",
        llm_timeout_s=1.0,
    )


def test_llm_proposer_hypotheses_reach_the_answer_and_failures_fall_back_and_are_counted() -> None:
    scene = load_resource_json("scenes/two_rooms.json")
    body = {"scene_graph": scene, "utterance": "my backpack is on the table", "options": {"proposer": "llm"}}
    reply = {
        "hypotheses": [
            {
                "utterance": "there is a backpack on the table",
                "referred_object_id": ["t2"],
                "region_id": 1,
                "confidence": 0.9,
            },
        ]
    }
    with FakeLLMServer() as server, TestClient(create_app(_settings(server))) as client:
        models = {(m["role"], m["name"]) for m in client.get("/v1/models").json()["models"]}
        assert {("proposer", "llm"), ("grounder", "scaffolded-llm"), ("grounder", "llm-e2e")} <= models
        server.script(Reply(content=json.dumps(reply)))
        answer = client.post("/v1/ground", json=body).json()
        assert [h["anchor_ids"] for h in answer["hypotheses"]] == [["t2"]]
        assert (
            "the region-grouped" not in server.requests[0].body["messages"][0]["content"][:0]
        )  # sent as chat
        server.script(*[Reply(body="not json at all")] * 3)
        fallback = client.post("/v1/ground", json=body).json()
        anchored = {a for h in fallback["hypotheses"] for a in h["anchor_ids"]}
        assert {"t1", "t2"} <= anchored  # the built-in answer
        metrics = client.get("/metrics").text
    assert 'vlmap_llm_fallbacks_total{reason="malformed_reply"} 1.0' in metrics


def test_llm_parts_are_absent_without_an_endpoint(client: TestClient) -> None:
    scene = load_resource_json("scenes/two_rooms.json")
    body = {"scene_graph": scene, "utterance": "the bag is on the table", "options": {"proposer": "llm"}}
    response = client.post("/v1/ground", json=body)
    assert response.status_code == 422
    assert response.json()["field"] == "options.proposer"


def test_hostile_llm_replies_fall_back_and_are_counted() -> None:
    scene = load_resource_json("scenes/two_rooms.json")
    body = {"scene_graph": scene, "utterance": "my backpack is on the table", "options": {"proposer": "llm"}}
    huge_confidence = (  # a JSON integer past the float range
        '{"hypotheses": [{"utterance": "there is a backpack on the table", "referred_object_id": ["t2"], '
        f'"region_id": 1, "confidence": {10**400}}}]}}'
    )
    with FakeLLMServer() as server, TestClient(create_app(_settings(server))) as client:
        for reply in (Reply(content=huge_confidence), Reply(content="[" * 3000)):
            server.script(reply)
            response = client.post("/v1/ground", json=body)
            assert response.status_code == 200
            anchored = {a for h in response.json()["hypotheses"] for a in h["anchor_ids"]}
            assert {"t1", "t2"} <= anchored  # the built-in answer
        metrics = client.get("/metrics").text
    assert 'vlmap_llm_fallbacks_total{reason="no_valid_hypotheses"} 1.0' in metrics
    assert 'vlmap_llm_fallbacks_total{reason="malformed_reply"} 1.0' in metrics
    assert len(server.requests) == 2  # answered calls are not retried
