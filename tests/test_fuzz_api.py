"""Hostile input through the API: random and mutated bodies never cause a 5xx or touch an existing belief."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.api.app import create_app
from app.sessions.batch import encode_msgpack_batch
from app.settings import Settings
from tests.conftest import load_resource_json

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def service() -> Iterator[tuple[TestClient, str]]:
    config = Settings(
        _env_file=None, log_json=False, data_dir=None, rate_limit_per_s=0, max_batch_voxels=10_000
    )  # type: ignore[call-arg]
    with TestClient(create_app(config)) as client:
        body = {
            "robot_id": "fuzz",
            "scene_graph": load_resource_json("scenes/two_rooms.json"),
            "target_label": "backpack",
            "label_map": {"0": "floor", "1": "backpack"},
            "grid": {"voxel_size": 0.25},
        }
        session_id = client.post("/v1/sessions", json=body).json()["id"]
        client.post(
            f"/v1/sessions/{session_id}/utterances", json={"utterance": "the backpack is on the table"}
        )
        client.post(f"/v1/sessions/{session_id}/observations", json={"voxels": [[2, 2, 2]], "labels": [1]})
        yield client, session_id


def _fingerprint(client: TestClient, session_id: str) -> str:
    grid = client.get(f"/v1/sessions/{session_id}/belief", params={"format": "grid", "layers": True})
    assert grid.status_code == 200
    return grid.headers["etag"] + hashlib.sha256(grid.content).hexdigest()


def _post_and_check(client: TestClient, session_id: str, body: bytes, content_type: str) -> None:
    before = _fingerprint(client, session_id)
    response = client.post(
        f"/v1/sessions/{session_id}/observations", content=body, headers={"content-type": content_type}
    )
    assert response.status_code < 500, response.text
    if response.status_code >= 400:
        assert _fingerprint(client, session_id) == before, (
            f"rejected ({response.status_code}) but the belief changed"
        )


_VALID = encode_msgpack_batch(voxels=np.array([[1, 1, 1], [2, 3, 1]]), labels=np.array([0, 1]), stamp=3.0)
_ENVELOPE_KEYS = st.sampled_from(["stamp", "voxels", "points", "labels", "p_target", "sensor_model", "extra"])
_LEAF = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.binary(max_size=64),
)
_VALUES = st.recursive(
    _LEAF,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.sampled_from(["dtype", "shape", "data", "tp", "fp"]), inner, max_size=4)
    ),
    max_leaves=12,
)


@FUZZ
@given(data=st.binary(max_size=512))
def test_random_bytes_as_msgpack(service: tuple[TestClient, str], data: bytes) -> None:
    _post_and_check(*service, data, "application/msgpack")


@FUZZ
@given(envelope=st.dictionaries(_ENVELOPE_KEYS, _VALUES, max_size=6))
def test_random_msgpack_envelopes(service: tuple[TestClient, str], envelope: dict[str, Any]) -> None:
    _post_and_check(*service, msgpack.packb(envelope, use_bin_type=True), "application/msgpack")


@FUZZ
@given(
    cut=st.integers(min_value=0, max_value=len(_VALID) - 1),
    flips=st.lists(st.tuples(st.integers(0, len(_VALID) - 1), st.integers(1, 255)), max_size=4),
)
def test_truncated_or_corrupted_valid_batches(
    service: tuple[TestClient, str], cut: int, flips: list[tuple[int, int]]
) -> None:
    data = bytearray(_VALID)
    for index, mask in flips:
        data[index] ^= mask
    _post_and_check(*service, bytes(data[: cut or None]), "application/msgpack")


@FUZZ
@given(body=st.dictionaries(_ENVELOPE_KEYS, _VALUES, max_size=6))
def test_random_json_batches(service: tuple[TestClient, str], body: dict[str, Any]) -> None:
    import json

    try:
        text = json.dumps(body, default=lambda b: b.hex() if isinstance(b, bytes) else str(b))
    except ValueError:
        return
    _post_and_check(*service, text.encode(), "application/json")


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene_graph=_VALUES)
def test_random_scene_graphs_on_create_and_replace(service: tuple[TestClient, str], scene_graph: Any) -> None:
    client, session_id = service
    before = _fingerprint(client, session_id)
    created = client.post("/v1/sessions", json={"robot_id": "fuzz2", "scene_graph": _jsonable(scene_graph)})
    assert created.status_code < 500, created.text
    replaced = client.put(f"/v1/sessions/{session_id}/scene-graph", json=_jsonable(scene_graph))
    assert replaced.status_code < 500, replaced.text
    if replaced.status_code >= 400:
        assert _fingerprint(client, session_id) == before


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    return value
