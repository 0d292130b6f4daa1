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
    overrides.setdefault("data_dir", None)  # never the repository's var/sessions
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
    assert (response.json()["code"], response.json()["field"]) == ("limit_exceeded", "max_body_bytes")


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
    assert (response.json()["code"], response.json()["field"]) == ("limit_exceeded", "max_body_bytes")


# --- roles on sessions ------------------------------------------------------------------------------------


@pytest.fixture
def secured_sessions(scene_graph_dict: dict) -> Iterator[tuple[TestClient, str, str]]:
    """A secured service with one session of robot r7 and one of robot r8 (created by the admin)."""
    settings = _settings(data_dir=None, rate_limit_per_s=0)
    with TestClient(create_app(settings)) as client:
        ids = []
        for robot in ("r7", "r8"):
            body = {
                "robot_id": robot,
                "scene_graph": scene_graph_dict,
                "target_label": "backpack",
                "grid": {"voxel_size": 0.25},
            }
            response = client.post("/v1/sessions", json=body, headers=_bearer("admin"))
            assert response.status_code == 201, response.text
            ids.append(response.json()["id"])
        yield client, ids[0], ids[1]


def _operations(session_id: str) -> dict[str, tuple[str, str, dict]]:
    return {
        "get": ("GET", f"/v1/sessions/{session_id}", {}),
        "belief": ("GET", f"/v1/sessions/{session_id}/belief", {}),
        "utterance": (
            "POST",
            f"/v1/sessions/{session_id}/utterances",
            {"json": {"utterance": "the bag is on the desk"}},
        ),
        "observe": (
            "POST",
            f"/v1/sessions/{session_id}/observations",
            {"json": {"voxels": [[1, 1, 1]], "labels": ["bag"]}},
        ),
        "delete": ("DELETE", f"/v1/sessions/{session_id}", {}),
    }


@pytest.mark.parametrize(
    ("role", "own", "allowed"),
    [
        ("robot", True, {"get", "belief", "utterance", "observe", "delete"}),
        ("robot", False, set()),  # another robot's session: neither read nor write
        ("viewer", True, {"get", "belief"}),
        ("viewer", False, {"get", "belief"}),
        ("admin", False, {"get", "belief", "utterance", "observe", "delete"}),
    ],
)
def test_each_role_may_do_exactly_its_operations(
    secured_sessions: tuple[TestClient, str, str], role: str, own: bool, allowed: set[str]
) -> None:
    client, r7_session, r8_session = secured_sessions
    session_id = r7_session if own else r8_session
    for name, (method, path, kwargs) in _operations(session_id).items():
        before = client.get(f"/v1/sessions/{session_id}", headers=_bearer("admin")).json()
        response = client.request(method, path, headers=_bearer(role), **kwargs)
        if name in allowed:
            assert response.status_code in (200, 204), (name, response.text)
        else:
            assert response.status_code == 403, (name, response.status_code)
            assert response.json()["code"] == "forbidden"
            after = client.get(f"/v1/sessions/{session_id}", headers=_bearer("admin")).json()
            assert after == before, f"{name} refused but the session changed"


def test_robots_create_only_their_own_sessions_and_list_only_theirs(
    secured_sessions: tuple[TestClient, str, str], scene_graph_dict: dict
) -> None:
    client, _, _ = secured_sessions
    body = {"scene_graph": scene_graph_dict, "grid": {"voxel_size": 0.25}}
    assert (
        client.post("/v1/sessions", json={"robot_id": "r7", **body}, headers=_bearer("robot")).status_code
        == 201
    )
    assert (
        client.post("/v1/sessions", json={"robot_id": "r8", **body}, headers=_bearer("robot")).status_code
        == 403
    )
    assert (
        client.post("/v1/sessions", json={"robot_id": "r7", **body}, headers=_bearer("viewer")).status_code
        == 403
    )
    listed = client.get("/v1/sessions", headers=_bearer("robot")).json()["sessions"]
    assert {s["robot_id"] for s in listed} == {"r7"}
    assert len(client.get("/v1/sessions", headers=_bearer("viewer")).json()["sessions"]) == 3


def test_unauthenticated_writes_change_nothing(secured_sessions: tuple[TestClient, str, str]) -> None:
    client, r7_session, _ = secured_sessions
    before = client.get(f"/v1/sessions/{r7_session}", headers=_bearer("admin")).json()
    for method, path, kwargs in _operations(r7_session).values():
        assert client.request(method, path, **kwargs).status_code == 401
    assert client.get(f"/v1/sessions/{r7_session}", headers=_bearer("admin")).json() == before


def test_a_bad_utterance_body_is_read_only_after_the_key_and_its_rate() -> None:
    path = "/v1/sessions/any/utterances"
    bodies = [(b'{"utterance": 5}', "application/json"), (b'{"utterance": "hi"}', "text/plain")]
    with TestClient(create_app(_settings(rate_limit_per_s=0.001, rate_limit_burst=1))) as client:
        for content, kind in bodies:
            for key in ({}, {"Authorization": "Bearer nope"}):
                answer = client.post(path, content=content, headers={"content-type": kind, **key})
                assert answer.status_code == 401, answer.text
        robot = {"content-type": "application/json", **_bearer("robot")}
        assert client.post(path, content=bodies[0][0], headers=robot).status_code == 422
        assert client.post(path, content=bodies[0][0], headers=robot).status_code == 429  # over its rate
