"""Grounding in worker processes (`VLMAP_WORKER_PROCESSES`): the same answers as on threads, errors that
cross the process boundary intact, and a pool that recovers from a dead worker."""

from __future__ import annotations

import asyncio
import contextlib
import os
import pickle
import signal
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.workers import WorkerProcesses
from tests.conftest import model_free_settings


@pytest.fixture(scope="module")
def pooled() -> Iterator[TestClient]:
    """An app that grounds in one worker process (geometric grounder, lexical proposer: no model files)."""
    with TestClient(create_app(model_free_settings(worker_processes=1))) as client:
        yield client


def _ground(client: TestClient, scene_graph: Any, utterance: str, **extra: Any) -> Any:
    return client.post("/v1/ground", json={"scene_graph": scene_graph, "utterance": utterance, **extra})


def _without_timings(body: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in body.items() if k != "timings_ms"}


def test_the_pool_starts_with_the_app_and_serves_the_local_parts_only(pooled: TestClient) -> None:
    workers = pooled.app.state.services.worker_processes  # type: ignore[attr-defined]
    assert isinstance(workers, WorkerProcesses)
    assert workers.serves("geometric", "builtin") and workers.serves("fixed", "builtin")
    assert not workers.serves("lsm", "builtin")  # not loaded by this app
    assert not workers.serves("geometric", "llm")  # network-bound: stays on threads


@pytest.mark.parametrize(
    "utterance, extra",
    [
        ("I left my backpack on the table", {}),
        ("the mouse is on the desk", {"options": {"grounder": "fixed"}}),
        ("the unicorn is on the spaceship", {}),  # no anchor: the broad prior
    ],
)
def test_workers_answer_exactly_as_threads_do(
    pooled: TestClient, client: TestClient, scene_graph_dict: dict, utterance: str, extra: dict
) -> None:
    in_worker = _ground(pooled, scene_graph_dict, utterance, **extra)
    on_thread = _ground(client, scene_graph_dict, utterance, **extra)
    assert in_worker.status_code == on_thread.status_code == 200, in_worker.text
    assert _without_timings(in_worker.json()) == _without_timings(on_thread.json())
    assert set(in_worker.json()["timings_ms"]) == set(on_thread.json()["timings_ms"])


def test_a_domain_error_raised_in_a_worker_is_the_same_4xx(
    pooled: TestClient, client: TestClient, scene_graph_dict: dict
) -> None:
    options = {"hypotheses": [{"anchor_ids": ["no-such-object"], "relation": "on"}]}
    in_worker = _ground(pooled, scene_graph_dict, "the cup is on it", options=options)
    on_thread = _ground(client, scene_graph_dict, "the cup is on it", options=options)
    assert in_worker.status_code == on_thread.status_code == 422

    def without_id(body: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in body.items() if k != "request_id"}

    assert without_id(in_worker.json()) == without_id(on_thread.json())
    assert in_worker.json()["field"] == "options.hypotheses.0.anchor_ids"


def test_worker_stage_timings_reach_the_service_metrics(pooled: TestClient, scene_graph_dict: dict) -> None:
    assert _ground(pooled, scene_graph_dict, "the bag is on the desk").status_code == 200
    metrics = pooled.get("/metrics").text
    assert 'vlmap_inference_duration_seconds_count{stage="grounder"}' in metrics
    assert 'vlmap_inference_duration_seconds_count{stage="grounder"} 0.0' not in metrics


def test_utterances_fuse_through_the_workers(pooled: TestClient, scene_graph_dict: dict) -> None:
    created = pooled.post(
        "/v1/sessions", json={"robot_id": "robot-1", "scene_graph": scene_graph_dict, "target_label": "bag"}
    )
    assert created.status_code == 201, created.text
    sid = created.json()["id"]
    fused = pooled.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "the bag is on the desk"})
    assert fused.status_code == 200, fused.text
    body = fused.json()
    assert body["grounding"]["grounded"] is True
    assert body["belief"]["version"] == 1


def test_a_killed_worker_costs_one_503_then_a_new_pool_serves(
    pooled: TestClient, scene_graph_dict: dict
) -> None:
    workers = pooled.app.state.services.worker_processes  # type: ignore[attr-defined]
    (pid,) = workers.pids()  # the pool's one worker
    os.kill(pid, signal.SIGKILL)
    statuses = [_ground(pooled, scene_graph_dict, "the bag is on the desk").status_code for _ in range(2)]
    assert statuses == [503, 200], statuses
    (new,) = workers.pids()
    assert new != pid


def test_a_request_cancelled_while_its_worker_computes_leaves_the_worker_to_the_next_requests(
    scene_graph_dict: dict,
) -> None:
    """One worker, a request cancelled after it was sent, then five at once: each gets its own answer (none
    the cancelled one's, which the pool reads and drops), in turn, from the same worker."""
    from app.scene_graph.model import SceneGraph

    workers = WorkerProcesses(model_free_settings(), 1)
    workers.start()
    scene = SceneGraph.model_validate(scene_graph_dict)
    targets = ["mug", "book", "phone", "key", "sock"]

    async def run() -> list[Any]:
        cancelled = asyncio.create_task(
            workers.ground("geometric", "builtin", scene, "the bag is on the desk", None)
        )
        await asyncio.sleep(0)  # the task runs until it waits for the answer: the request is written
        cancelled.cancel()
        with pytest.raises(asyncio.CancelledError):
            await cancelled
        return await asyncio.gather(
            *(workers.ground("geometric", "builtin", scene, f"the {t} is on the desk", None) for t in targets)
        )

    try:
        (pid,) = workers.pids()
        groundings = asyncio.run(run())
        assert [g.proposal.parse.target for g in groundings] == targets
        assert workers.pids() == [pid]
    finally:
        workers.close()
    assert workers.pids() == []


