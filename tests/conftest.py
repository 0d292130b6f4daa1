"""Shared fixtures: real scenes from tests/resources and an in-process service."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.lsm.features import rotation_z
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from tests.harness import RedisServer

RESOURCES = Path(__file__).parent / "resources"

# Tests build dozens of apps and services: a grounding worker process for each would load its models again
# (seconds apiece). They ground on threads; tests/test_workers.py tests the worker processes.
os.environ.setdefault("VLMAP_WORKER_PROCESSES", "0")


def load_resource_json(relative: str) -> Any:
    return json.loads((RESOURCES / relative).read_text(encoding="utf-8"))


@pytest.fixture
def scene_graph_dict() -> dict[str, Any]:
    """ScanNet scene0590_00 (60 objects: 2 tables, 3 chairs, 5 bags, a desk, a lamp, ...)."""
    return load_resource_json("scenes/scannet_scene0590_00.json")


def model_free_settings(**overrides: Any) -> Settings:
    """In-memory sessions, no rate limit, and the model-free parts (geometric grounder, lexical proposer):
    what most tests want. The shipped models are tested where they are the subject."""
    fields: dict[str, Any] = {
        "log_json": False,
        "data_dir": None,
        "rate_limit_per_s": 0,
        "grounder": "geometric",
        "grounders": ["geometric", "fixed"],
        "proposer": "lexical",
    }
    return Settings(_env_file=None, **(fields | overrides))  # type: ignore[call-arg]


@pytest.fixture
def settings() -> Settings:
    return model_free_settings()


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        yield test_client


@pytest.fixture(scope="session")
def redis_url() -> Iterator[str]:
    """The Redis that `.ci/run` started (VLMAP_TEST_REDIS_URL), else a private redis-server on loopback.

    Skips only when no redis-server binary exists on this machine (`apt-get install redis-server`).
    """
    given = os.environ.get("VLMAP_TEST_REDIS_URL")
    if given:
        yield given
        return
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (apt-get install redis-server)")
    server = RedisServer(binary)
    server.start()
    try:
        yield server.url
    finally:
        server.close()


@pytest.fixture(scope="session")
def redis_cluster_url() -> str:
    """A Redis Cluster of 3 masters with a replica each, started by `.ci/run` (VLMAP_TEST_REDIS_CLUSTER_URL,
    any of its nodes). Skips without one: a cluster takes six servers and `redis-cli --cluster create`."""
    given = os.environ.get("VLMAP_TEST_REDIS_CLUSTER_URL")
    if not given:
        pytest.skip(
            "no Redis Cluster: set VLMAP_TEST_REDIS_CLUSTER_URL (.ci/run starts one on ports 7000-7005)"
        )
    return given


def moved_scene(scene_graph: SceneGraph, yaw: float, offset: np.ndarray) -> SceneGraph:
    """The whole scene turned by `yaw` about the origin and shifted by `offset` (regions dropped: an
    axis-aligned region box does not stay one under a turn)."""
    turn = rotation_z(yaw)
    objects = [
        o.model_copy(
            update={
                "center": (turn @ np.asarray(o.center) + offset).tolist(),
                "yaw": o.yaw + yaw,
                "region_id": None,
            }
        )
        for o in scene_graph.objects
    ]
    return scene_graph.model_copy(update={"objects": objects, "regions": []})
