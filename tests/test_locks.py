"""The two locks: the runtime one holds everything the service imports, the two together are complete and
consistent (what `pip check` verifies), and no package is pinned twice."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def pins(name: str) -> dict[str, str]:
    """Package (normalised name) -> version, of a lock file."""
    out = {}
    for line in (ROOT / name).read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            package, version = line.split("==")
            out[re.sub(r"[-_.]+", "-", package).lower()] = version.strip()
    return out


def test_no_package_is_pinned_in_both_locks_and_together_they_are_complete() -> None:
    runtime, dev = pins("requirements.lock"), pins("requirements-dev.lock")
    assert not set(runtime) & set(dev)
    assert "torch" in runtime and "pytest" in dev and "pytest" not in runtime
    # The test environment is the two locks installed together: pip finds every requirement satisfied.
    check = subprocess.run(
        [sys.executable, "-m", "pip", "check"], capture_output=True, text=True, timeout=120
    )
    assert check.returncode == 0, check.stdout + check.stderr


def runtime_only_path(into: Path) -> Path:
    """A directory of links to what the runtime lock installs, of this environment's site-packages (the
    packages and their metadata): with `python -S` and it alone on the path, Python sees an install of
    requirements.lock and nothing else."""
    import importlib.metadata

    runtime = set(pins("requirements.lock")) | {"pip", "setuptools"}
    for dist in importlib.metadata.distributions():
        if re.sub(r"[-_.]+", "-", dist.metadata["Name"]).lower() not in runtime:
            continue
        for file in dist.files or []:
            top = Path(str(file)).parts[0]
            source = Path(str(dist.locate_file(top)))
            if top not in ("..", "__pycache__") and source.exists() and not (into / top).exists():
                (into / top).symlink_to(source)
    return into


# What a replica runs: the app, the loaded models (as a worker loads them), a grounding, a session with an
# utterance and a summary, the metrics, and the imports of Spark-DSG decoding and Redis.
_SERVE = """
import json, os, sys
os.environ["HF_HUB_OFFLINE"] = "1"
from fastapi.testclient import TestClient
from app.api.app import create_app
from app.settings import Settings
settings = Settings(_env_file=None, data_dir=None, rate_limit_per_s=0, worker_processes=0)
scene = json.load(open(sys.argv[1]))
with TestClient(create_app(settings)) as client:
    ground = {"scene_graph": scene, "utterance": "the backpack is on the table"}
    assert client.post("/v1/ground", json=ground).status_code == 200
    session = {"robot_id": "r", "scene_graph": scene, "target_label": "backpack"}
    sid = client.post("/v1/sessions", json=session).json()["id"]
    said = {"utterance": "my backpack is on the table"}
    assert client.post(f"/v1/sessions/{sid}/utterances", json=said).status_code == 200
    assert client.get(f"/v1/sessions/{sid}/belief").status_code == 200
    assert client.get("/metrics").status_code == 200
import spark_dsg, redis, hiredis, uvicorn, uvloop, httptools
for absent in ("pytest", "scipy", "matplotlib"):
    try:
        __import__(absent)
    except ModuleNotFoundError:
        continue
    raise SystemExit(f"{absent} is importable: the path is not the runtime lock's alone")
print("served")
"""


def test_the_service_runs_with_the_runtime_lock_alone(tmp_path: Path) -> None:
    import os

    scene = ROOT / "tests" / "resources" / "scenes" / "scannet_scene0590_00.json"
    env = {**os.environ, "PYTHONPATH": f"{runtime_only_path(tmp_path)}{os.pathsep}{ROOT}"}
    run = subprocess.run(
        [sys.executable, "-S", "-c", _SERVE, str(scene)], capture_output=True, text=True, timeout=300, env=env
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip() == "served"