def test_a_request_longer_than_the_pipes_buffer_reaches_a_slow_worker_under_uvloop(
    scene_graph_dict: dict,
) -> None:
    """The service runs on uvloop, whose add_reader leaves the pipe non-blocking: a scene graph of 2,000
    objects (hundreds of kB, where the pipe holds 64 kB) sent to a worker that is not reading yet (stopped
    for 0.3 s) must still arrive whole (it failed part-way, EAGAIN, as a "dead worker" before)."""
    import threading

    import uvloop

    from app.scene_graph.model import SceneGraph

    objects = [
        dict(
            obj,
            id=f"{k}-{obj['id']}",
            center=[obj["center"][0] + 12.0 * k, *obj["center"][1:]],
            region_id=None,
        )
        for k in range(34)
        for obj in scene_graph_dict["objects"]
    ][:2000]
    big = SceneGraph.model_validate({"regions": [], "objects": objects})
    assert len(pickle.dumps(big)) > 4 * 65536
    small = SceneGraph.model_validate(scene_graph_dict)
    workers = WorkerProcesses(model_free_settings(), 1)
    workers.start()
    (pid,) = workers.pids()

    async def run() -> Any:
        await workers.ground("geometric", "builtin", small, "the bag is on the desk", None)  # the reader set
        os.kill(pid, signal.SIGSTOP)
        threading.Timer(0.3, os.kill, (pid, signal.SIGCONT)).start()
        return await workers.ground("geometric", "builtin", big, "the mug is on one of the tables", None)

    try:
        grounding = uvloop.run(run())
        assert (grounding.proposal.parse.target, len(grounding.hypotheses)) == ("mug", 5)
        assert workers.pids() == [pid]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
        workers.close()


def test_a_worker_dying_while_it_holds_a_request_fails_that_request_alone(scene_graph_dict: dict) -> None:
    """The worker is stopped (SIGSTOP) before the request reaches it and killed once the request is in its
    pipe: that request gets `ModelUnavailable`; the next one waits for a new worker to load and is served."""
    from app.errors import ModelUnavailable
    from app.scene_graph.model import SceneGraph

    workers = WorkerProcesses(model_free_settings(), 1)
    workers.start()
    scene = SceneGraph.model_validate(scene_graph_dict)
    (pid,) = workers.pids()

    async def run() -> Any:
        os.kill(pid, signal.SIGSTOP)
        held = asyncio.create_task(
            workers.ground("geometric", "builtin", scene, "the mug is on the desk", None)
        )
        await asyncio.sleep(0.05)  # written into the stopped worker's pipe
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(ModelUnavailable, match="worker process died"):
            await held
        return await workers.ground("geometric", "builtin", scene, "the book is on the desk", None)

    try:
        grounding = asyncio.run(run())
        assert grounding.proposal.parse.target == "book"
        (new,) = workers.pids()
        assert new != pid
    finally:
        workers.close()


def test_a_request_process_with_workers_describes_the_models_from_their_files_as_loaded_ones_do() -> None:
    """With grounding workers the request process loads no model (`WorkerServed`); what /v1/models says of
    the LSM and the built-in proposer is what the loaded models say of themselves."""
    from app.api.bootstrap import WorkerServed, build_sensors
    from app.api.observability import Metrics
    from app.lsm.grounder import LSMGrounder
    from app.settings import Settings

    settings = Settings(_env_file=None, grounder="lsm", proposer="builtin")  # type: ignore[call-arg]
    described = build_sensors(settings, Metrics(), in_workers=True)
    assert isinstance(described.grounders["lsm"], WorkerServed)
    assert isinstance(described.proposers["builtin"], WorkerServed)
    loaded = build_sensors(settings, Metrics())
    assert isinstance(loaded.grounders["lsm"], LSMGrounder)
    for name in ("lsm", "geometric", "fixed"):
        assert described.grounders[name].describe() == loaded.grounders[name].describe()
    assert described.proposers["builtin"].describe() == loaded.proposers["builtin"].describe()
    with_llm = build_sensors(
        settings.model_copy(update={"llm_url": "http://127.0.0.1:9"}), Metrics(), in_workers=True
    )
    assert not isinstance(with_llm.grounders["lsm"], WorkerServed)  # the LLM parts need them here


def test_the_request_process_of_a_pooled_service_never_imports_torch() -> None:
    """What a replica's request process runs at start-up and to describe its models imports no torch or
    transformers: their memory is the workers' alone."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from app.api.app import create_app\n"
        "from app.api.bootstrap import build_sensors\n"
        "from app.api.observability import Metrics\n"
        "from app.settings import Settings\n"
        "settings = Settings(_env_file=None, grounder='lsm', proposer='builtin', worker_processes=1)\n"
        "create_app(settings)\n"
        "build_sensors(settings, Metrics(), in_workers=True)\n"
        "print(sorted(m for m in ('torch', 'transformers') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]", out.stderr
