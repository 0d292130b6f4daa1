"""The committed OpenAPI contract equals what the service serves, and the service keeps to it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance

from app.api.app import create_app
from app.api.auth import digest, new_key
from app.api.bootstrap import build_sensors
from app.api.cli import openapi_spec
from app.api.observability import Metrics
from app.settings import Settings
from app.stores import MemorySessionStore

COMMITTED = Path(__file__).resolve().parent.parent / "openapi" / "openapi.json"
REGENERATE = "vlmap openapi --out openapi/openapi.json"
RESOURCES = Path(__file__).resolve().parent / "resources"


def test_committed_spec_matches_the_served_one(client: TestClient) -> None:
    served = client.get("/openapi.json").json()
    committed = json.loads(COMMITTED.read_text(encoding="utf-8"))
    assert served == committed, f"openapi/openapi.json is stale: regenerate it with `{REGENERATE}`"
    assert COMMITTED.read_text(encoding="utf-8") == openapi_spec(), (
        f"not in canonical form: run `{REGENERATE}`"
    )


def test_every_operation_has_a_stable_id_a_summary_and_documented_errors() -> None:
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    ids = []
    for path, methods in spec["paths"].items():
        for method, op in methods.items():
            ids.append(op["operationId"])
            assert op.get("description"), f"{method.upper()} {path} has no docstring"
            assert "\n" not in op["description"].strip(), f"{method.upper()} {path}: one-line docstrings only"
            if op.get("requestBody") or op.get("parameters"):
                assert "422" in op["responses"], f"{method.upper()} {path} does not document 422"
    assert len(ids) == len(set(ids))


def test_every_conditional_read_declares_its_etag() -> None:
    """A GET that may answer 304 says which ETag its 200 carries, for generated clients to read it."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    conditional = [
        (path, op)
        for path, methods in spec["paths"].items()
        for method, op in methods.items()
        if "304" in op["responses"]
    ]
    assert len(conditional) >= 2
    for path, op in conditional:
        assert "ETag" in op["responses"]["200"].get("headers", {}), path


def spec_validator(spec: dict[str, Any], schema: dict[str, Any]) -> jsonschema.Draft202012Validator:
    """A validator for one of the spec's schemas, its "#/components/..." references resolved in the spec."""
    return jsonschema.Draft202012Validator({**schema, "components": spec["components"]})


def test_the_spec_refuses_what_the_service_refuses() -> None:
    """Rules JSON Schema can state are stated: a side of zero, an array of a dtype its field never takes."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    box = spec_validator(spec, {"$ref": "#/components/schemas/SceneObject"})
    assert box.is_valid({"id": "a", "label": "box", "center": [0, 0, 0], "size": [1, 1, 0.5]})
    assert not box.is_valid({"id": "a", "label": "box", "center": [0, 0, 0], "size": [1, 0, 0.5]})
    operation = spec["paths"]["/v1/sessions/{session_id}/observations"]["post"]
    batch = spec_validator(spec, operation["requestBody"]["content"]["application/msgpack"]["schema"])
    voxels = {"dtype": "<i4", "shape": [1, 3], "data": "AAAA"}
    labels = {"dtype": "<u4", "shape": [1], "data": "AAAA"}
    assert batch.is_valid({"voxels": voxels, "labels": labels})
    assert not batch.is_valid({"voxels": {**voxels, "dtype": "<f8"}, "labels": labels})
    assert not batch.is_valid({"voxels": voxels, "labels": {**labels, "dtype": "<i8"}})


REQUEST_FILES = {
    ("/v1/ground", "post"): ["requests/ground.json", "requests/ground_small.json"],
    ("/v1/sessions", "post"): ["requests/session.json"],
    ("/v1/sessions/{session_id}/scene-graph", "put"): ["scenes/two_rooms.json"],
    ("/v1/scene-graphs/normalize", "post"): ["scenes/two_rooms.json"],
}


def test_the_spec_accepts_its_own_examples_and_the_readme_requests() -> None:
    """A user's contract test validates requests against the committed spec: what the service documents
    and accepts must validate (a oneOf over overlapping branches once refused every native scene graph)."""
    spec = json.loads(COMMITTED.read_text(encoding="utf-8"))
    checked = 0
    for path, methods in spec["paths"].items():
        for method, op in methods.items():
            media = op.get("requestBody", {}).get("content", {}).get("application/json")
            if media is None:
                continue
            validator = spec_validator(spec, media["schema"])
            bodies = [(name, example["value"]) for name, example in media.get("examples", {}).items()]
            for name in REQUEST_FILES.get((path, method), []):
                bodies.append((name, json.loads((RESOURCES / name).read_text(encoding="utf-8"))))
            for name, body in bodies:
                errors = [error.message[:200] for error in validator.iter_errors(body)]
                assert not errors, f"{method.upper()} {path} [{name}]: {errors}"
                checked += 1
    assert checked >= 15


_ADMIN_KEY = new_key()
_settings = Settings(  # type: ignore[call-arg]
    _env_file=None,
    log_json=False,
    rate_limit_per_s=0,
    api_keys=json.dumps([{"name": "ci-admin", "role": "admin", "sha256": digest(_ADMIN_KEY)}]),
    # An event stream answers through the ASGI transport only once it ends: here, at once.
    events_max_stream_s=0.05,
)
_app = create_app(_settings, sensors=build_sensors(_settings, Metrics()), store=MemorySessionStore(None))
schema = schemathesis.openapi.from_asgi("/openapi.json", _app)


@schemathesis.serializer("application/msgpack")
def _msgpack(ctx: object, value: object) -> bytes:
    """Generated msgpack bodies: the schema's map, packed (byte strings stay bin)."""
    return msgpack.packb(value, use_bin_type=True, default=str)


@schema.parametrize()
# Derandomized: the same examples every run, so CI never flakes on schemathesis' rare false positives
# (a generated boolean query value that serialises to a valid string, "false"); run it with more, random
# examples by hand when changing the API (300 random examples per operation passed on this revision).
@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@pytest.mark.filterwarnings("ignore")
def test_api_keeps_its_contract(case: schemathesis.Case) -> None:
    """No 5xx and every response conforms to the schema, over generated requests to every operation.

    Positive-data acceptance is not required: duplicate ids, dangling region ids, object caps and unknown
    anchor ids are rules JSON Schema cannot state, so a schema-valid body may get the documented 422.
    Negative-data rejection is not required either: a query string has no types, so a generated number
    for robot_id ("1.37e-217") arrives as a valid string id; invalid bodies are covered by the fuzz tests.
    """
    case.call_and_validate(
        headers={"Authorization": f"Bearer {_ADMIN_KEY}"},
        excluded_checks=[positive_data_acceptance, negative_data_rejection],
    )
