"""API keys, roles, rate and size limits on the stateless endpoints; the secure-by-default start-up."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.auth import KeyRing, Principal, Role, digest, new_key
from app.api.cli import serve_command
from app.errors import Forbidden, InvalidInput
from app.settings import Settings

KEYS = {"admin": new_key(), "viewer": new_key(), "robot": new_key()}


def _settings(**overrides: object) -> Settings:
    records = [
        {"name": "ops", "role": "admin", "sha256": digest(KEYS["admin"])},
        {"name": "dashboard", "role": "viewer", "sha256": digest(KEYS["viewer"])},
        {"name": "robot-7", "role": "robot", "sha256": digest(KEYS["robot"]), "robot_ids": ["r7"]},
    ]
    return Settings(_env_file=None, log_json=False, api_keys=json.dumps(records), **overrides)  # type: ignore[call-arg]


@pytest.fixture
def secured() -> Iterator[TestClient]:
    with TestClient(create_app(_settings())) as client:
        yield client


def _bearer(role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {KEYS[role]}"}


def test_missing_or_unknown_key_is_401_with_a_bearer_challenge(
    secured: TestClient, scene_graph_dict: dict
) -> None:
    body = {"scene_graph": scene_graph_dict, "utterance": "the bag is on the table"}
    for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": "Basic abc"}):
        response = secured.post("/v1/ground", json=body, headers=headers)
        assert response.status_code == 401, headers
        assert response.headers["www-authenticate"] == "Bearer"
        assert response.json()["code"] == "unauthenticated"


@pytest.mark.parametrize("role", ["admin", "viewer", "robot"])
def test_every_role_may_ground_and_list_models(
    secured: TestClient, scene_graph_dict: dict, role: str
) -> None:
    body = {"scene_graph": scene_graph_dict, "utterance": "the bag is on the table"}
    assert secured.post("/v1/ground", json=body, headers=_bearer(role)).status_code == 200
    assert secured.get("/v1/models", headers=_bearer(role)).status_code == 200


def test_probes_and_metrics_need_no_key(secured: TestClient) -> None:
    for path in ("/healthz", "/readyz", "/metrics"):
        assert secured.get(path).status_code == 200


def test_rate_limit_per_key_is_429() -> None:
    with TestClient(create_app(_settings(rate_limit_per_s=0.001, rate_limit_burst=3))) as client:
        codes = [client.get("/v1/models", headers=_bearer("viewer")).status_code for _ in range(5)]
        # Another key has its own bucket.
        other = client.get("/v1/models", headers=_bearer("admin")).status_code
    assert codes == [200, 200, 200, 429, 429]
    assert other == 200


def test_body_larger_than_the_limit_is_413(scene_graph_dict: dict) -> None:
    with TestClient(create_app(_settings(max_body_bytes=4096))) as client:
        body = {"scene_graph": scene_graph_dict, "utterance": "the bag is on the table"}
        response = client.post("/v1/ground", json=body, headers=_bearer("admin"))
    assert response.status_code == 413
    assert response.json()["code"] == "limit_exceeded"


def test_robot_principal_reads_and_writes_only_its_robots() -> None:
    robot = Principal("robot-7", Role.ROBOT, frozenset({"r7"}))
    viewer = Principal("dash", Role.VIEWER)
    admin = Principal("ops", Role.ADMIN)
    assert robot.can_write("r7") and robot.can_read("r7")
    assert not robot.can_write("r8") and not robot.can_read("r8")
    assert viewer.can_read("r8") and not viewer.can_write("r8")
    assert admin.can_write("anything")
    with pytest.raises(Forbidden, match="may not change robot 'r8'"):
        robot.require_write("r8")


def test_keyring_stores_digests_and_finds_the_right_record() -> None:
    ring = KeyRing.from_json(_settings().api_keys or "", "test")
    assert all(len(r.sha256) == 64 for r in ring.records)
    assert KEYS["robot"] not in (_settings().api_keys or "")
    principal = ring.authenticate(KEYS["robot"])
    assert principal == Principal("robot-7", Role.ROBOT, frozenset({"r7"}))
    assert ring.authenticate(KEYS["robot"] + "x") is None


@pytest.mark.parametrize(
    "text",
    ["not json", "{}", '[{"name": "a", "role": "god", "sha256": "' + "0" * 64 + '"}]', '[{"name": "a"}]'],
)
def test_bad_key_files_are_rejected_naming_the_entry(text: str) -> None:
    with pytest.raises(InvalidInput, match="keys"):
        KeyRing.from_json(text, "keys.json")


def test_serve_refuses_a_public_address_without_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("VLMAP_API_KEYS", raising=False)
    monkeypatch.delenv("VLMAP_API_KEYS_FILE", raising=False)
    monkeypatch.delenv("VLMAP_ALLOW_OPEN", raising=False)
    args = argparse.Namespace(host="0.0.0.0", port=8999, allow_open=False)
    assert serve_command(args) == 2


def test_streamed_body_larger_than_the_limit_is_413(scene_graph_dict: dict) -> None:
    payload = json.dumps({"scene_graph": scene_graph_dict, "utterance": "the bag is on the table"}).encode()

    def chunks() -> Iterator[bytes]:  # no Content-Length: the server must count
        for start in range(0, len(payload), 1024):
            yield payload[start : start + 1024]

    with TestClient(create_app(_settings(max_body_bytes=4096))) as client:
        response = client.post(
            "/v1/ground", content=chunks(), headers={**_bearer("admin"), "content-type": "application/json"}
        )
    assert response.status_code == 413
    assert response.json()["code"] == "limit_exceeded"
