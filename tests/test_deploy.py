"""The deploy files: valid Kubernetes objects, probes and settings that exist, a compose file in shape."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from app.api.app import create_app
from app.settings import Settings

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
K8S_VERSION = "1.30.0"


def _documents() -> list[tuple[str, dict[str, Any]]]:
    docs = []
    for path in sorted((DEPLOY / "k8s").glob("*.yaml")):
        docs += [(path.name, d) for d in yaml.safe_load_all(path.read_text()) if d]
    return docs


@pytest.mark.parametrize(
    ("name", "doc"), [d for d in _documents() if "." not in d[1]["apiVersion"].split("/")[0]]
)
def test_core_manifests_validate_against_the_kubernetes_schemas(name: str, doc: dict[str, Any]) -> None:
    kubernetes_validate.validate(doc, K8S_VERSION, strict=True)


def test_service_monitor_scrapes_the_metrics_route() -> None:
    (monitor,) = [d for _, d in _documents() if d["kind"] == "ServiceMonitor"]
    assert monitor["apiVersion"] == "monitoring.coreos.com/v1"
    (endpoint,) = monitor["spec"]["endpoints"]
    assert endpoint["path"] == "/metrics"
    service = next(d for _, d in _documents() if d["kind"] == "Service" and d["metadata"]["name"] == "vlmap")
    assert endpoint["port"] in {p["name"] for p in service["spec"]["ports"]}
    assert monitor["spec"]["selector"]["matchLabels"].items() <= service["metadata"]["labels"].items()


def test_probes_point_at_routes_the_service_has() -> None:
    paths = set(create_app(Settings(_env_file=None, data_dir=None)).openapi()["paths"])  # type: ignore[call-arg]
    deployment = next(d for _, d in _documents() if d["kind"] == "Deployment")
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz" in paths
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz" in paths
    assert deployment["spec"]["replicas"] >= 2


def test_every_vlmap_variable_named_in_deploy_is_a_setting() -> None:
    fields = {f"VLMAP_{name.upper()}" for name in Settings.model_fields}
    named = set()
    for path in DEPLOY.rglob("*"):
        if path.is_file():
            named |= set(re.findall(r"\bVLMAP_[A-Z_]+\b", path.read_text()))
    assert named, "no VLMAP_ variables found"
    assert named <= fields, f"unknown settings: {sorted(named - fields)}"


def test_compose_runs_two_replicas_on_redis_with_aof_behind_a_balancer() -> None:
    compose = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    services = compose["services"]
    replicas = [s for s in services.values() if "build" in s]
    assert len(replicas) == 2
    assert all(s["environment"]["VLMAP_STORE"].startswith("redis://redis:") for s in replicas)
    assert "--appendonly" in services["redis"]["command"] and "yes" in services["redis"]["command"]
    nginx = (DEPLOY / "nginx.conf").read_text()
    assert all(f"server {name}:8000" in nginx for name in ("vlmap-a", "vlmap-b"))


def test_the_image_takes_torch_from_an_index_of_cpu_builds_before_the_lock() -> None:
    """The default index's torch is the CUDA build, whose libraries `--no-deps` leaves out: the image could
    not import it."""
    dockerfile = (DEPLOY.parent / "Dockerfile").read_text()
    lock = (DEPLOY.parent / "requirements.lock").read_text()
    (pinned,) = re.findall(r"^torch==(\S+)$", lock, flags=re.MULTILINE)
    torch_step = dockerfile.index(f'--index-url "$TORCH_INDEX_URL" torch=={pinned}')
    assert "ARG TORCH_INDEX_URL" in dockerfile and torch_step < dockerfile.index("-r requirements.lock")
    compose = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    replicas = [s for s in compose["services"].values() if "build" in s]
    assert all("TORCH_INDEX_URL" in s["build"]["args"] for s in replicas)


def test_the_balancer_drops_idle_connections_before_the_service_closes_them() -> None:
    """A connection the service closed and nginx reuses fails a POST with a 502 (nginx does not retry it)."""
    upstream = re.search(r"upstream vlmap \{(.*?)\}", (DEPLOY / "nginx.conf").read_text(), flags=re.DOTALL)
    assert upstream is not None
    (timeout,) = re.findall(r"keepalive_timeout (\d+)s;", upstream.group(1))
    assert int(timeout) < Settings().keep_alive_s
