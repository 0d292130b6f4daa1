"""Health, readiness, model listing and Prometheus metrics."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.settings import Settings
from app.sim.service import MODEL_FREE_ENV, free_port
from app.stores.memory import MemorySessionStore


def test_health_and_readiness(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready", "grounder": "geometric"}


def test_not_ready_before_the_model_is_loaded(settings: Settings) -> None:
    app = create_app(settings)
    # Without entering the lifespan, the sensor is never built: readiness must say so.
    client = TestClient(app)
    response = client.get("/readyz")
    assert response.status_code == 503
    assert response.json()["code"] == "unavailable"
    assert client.get("/healthz").status_code == 200


def test_a_service_started_in_the_background_is_live_at_once_and_ready_once_loaded(
    settings: Settings, monkeypatch: pytest.MonkeyPatch, scene_graph_dict: dict
) -> None:
    """`vlmap serve` answers /healthz while the models load, so that an orchestrator tells starting from
    dead; /readyz and what needs the models answer 503 until they are loaded."""
    from app.api import app as app_module

    loaded, build = threading.Event(), app_module.build_sensors

    def slow_build(*args: object, **kwargs: object) -> object:
        assert loaded.wait(30)
        return build(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(app_module, "build_sensors", slow_build)
    with TestClient(create_app(settings, start_in_background=True)) as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/readyz").status_code == 503
        ground = {"scene_graph": scene_graph_dict, "utterance": "the backpack is on the table"}
        assert client.post("/v1/ground", json=ground).status_code == 503
        loaded.set()
        for _ in range(300):
            if client.get("/readyz").status_code == 200:
                break
            threading.Event().wait(0.05)
        assert client.get("/readyz").json() == {"status": "ready", "grounder": "geometric"}
        assert client.post("/v1/ground", json=ground).status_code == 200


def test_a_failed_background_start_up_says_why_and_asks_to_stop(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A start-up that fails in the background (here the model files) is not "still loading" for ever: the
    503s carry its error and the app calls its stop hook once; liveness still answers."""
    from app.api import app as app_module

    def broken_build(*args: object, **kwargs: object) -> object:
        msg = "models/lsm/model.safetensors: unreadable"
        raise OSError(msg)

    monkeypatch.setattr(app_module, "build_sensors", broken_build)
    stops: list[bool] = []
    app = create_app(settings, start_in_background=True, on_startup_failure=lambda: stops.append(True))
    with TestClient(app) as client:
        for _ in range(300):
            if stops:
                break
            threading.Event().wait(0.05)
        assert stops == [True]
        ready = client.get("/readyz")
        assert ready.status_code == 503
        assert ready.json()["message"] == (
            "the service failed to start and is stopping: models/lsm/model.safetensors: unreadable"
        )
        assert client.get("/healthz").status_code == 200


def test_vlmap_serve_exits_1_when_its_data_directory_is_held(tmp_path: Path) -> None:
    """`vlmap serve` whose start-up fails (another store holds its session data directory) logs why and
    exits 1 instead of serving 503s for ever."""
    held = MemorySessionStore(tmp_path)
    try:
        env = dict(os.environ, **MODEL_FREE_ENV, VLMAP_DATA_DIR=str(tmp_path), VLMAP_LOG_JSON="false")
        done = subprocess.run(
            [sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1", "--port", str(free_port())],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
    finally:
        held.close()
    assert done.returncode == 1, done.stderr[-2000:]
    assert "start-up failed" in done.stderr
    assert "in use by another store" in done.stderr


def test_models_lists_grounder_and_proposer(client: TestClient) -> None:
    models = client.get("/v1/models").json()["models"]
    assert [(m["role"], m["name"]) for m in models] == [
        ("grounder", "geometric"),
        ("grounder", "fixed"),
        ("proposer", "lexical"),
    ]
    assert models[0]["checksum"].startswith("sha256:")
    assert "near_margin" in models[0]["config"]


def _sample(text: str, name: str, **labels: str) -> float:
    for line in text.splitlines():
        if not line.startswith(name + "{") and not line.startswith(name + " "):
            continue
        found = dict(re.findall(r'(\w+)="([^"]*)"', line))
        if all(found.get(k) == v for k, v in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    msg = f"no sample {name} {labels} in metrics"
    raise AssertionError(msg)


def test_metrics_count_requests_and_time_inference_stages(client: TestClient, scene_graph_dict: dict) -> None:
    for _ in range(2):
        client.post(
            "/v1/ground", json={"scene_graph": scene_graph_dict, "utterance": "the bag is on the desk"}
        )
    client.post("/v1/ground", json={"utterance": "missing scene graph"})
    text = client.get("/metrics").text
    assert _sample(text, "vlmap_http_requests_total", method="POST", route="/v1/ground", status="200") == 2
    assert _sample(text, "vlmap_http_requests_total", method="POST", route="/v1/ground", status="422") == 1
    assert _sample(text, "vlmap_http_request_duration_seconds_count", method="POST", route="/v1/ground") == 3
    assert _sample(text, "vlmap_inference_duration_seconds_count", stage="proposer") == 2
    assert _sample(text, "vlmap_inference_duration_seconds_count", stage="grounder") == 2
    # The /metrics request itself is in flight while it is rendered.
    assert _sample(text, "vlmap_http_requests_in_flight") == 1
    # Route templates, never raw paths, so the label set stays bounded.
    client.get("/no/such/path/123")
    assert 'route="unmatched"' in client.get("/metrics").text


def test_the_default_service_uses_the_calibrated_builtin_proposer(scene_graph_dict: dict) -> None:
    defaults = Settings(_env_file=None, data_dir=None, log_json=False)  # type: ignore[call-arg]
    with TestClient(create_app(defaults)) as client:
        proposers = [m for m in client.get("/v1/models").json()["models"] if m["role"] == "proposer"]
        body = {"scene_graph": scene_graph_dict, "utterance": "I left my backpack on the table"}
        answer = client.post("/v1/ground", json=body).json()
    grounders = [m["name"] for m in client.get("/v1/models").json()["models"] if m["role"] == "grounder"]
    assert grounders == ["lsm", "fixed", "geometric"]  # the shipped LSM first: the default
    assert answer["model"]["name"] == "lsm"
    assert [p["name"] for p in proposers] == ["builtin"]
    assert proposers[0]["checksum"].startswith("sha256:")
    weights = {tuple(h["anchor_ids"]): h["weight"] for h in answer["hypotheses"]}
    assert abs(sum(weights.values()) - 1) < 1e-9
    tables = {(o["id"],) for o in scene_graph_dict["objects"] if o["label"] == "table"}
    assert len(tables) == 2 and tables <= set(weights)  # the room's two tables are among the readings


def test_an_empty_data_dir_means_not_durable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VLMAP_DATA_DIR", "")
    assert Settings().data_dir is None
    monkeypatch.setenv("VLMAP_DATA_DIR", "var/x")
    assert str(Settings().data_dir) == "var/x"
