"""Session stores: the same behaviour from the memory store (plain and durable) and the Redis store.

The stores are called through `tests.store_ops.StoreOps` (each call on an event loop of its own), with the
changes the service makes (`app.sessions.changes`). The reference for every update is a local `Session`
that applies the same operations directly. The Redis tests start a private `redis-server` on a free
loopback port and skip only when the binary is absent.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.belief.fusion import LayerLimits
from app.belief.session import SensorModel, Session, language_log_likelihood, new_session
from app.belief.summary import summarize
from app.errors import Conflict, InvalidInput, NotFound, StoreUnavailable
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph
from app.sessions import changes
from app.sessions.service import summary_options
from app.sim.service import free_port
from app.stores import MemorySessionStore, SessionStore, open_store
from app.stores.memory import _HEADER
from tests.harness import RedisServer
from tests.store_ops import StoreOps

REPO = Path(__file__).resolve().parent.parent
SCENE_DICT = {
    "regions": [{"id": "r", "name": "living room", "center": [2.0, 1.0, 1.0], "size": [4.0, 2.0, 2.0]}],
    "objects": [
        {"id": "1", "label": "table", "center": [1.0, 1.0, 0.4], "size": [1.0, 0.8, 0.8], "region_id": "r"},
        {"id": "2", "label": "sofa", "center": [3.0, 1.0, 0.4], "size": [1.6, 0.9, 0.8], "region_id": "r"},
    ],
}
SCENE = SceneGraph.model_validate(SCENE_DICT)
LABELS = {0: "floor", 1: "backpack", 2: "table"}


UNCLAMPED = LayerLimits(vis_min=-1e4, vis_max=1e4, lang_span=1e4)


def make_session(
    session_id: str | None = None, robot_id: str = "robot-1", limits: LayerLimits | None = None
) -> Session:
    sid = session_id or uuid.uuid4().hex
    return new_session(robot_id, SCENE, "backpack", label_map=LABELS, session_id=sid, limits=limits)


def wide_mixture(rng: np.random.Generator) -> GaussianMixture:
    """A broad two-component mixture over the test room."""
    gaussians = [
        Gaussian(rng.uniform([0.5, 0.5, 0.2], [3.5, 1.5, 1.2]), np.diag(rng.uniform(1.0, 3.0, 3)))
        for _ in range(2)
    ]
    return GaussianMixture.from_components(rng.uniform(0.3, 1.0, 2), gaussians)


Op = Callable[[Any], Any]  # applied to a store-like target: (store, session id) or a local Session


def random_ops(seed: int, n: int, n_voxels: int) -> list[tuple[str, dict[str, Any]]]:
    """Mixed updates: broad utterances, labels with a tp/fp override, detections; random repeated voxels."""
    rng = np.random.default_rng(seed)
    ops: list[tuple[str, dict[str, Any]]] = []
    for _ in range(n):
        kind = rng.choice(["utterance", "labels", "detections"], p=[0.2, 0.5, 0.3])
        if kind == "utterance":
            ops.append(("utterance", {"mixture": wide_mixture(rng)}))
        elif kind == "labels":
            m = int(rng.integers(1, 300))
            ops.append(
                (
                    "labels",
                    {
                        "labels": rng.integers(0, 3, m),
                        "flat_idx": rng.integers(0, n_voxels, m),
                        "tp": 0.6,
                        "fp": 0.4,
                    },
                )
            )
        else:
            m = int(rng.integers(1, 300))
            ops.append(
                (
                    "detections",
                    {"p_target": rng.uniform(0.3, 0.7, m), "flat_idx": rng.integers(0, n_voxels, m)},
                )
            )
    return ops


def apply_to_store(store: StoreOps, session_id: str, op: tuple[str, dict[str, Any]]) -> int:
    kind, args = op
    if kind == "utterance":
        return store.utter(session_id, args["mixture"]).version
    if kind == "labels":
        a = dict(args)
        return store.observe(session_id, a.pop("labels"), **a).version
    a = dict(args)
    return store.detect(session_id, a.pop("p_target"), **a).version


def apply_to_session(session: Session, op: tuple[str, dict[str, Any]]) -> None:
    kind, args = op
    if kind == "utterance":
        session.belief.apply_utterance(args["mixture"])
    elif kind == "labels":
        a = dict(args)
        session.belief.apply_increments(session.observation_batch(a.pop("labels"), **a))
    else:
        a = dict(args)
        session.belief.apply_increments(session.detection_batch(a.pop("p_target"), **a))


def assert_same_belief(got: Session, expected: Session, exact: bool = True) -> None:
    assert got.version == expected.version
    if exact:
        np.testing.assert_array_equal(got.belief.lang, expected.belief.lang)
        np.testing.assert_array_equal(got.belief.vis, expected.belief.vis)
    else:
        np.testing.assert_allclose(got.belief.lang, expected.belief.lang, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(got.belief.vis, expected.belief.vis, rtol=1e-5, atol=1e-5)


def assert_unclamped(session: Session) -> None:
    limits = session.belief.limits
    assert session.belief.lang.min() > -limits.lang_span
    assert limits.vis_min < session.belief.vis.min() and session.belief.vis.max() < limits.vis_max
    assert session.belief.lang.min() < -1.0 and np.abs(session.belief.vis).max() > 1.0  # not a trivial belief


# -- Redis: the `redis_url` fixture (tests/conftest.py) gives a real server on loopback ------------------


def redis_store(url: str, **kwargs: Any) -> Any:
    """A `RedisSessionStore` on `url` with a prefix of its own, called through `StoreOps`."""
    from app.stores.redis_store import RedisSessionStore

    kwargs.setdefault("prefix", f"test-{uuid.uuid4().hex[:8]}")
    kwargs.setdefault("block_voxels", 1024)  # several blocks even on the small test grid
    return StoreOps(RedisSessionStore(url, **kwargs))


def memory_store(*args: Any, **kwargs: Any) -> Any:
    """A `MemorySessionStore(*args, **kwargs)` called through `StoreOps`."""
    return StoreOps(MemorySessionStore(*args, **kwargs))


@pytest.fixture(
    params=[
        "memory",
        "durable",
        pytest.param("redis", marks=pytest.mark.redis),
        pytest.param("redis-cluster", marks=pytest.mark.redis),
    ]
)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Any]:
    if request.param == "memory":
        s: Any = memory_store()
    elif request.param == "durable":
        s = memory_store(tmp_path / "data", snapshot_every=5)
    elif request.param == "redis":
        s = redis_store(request.getfixturevalue("redis_url"))
    else:
        s = redis_store(request.getfixturevalue("redis_cluster_url"))
        assert s.clustered
    yield s
    s.close()


# -- behaviour every store shares --------------------------------------------------------------------------


def test_round_trip_list_and_delete(store: Any) -> None:
    session = make_session("s-1")
    session.belief.apply_utterance(wide_mixture(np.random.default_rng(0)))  # a non-trivial initial belief
    info = store.create(session)
    assert (info.id, info.robot_id, info.version, info.n_voxels) == (
        "s-1",
        "robot-1",
        1,
        session.grid.n_voxels,
    )
    got = store.get("s-1")
    assert_same_belief(got, session)
    assert {k: v for k, v in got.meta().items() if k != "updated_at"} == {
        k: v for k, v in session.meta().items() if k != "updated_at"
    }
    store.create(make_session("s-2", robot_id="robot-2"))
    assert [i.id for i in store.list()] == ["s-1", "s-2"]
    assert [i.id for i in store.list("robot-2")] == ["s-2"]
    assert store.list("nobody") == []
    with pytest.raises(InvalidInput):
        store.create(make_session("s-1"))
    with pytest.raises(InvalidInput):
        store.create(make_session("../escape"))
    store.delete("s-1")
    for call in (
        lambda: store.get("s-1"),
        lambda: store.delete("s-1"),
        lambda: store.utter("s-1", wide_mixture(np.random.default_rng(1))),
    ):
        with pytest.raises(NotFound):
            call()
    assert [i.id for i in store.list()] == ["s-2"]


def test_updates_match_a_local_reference(store: Any) -> None:
    session = make_session()
    reference = session.copy()
    store.create(session)
    n = session.grid.n_voxels
    ops = random_ops(1, 12, n)
    for number, op in enumerate(ops, start=1):
        assert apply_to_store(store, session.id, op) == number
        apply_to_session(reference, op)
    points = reference.grid.centers(np.array([3, 4, 5]))
    points = np.vstack([points, [[50.0, 0.0, 0.0]]])
    result = store.observe(session.id, ["Backpacks", "table", "rucksack", "table"], points=points)
    assert (result.voxels_updated, result.voxels_outside) == (3, 1)
    reference.belief.apply_increments(
        reference.observation_batch(["Backpacks", "table", "rucksack", "table"], points=points)
    )
    moved = SceneGraph.model_validate({**SCENE_DICT, "objects": SCENE_DICT["objects"][:1]})
    assert store.replace_scene_graph(session.id, moved) == len(ops) + 2
    reference.scene_graph = moved
    reference.belief.version += 1
    got = store.get(session.id)
    assert_same_belief(got, reference)
    assert got.scene_graph == moved
    layers = store.layers(session.id)
    np.testing.assert_array_equal(layers.vis, reference.belief.vis)
    assert layers.version == reference.version
    expected = summarize(reference.grid, reference.belief.lang, reference.belief.vis, moved)
    assert store.summary(session.id) == dataclasses.replace(expected, version=reference.version)


def test_rejected_updates_change_nothing(store: Any) -> None:
    session = make_session()
    store.create(session)
    bad_mixture = GaussianMixture(np.array([1.0]), np.array([[np.nan, 0.0, 0.0]]), np.eye(3)[None])
    with pytest.raises(InvalidInput):
        store.utter(session.id, bad_mixture)
    with pytest.raises(InvalidInput):
        store.observe(session.id, [7], flat_idx=np.array([0]))  # id 7 is not in the label map
    with pytest.raises(InvalidInput):
        store.detect(session.id, [0.5], flat_idx=np.array([session.grid.n_voxels]))
    got = store.get(session.id)
    assert got.version == 0 and not got.belief.lang.any() and not got.belief.vis.any()


def test_an_utterance_decided_against_another_target_class_is_refused(store: Any) -> None:
    session = make_session()  # its target: backpack
    store.create(session)
    mixture = wide_mixture(np.random.default_rng(0))
    log_likelihood = language_log_likelihood(session.grid, mixture)
    # Decided while the session had no target yet (a concurrent utterance named it since).
    change = changes.utterance(mixture, log_likelihood, session.grid, names_target="mug", target_read="")
    with pytest.raises(Conflict):
        store.update(session.id, change)
    got = store.get(session.id)
    assert got.version == 0 and got.target_label == "backpack" and not got.belief.lang.any()
    same = changes.utterance(mixture, log_likelihood, session.grid, target_read="backpack")
    assert store.update(session.id, same).version == 1


def test_voxel_coordinates_equal_flat_indices_and_those_outside_the_grid_are_counted(store: Any) -> None:
    session = make_session()
    store.create(session)
    nx, ny, nz = session.grid.shape
    flat = np.array([0, 5, session.grid.n_voxels - 1])
    ijk = np.vstack([session.grid.flat_to_ijk(flat), [[-1, 0, 0], [nx, 0, 0], [0, ny, nz]]])
    result = store.observe(session.id, np.ones(len(ijk), dtype=np.int64), voxels=ijk)
    assert (result.voxels_updated, result.voxels_outside) == (3, 3)
    detections = store.detect(session.id, np.full(len(ijk), 0.8), voxels=ijk)
    assert (detections.voxels_updated, detections.voxels_outside) == (3, 3)
    for batch in (
        session.observation_batch(np.ones(3, dtype=np.int64), flat_idx=flat),
        session.detection_batch(np.full(3, 0.8), flat_idx=flat),
    ):
        session.belief.apply_increments(batch)
    assert_same_belief(store.get(session.id), session)
    with pytest.raises(InvalidInput, match="voxels"):
        store.detect(session.id, [0.5], voxels=np.array([[0.5, 0.0, 0.0]]))  # not integers
    with pytest.raises(InvalidInput, match="exactly one"):
        store.detect(session.id, [0.5], voxels=ijk[:1], flat_idx=flat[:1])
    assert store.head(session.id).version == 2


class Refused(Exception):
    pass


class Writers:
    """A `Caller` (`app.sessions.changes.Caller`) that may write the sessions of the robots it names (all of
    them when it names none) and records whose sessions it was asked about."""

    def __init__(self, *robots: str) -> None:
        self.robots = set(robots)
        self.asked: list[str] = []

    def can_read(self, robot_id: str) -> bool:
        return not self.robots or robot_id in self.robots

    def require_read(self, robot_id: str) -> None:
        if not self.can_read(robot_id):
            raise Refused(robot_id)

    def require_write(self, robot_id: str) -> None:
        self.asked.append(robot_id)
        self.require_read(robot_id)


def test_an_update_is_authorized_against_its_owner_before_anything_changes(store: Any) -> None:
    session = make_session(robot_id="robot-7")
    store.create(session)
    only_robot_1 = Writers("robot-1")
    ijk = session.grid.flat_to_ijk(np.array([3, 4]))
    with pytest.raises(Refused):
        store.observe(session.id, [1, 1], voxels=ijk, caller=only_robot_1)
    with pytest.raises(Refused):
        store.detect(session.id, [0.9, 0.9], voxels=ijk, caller=only_robot_1)
    with pytest.raises(Refused):  # refused before the labels are looked at (7 is not in the label map)
        store.observe(session.id, [7, 7], voxels=ijk, caller=only_robot_1)
    with pytest.raises(Refused):
        store.utter(session.id, wide_mixture(np.random.default_rng(2)), caller=only_robot_1)
    with pytest.raises(Refused):
        store.replace_scene_graph(session.id, SCENE, caller=only_robot_1)
    with pytest.raises(Refused):  # refused before the label is looked at ("sofa" is not in the label map)
        store.set_target(session.id, "sofa", caller=only_robot_1)
    assert only_robot_1.asked == ["robot-7"] * 6
    got = store.get(session.id)
    assert got.version == 0 and not got.belief.vis.any() and not got.belief.lang.any()
    anyone = Writers()
    assert store.detect(session.id, [0.9, 0.9], voxels=ijk, caller=anyone).version == 1
    assert anyone.asked == ["robot-7"]
    with pytest.raises(NotFound):
        store.detect("no-such-session", [0.9], voxels=ijk[:1], caller=only_robot_1)


def test_concurrent_updates_on_one_session_equal_the_sequential_sum(store: Any) -> None:
    session = make_session(limits=UNCLAMPED)  # clamping would make the order matter
    store.create(session)
    per_thread = [random_ops(10 + t, 8, session.grid.n_voxels) for t in range(4)]
    errors: list[BaseException] = []

    def worker(ops: list[tuple[str, dict[str, Any]]]) -> None:
        try:
            for op in ops:
                apply_to_store(store, session.id, op)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(ops,)) for ops in per_thread]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    reference = session.copy()
    for ops in per_thread:
        for op in ops:
            apply_to_session(reference, op)
    assert_unclamped(reference)
    assert_same_belief(store.get(session.id), reference, exact=False)


# -- expiry -----------------------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_000.0

    def __call__(self) -> float:
        return self.now


@pytest.mark.parametrize("durable", [False, True])
def test_memory_sessions_expire_after_idle_ttl(tmp_path: Path, durable: bool) -> None:
    clock = FakeClock()
    data_dir = tmp_path / "data" if durable else None
    store = memory_store(data_dir, ttl_s=10.0, clock=clock)
    session = make_session("idle")
    store.create(session)
    clock.now += 8
    store.detect("idle", [0.6], flat_idx=np.array([0]))  # a write extends the lifetime
    clock.now += 8
    assert store.get("idle").version == 1  # reads work but do not extend
    clock.now += 3
    with pytest.raises(NotFound):
        store.get("idle")
    assert store.list() == []
    assert store.purge() == 0  # the read removed it already
    store.create(make_session("idle"))  # the id is free again
    clock.now += 11
    assert store.purge() == 1
    with pytest.raises(NotFound):
        store.head("idle")
    store.close()
    if durable:
        clock.now += 20
        reopened = memory_store(data_dir, ttl_s=10.0, clock=clock)
        assert reopened.list() == []
        reopened.close()


@pytest.mark.redis
def test_redis_sessions_expire_after_idle_ttl(redis_url: str) -> None:
    store = redis_store(redis_url, ttl_s=0.6)
    store.create(make_session("short"))
    store.create(make_session("kept"))
    time.sleep(0.4)
    store.detect("kept", [0.6], flat_idx=np.array([0]))
    time.sleep(0.4)
    with pytest.raises(NotFound):
        store.get("short")
    assert [i.id for i in store.list()] == ["kept"]
    assert store.get("kept").version == 1
    store.close()


# -- durability of the memory store ---------------------------------------------------------------------


def durable_state(store: StoreOps) -> dict[str, Session]:
    return {info.id: store.get(info.id) for info in store.list()}


def assert_same_sessions(got: dict[str, Session], expected: dict[str, Session]) -> None:
    assert sorted(got) == sorted(expected)
    for sid, session in expected.items():
        assert_same_belief(got[sid], session)
        assert got[sid].meta() == session.meta()


def reopen(data_dir: Path, **kwargs: Any) -> Any:
    """Open the directory again once the caller dropped its store unclosed (as a crash would)."""
    gc.collect()  # the dropped store's LOCK file handle goes with it
    return memory_store(data_dir, **kwargs)


def test_reopen_without_close_gives_the_identical_belief(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    store = memory_store(data_dir, snapshot_every=10_000)
    a, b = make_session("a"), make_session("b", robot_id="robot-2")
    store.create(a)
    store.create(b)
    for op in random_ops(3, 6, a.grid.n_voxels):
        apply_to_store(store, "a", op)
    store.replace_scene_graph("b", SceneGraph.model_validate({**SCENE_DICT, "objects": []}))
    store.utter("b", wide_mixture(np.random.default_rng(5)))
    before = durable_state(store)
    del store
    store = reopen(data_dir)
    assert_same_sessions(durable_state(store), before)
    store.close()


@pytest.mark.parametrize("tail", ["short header", "short payload", "bad crc"])
def test_a_torn_last_record_is_ignored(tmp_path: Path, tail: str) -> None:
    data_dir = tmp_path / "data"
    store = memory_store(data_dir, snapshot_every=10_000)
    store.create(make_session("a"))
    for op in random_ops(4, 5, store.get("a").grid.n_voxels):
        apply_to_store(store, "a", op)
    before = durable_state(store)
    segment = max(data_dir.glob("wal-*.log"))
    torn = {
        "short header": b"\x10\x00",
        "short payload": _HEADER.pack(5000, 0) + b"\x81" * 100,
        "bad crc": _HEADER.pack(4, 12345) + b"\x80\x80\x80\x80",
    }[tail]
    with segment.open("ab") as fh:
        fh.write(torn)  # a crash in the middle of an append
    del store
    store = reopen(data_dir)
    assert_same_sessions(durable_state(store), before)
    store.detect("a", [0.9], flat_idx=np.array([7]))  # appends after the cut-off record
    after = durable_state(store)
    del store
    store = reopen(data_dir)
    assert_same_sessions(durable_state(store), after)
    store.close()


def test_snapshots_and_log_replay(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    store = memory_store(data_dir, snapshot_every=3)
    store.create(make_session("a"))
    store.create(make_session("gone"))
    ops = random_ops(6, 10, store.get("a").grid.n_voxels)
    for op in ops:
        apply_to_store(store, "a", op)
    store.delete("gone")
    store.create(make_session("gone"))  # the same id again, a new session
    store.detect("gone", [0.8], flat_idx=np.array([3]))
    assert (data_dir / "sessions" / "a.snap").exists()
    assert len(list(data_dir.glob("wal-*.log"))) <= 2  # compaction dropped the older segments
    before = durable_state(store)
    assert before["gone"].version == 1
    del store
    store = reopen(data_dir, snapshot_every=3)
    assert_same_sessions(durable_state(store), before)
    store.close()


def test_a_crash_between_snapshot_and_log_deletion_does_not_double_apply(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    store = memory_store(data_dir, snapshot_every=10_000)
    store.create(make_session("a"))
    ops = random_ops(7, 8, store.get("a").grid.n_voxels)
    for op in ops[:5]:
        apply_to_store(store, "a", op)
    saved = {p.name: p.read_bytes() for p in data_dir.glob("wal-*.log")}
    store._compact()  # snapshots "a" and deletes the old segments ...
    for name, data in saved.items():
        (data_dir / name).write_bytes(data)  # ... which a crash would have left behind
    for op in ops[5:]:
        apply_to_store(store, "a", op)
    before = durable_state(store)
    del store
    store = reopen(data_dir)
    assert_same_sessions(durable_state(store), before)
    store.close()


def test_a_data_directory_serves_one_store_at_a_time(tmp_path: Path) -> None:
    first = MemorySessionStore(tmp_path)
    with pytest.raises(StoreUnavailable):
        MemorySessionStore(tmp_path)
    first.close()
    MemorySessionStore(tmp_path).close()


CRASHING_WRITER = """
import asyncio, json, sys
import numpy as np
from app.belief.session import new_session
from app.scene_graph.model import SceneGraph
from app.sessions import changes
from app.stores import MemorySessionStore

async def main():
    store = MemorySessionStore(sys.argv[1], snapshot_every=7)
    scene = SceneGraph.model_validate(json.loads(sys.argv[2]))
    label_map = {0: "floor", 1: "backpack"}
    session = new_session("robot", scene, "backpack", label_map=label_map, session_id="crash")
    await store.create(session)
    k = 0
    while True:
        k += 1
        rng = np.random.default_rng(k)
        labels, idx = rng.integers(0, 2, 400), rng.integers(0, session.grid.n_voxels, 400)
        change = changes.labels(labels, flat_idx=idx, max_voxels=400, inline=True)
        result = await store.update("crash", change)
        print("ack", result.version, flush=True)

asyncio.run(main())
"""


def test_kill_9_loses_no_acknowledged_update(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    proc = subprocess.Popen(
        [sys.executable, "-c", CRASHING_WRITER, str(data_dir), json.dumps(SCENE_DICT)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    acked = 0
    try:
        for line in proc.stdout:
            acked = int(line.split()[1])
            if acked >= 25:
                break
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert acked >= 25, "the writer died before acknowledging enough updates"
    store = memory_store(data_dir)
    got = store.get("crash")
    assert got.version >= acked  # it may hold one more update that was logged but not yet acknowledged
    reference = new_session(
        "robot", SCENE, "backpack", label_map={0: "floor", 1: "backpack"}, session_id="crash"
    )
    for k in range(1, got.version + 1):
        rng = np.random.default_rng(k)
        labels, idx = rng.integers(0, 2, 400), rng.integers(0, reference.grid.n_voxels, 400)
        reference.belief.apply_increments(reference.observation_batch(labels, flat_idx=idx))
    assert_same_belief(got, reference)
    store.close()


# -- Redis: replicas, blocks, failures --------------------------------------------------------------------


@pytest.mark.redis
def test_two_replicas_updating_one_session_equal_the_sequential_sum(redis_url: str) -> None:
    first = redis_store(redis_url)
    second = redis_store(redis_url, prefix=first.prefix)  # another process's view of the same server
    session = make_session(limits=UNCLAMPED)  # clamping would make the order matter
    first.create(session)
    per_thread = [random_ops(20 + t, 6, session.grid.n_voxels) for t in range(4)]
    errors: list[BaseException] = []

    def worker(replica: Any, ops: list[tuple[str, dict[str, Any]]]) -> None:
        try:
            for op in ops:
                apply_to_store(replica, session.id, op)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [
        threading.Thread(target=worker, args=((first, second)[t % 2], ops))
        for t, ops in enumerate(per_thread)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    reference = session.copy()
    for ops in per_thread:
        for op in ops:
            apply_to_session(reference, op)
    assert_unclamped(reference)
    assert_same_belief(second.get(session.id), reference, exact=False)
    first.close()
    second.close()


@pytest.mark.redis
def test_replicas_share_each_version_summary_and_never_serve_a_stale_one(
    redis_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import app.belief.session as session_module

    calls: list[int] = []

    def counting_summarize(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return summarize(*args, **kwargs)

    monkeypatch.setattr(session_module, "summarize", counting_summarize)  # what `Session.summary` calls
    first = redis_store(redis_url)
    second = redis_store(redis_url, prefix=first.prefix)
    session = make_session()
    first.create(session)
    rng = np.random.default_rng(3)
    for step in range(3):
        apply_to_store(first, session.id, random_ops(40 + step, 1, session.grid.n_voxels)[0])
        expected = first.get(session.id)
        reference = dataclasses.replace(
            summarize(expected.grid, expected.belief.lang, expected.belief.vis, SCENE, top_k=3),
            version=expected.version,
        )
        options = summary_options(3, expected.created_at)
        for reader in (first, second):  # the last version's entry is not this version's summary
            assert reader.run(reader.summary_get(session.id, expected.version, options)) is None
        replica = (first, second)[int(rng.integers(0, 2))]
        assert replica.summary(session.id, top_k=3) == reference  # computed and stored
        assert second.summary(session.id, top_k=3) == reference  # read back, not recomputed
        assert first.summary(session.id, top_k=3) == reference
        assert len(calls) == step + 1
    assert first.summary(session.id, top_k=4).top_voxels[3] is not None  # other options: their own entry
    assert len(calls) == 4
    first.delete(session.id)
    assert not first._client.exists(first._key(session.id, "summary"))
    first.close()
    second.close()


@pytest.mark.redis
def test_an_observation_batch_writes_only_the_blocks_it_touches(redis_url: str) -> None:
    store = redis_store(redis_url, block_voxels=1024)
    session = make_session()
    store.create(session)
    vis_key = store._key(session.id, "vis")
    store.observe(session.id, [1, 0], flat_idx=np.array([5, 1030]))
    assert sorted(int(k) for k in store._client.hkeys(vis_key)) == [0, 1]
    before = store._client.hget(vis_key, "0")
    store.observe(session.id, [1], flat_idx=np.array([3 * 1024 + 2]))
    assert sorted(int(k) for k in store._client.hkeys(vis_key)) == [0, 1, 3]
    assert store._client.hget(vis_key, "0") == before
    store.close()


@pytest.mark.redis
def test_a_session_stored_with_another_block_size_is_read_and_updated_in_its_own(redis_url: str) -> None:
    from app.stores.redis_store import LEGACY_BLOCK_VOXELS

    session = make_session()
    session.belief.apply_utterance(wide_mixture(np.random.default_rng(3)))
    older = redis_store(redis_url, block_voxels=LEGACY_BLOCK_VOXELS)
    older.create(session)
    store = redis_store(redis_url, block_voxels=1024, prefix=older.prefix)
    older._client.hdel(older._key(session.id, "meta"), "block_voxels")  # as stored before the field existed
    ops = random_ops(5, 12, session.grid.n_voxels)
    for op in ops:
        apply_to_store(store, session.id, op)
        apply_to_session(session, op)
    assert_same_belief(store.get(session.id), session, exact=False)
    assert store._client.hkeys(store._key(session.id, "vis")) == [b"0"]  # still one 65,536-voxel block
    older.close()
    store.close()


@pytest.mark.redis
def test_a_session_lock_held_elsewhere_makes_updates_wait_then_give_up(redis_url: str) -> None:
    store = redis_store(redis_url, lock_wait_s=0.2)
    session = make_session()
    store.create(session)
    store._client.set(store._key(session.id, "lock"), "another-replica", px=400)
    with pytest.raises(StoreUnavailable):
        store.detect(session.id, [0.9], flat_idx=np.array([0]))
    time.sleep(0.3)  # the other holder's lock expires
    assert store.detect(session.id, [0.9], flat_idx=np.array([0])).version == 1
    store.close()


@pytest.mark.redis
def test_a_lock_left_by_a_killed_holder_delays_writers_only_by_its_short_ttl(redis_url: str) -> None:
    """A replica killed mid-update (kill -9) leaves its lock: it lasts the lock's ttl (3 s; the old 30 s made
    every write wait its full 10 s and give up), since live holders renew theirs. A writer that waits for a
    lock at most a second longer than that ttl gets it."""
    from app.stores.redis_store import DEFAULT_LOCK_TTL_S

    store = redis_store(redis_url, lock_wait_s=DEFAULT_LOCK_TTL_S + 1.0)
    session = make_session()
    store.create(session)
    store._client.set(store._key(session.id, "lock"), "a-killed-replica", px=int(DEFAULT_LOCK_TTL_S * 1000))
    assert store.detect(session.id, [0.9], flat_idx=np.array([0])).version == 1  # else StoreUnavailable
    store.close()


@pytest.mark.redis
def test_a_live_lock_holder_keeps_its_lock_past_the_ttl(redis_url: str) -> None:
    prefix = f"test-{uuid.uuid4().hex[:8]}"
    holder = redis_store(redis_url, prefix=prefix, lock_ttl_s=0.3)
    other = redis_store(redis_url, prefix=prefix, lock_wait_s=0.2)
    holder.create(make_session("held"))
    with holder._session_lock("held") as token:
        time.sleep(1.0)  # three ttls of work
        assert holder._client.get(holder._key("held", "lock")) == token.encode()
        with pytest.raises(StoreUnavailable):  # a writer that takes the lock waits, then gives up
            other.detect("held", [0.9], flat_idx=np.array([0]))
    assert holder._client.get(holder._key("held", "lock")) is None  # released
    holder.close()
    other.close()


def _layer_reads(commands: list[str]) -> list[str]:
    """The reads of a layer hash among MONITOR's commands."""
    reads = {"HGETALL", "HMGET", "HGET"}
    return [c for c in commands if c.split()[0] in reads and c.split()[1].endswith((":lang", ":vis"))]


@pytest.mark.redis
def test_the_replica_that_wrote_last_updates_and_summarises_from_its_mirror(redis_url: str) -> None:
    store = redis_store(redis_url)
    session = make_session()
    store.create(session)
    ops = random_ops(11, 8, session.grid.n_voxels)
    for op in ops:
        commands = redis_commands(store, lambda op=op: apply_to_store(store, session.id, op))
        assert not _layer_reads(commands)  # computed from the mirror, committed on its version
        apply_to_session(session, op)
    commands = redis_commands(store, lambda: store.summary(session.id, top_k=3))
    assert not _layer_reads(commands) and any("summary" in c for c in commands)
    fresh = redis_store(redis_url, prefix=store.prefix)  # no mirror: reads everything from Redis
    assert_same_belief(fresh.get(session.id), session)
    expected = summarize(session.grid, session.belief.lang, session.belief.vis, SCENE, top_k=3)
    assert store.summary(session.id, top_k=3) == dataclasses.replace(expected, version=session.version)
    fresh.close()
    store.close()


@pytest.fixture
def replicas(redis_url: str) -> Iterator[tuple[Any, Any]]:
    """Two stores on one Redis, as two service processes see it (each with its own mirror)."""
    first = redis_store(redis_url)
    second = redis_store(redis_url, prefix=first.prefix)
    yield first, second
    first.close()
    second.close()


@pytest.mark.redis
def test_a_mirror_left_behind_by_another_replica_is_never_used(replicas: tuple[Any, Any]) -> None:
    first, second = replicas
    session = make_session()
    first.create(session)
    for step, op in enumerate(random_ops(12, 9, session.grid.n_voxels)):
        replica = (first, second)[step % 3 == 2]  # the first's mirror goes stale every third update
        apply_to_store(replica, session.id, op)
        apply_to_session(session, op)
        expected = summarize(session.grid, session.belief.lang, session.belief.vis, SCENE, top_k=2)
        for reader in (first, second):
            summary = reader.summary(session.id, top_k=2)
            assert summary.version == session.version
            assert summary.top_voxels == expected.top_voxels
    assert_same_belief(first.get(session.id), session, exact=False)


@pytest.mark.redis
def test_a_session_made_again_under_its_id_is_not_mistaken_for_the_mirrored_one(
    replicas: tuple[Any, Any],
) -> None:
    first, second = replicas
    first.create(make_session("again"))
    first.detect("again", [0.9], flat_idx=np.array([7]))  # the first mirrors version 1
    second.delete("again")
    new = make_session("again")
    second.create(new)
    second.detect("again", [0.2], flat_idx=np.array([3]))  # version 1 again, another state
    first.detect("again", [0.6], flat_idx=np.array([3]))
    for p_target in (0.2, 0.6):
        new.belief.apply_increments(new.detection_batch([p_target], flat_idx=np.array([3])))
    assert_same_belief(first.get("again"), new)
    assert first.get("again").belief.vis[7] == 0.0  # nothing of the old session


@pytest.mark.redis
def test_a_session_made_again_for_another_robot_is_authorized_as_that_robot(
    replicas: tuple[Any, Any],
) -> None:
    first, second = replicas
    first.create(make_session("reused", robot_id="robot-1"))
    ijk = np.array([[0, 0, 0]])
    first.detect("reused", [0.9], voxels=ijk)  # the first mirrors robot-1's session
    second.delete("reused")
    second.create(make_session("reused", robot_id="robot-2"))
    only_robot_1 = Writers("robot-1")
    with pytest.raises(Refused):
        first.detect("reused", [0.9], voxels=ijk, caller=only_robot_1)
    assert only_robot_1.asked[-1] == "robot-2"  # the owner of the state the commit would have been made on
    assert second.get("reused").version == 0


@pytest.mark.redis
def test_a_change_is_never_refused_on_the_strength_of_a_stale_mirror(replicas: tuple[Any, Any]) -> None:
    """A change that refuses the mirrored state is refused only if the stored state is that state: a mirror
    left behind by another replica's writes (a target named there, the session made again for another
    robot) is checked against Redis first, on the event loop's path and on the worker thread's alike."""
    first, second = replicas
    session = new_session("robot-1", SCENE, "", label_map=LABELS, session_id="named-elsewhere")
    first.create(session)
    first.detect(session.id, [0.8], flat_idx=np.array([3]))  # the first mirrors it, its target unknown
    with pytest.raises(Conflict):  # refused from a current mirror, which stays
        first.observe(session.id, [1], flat_idx=np.array([3]))
    assert first._mirror.get(session.id) is not None
    assert second.set_target(session.id, "backpack") == 2  # the first's mirror is now stale
    assert first.observe(session.id, [1, 0], flat_idx=np.array([3, 4])).version == 3  # inline, on the loop
    reference = session.copy()
    reference.belief.apply_increments(reference.detection_batch([0.8], flat_idx=np.array([3])))
    reference.set_target_label("backpack")
    reference.belief.version += 1
    reference.belief.apply_increments(reference.observation_batch([1, 0], flat_idx=np.array([3, 4])))
    assert_same_belief(second.get(session.id), reference)

    first.get(session.id)  # mirrored again (robot-1's)
    second.delete(session.id)
    second.create(make_session(session.id, robot_id="robot-2"))
    robot_2 = Writers("robot-2")
    ijk = np.array([[0, 0, 0]])
    assert first.detect(session.id, [0.9], voxels=ijk, caller=robot_2).version == 1  # inline
    first.get(session.id)  # mirrored again (robot-2's)
    second.delete(session.id)
    second.create(make_session(session.id, robot_id="robot-3"))
    robot_3 = Writers("robot-3")
    mixture = wide_mixture(np.random.default_rng(8))
    assert first.utter(session.id, mixture, caller=robot_3).version == 1  # not inline: a worker thread
    assert first.detect(session.id, [0.9], voxels=ijk, caller=robot_3, inline=False).version == 2
    assert robot_3.asked[-2:] == ["robot-3", "robot-3"]


@pytest.mark.redis
def test_voxel_coordinates_read_only_their_blocks_without_a_mirror(redis_url: str) -> None:
    store = redis_store(redis_url)
    session = make_session()
    store.create(session)
    far = session.grid.flat_to_ijk(np.array([0, session.grid.n_voxels - 1]))
    fresh = redis_store(redis_url, prefix=store.prefix)  # no mirror, no grid known: the update reads
    commands = redis_commands(fresh, lambda: fresh.detect(session.id, [0.9, 0.9], voxels=far))
    reads = _layer_reads(commands)
    last_block = str((session.grid.n_voxels - 1) // 1024)
    assert reads and all(c.split()[2:] in (["0", last_block], ["0"], [last_block]) for c in reads), reads
    commands = redis_commands(fresh, lambda: fresh.detect(session.id, [0.9], voxels=far[:1]))
    assert _layer_reads(commands)  # still no mirror: only a full read makes one
    fresh.get(session.id)
    commands = redis_commands(fresh, lambda: fresh.detect(session.id, [0.9], voxels=far[:1]))
    assert not _layer_reads(commands)
    both = np.array([0, session.grid.n_voxels - 1])
    for flat in (both, both[:1], both[:1]):
        session.belief.apply_increments(session.detection_batch(np.full(len(flat), 0.9), flat_idx=flat))
    assert_same_belief(store.get(session.id), session)
    fresh.close()
    store.close()


@pytest.mark.redis
def test_an_event_loop_update_takes_a_worker_thread_only_when_it_must_read(
    replicas: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`RedisSessionStore.update`: an inline change (an observation batch) from the mirror is computed on the
    event loop and committed with the loop's client; otherwise it runs on a worker thread."""
    first, second = replicas
    session = make_session()
    first.create(session)
    threads = count_worker_threads(monkeypatch)
    ijk = session.grid.flat_to_ijk(np.array([2, session.grid.n_voxels - 2]))

    def detect(store: Any, p: float, inline: bool = True) -> tuple[list[str], int]:
        """The commands of one update of `store` and the worker threads it took."""
        session.belief.apply_increments(session.detection_batch([p, p], voxels=ijk))
        before = len(threads)
        change = lambda: store.detect(session.id, [p, p], voxels=ijk, inline=inline)  # noqa: E731
        commands = redis_commands(store, change, session.id)
        return commands, len(threads) - before

    commands, taken = detect(first, 0.8)
    assert not _layer_reads(commands) and taken == 0  # from the mirror made by create
    second.detect(session.id, [0.3], voxels=ijk[:1])  # the first's mirror is now stale
    session.belief.apply_increments(session.detection_batch([0.3], voxels=ijk[:1]))
    commands, taken = detect(first, 0.6)  # its commit failed: it read, on a thread
    assert _layer_reads(commands) and taken == 1
    # ... the meta hash, then only the vision blocks the batch touches
    last_block = str((session.grid.n_voxels - 2) // 1024)
    assert all(c.split()[2:] == ["0", last_block] for c in _layer_reads(commands)), commands
    first.get(session.id)  # a full read mirrors the session again
    commands, taken = detect(first, 0.7)
    assert not _layer_reads(commands) and taken == 0
    commands, taken = detect(first, 0.5, inline=False)  # not inline: from the mirror, on a worker thread
    assert not _layer_reads(commands) and taken == 1
    assert_same_belief(second.get(session.id), session)


def count_worker_threads(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The functions the stores run on worker threads (`anyio.to_thread.run_sync`) from now on."""
    import anyio.to_thread

    calls: list[Any] = []
    run_sync = anyio.to_thread.run_sync

    async def counted(func: Any, *args: Any, **kwargs: Any) -> Any:
        calls.append(func)
        return await run_sync(func, *args, **kwargs)

    monkeypatch.setattr(anyio.to_thread, "run_sync", counted)
    return calls


@pytest.mark.parametrize("durable", [False, True])
def test_a_memory_store_update_takes_a_worker_thread_only_when_it_must_wait(
    tmp_path: Path, durable: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`MemorySessionStore.update`: an inline change of a store without a log runs on the event loop when
    its session's lock is free; otherwise (a log to append to, a change that is not inline, a lock held
    elsewhere) it runs on a worker thread."""
    store = memory_store(tmp_path / "data" if durable else None)
    session = make_session()
    store.create(session)
    threads = count_worker_threads(monkeypatch)

    def detect(p: float, inline: bool) -> int:
        """The worker threads one update took."""
        before = len(threads)
        result = store.detect(session.id, [p], flat_idx=np.array([2]), inline=inline)
        session.belief.apply_increments(session.detection_batch([p], flat_idx=np.array([2])))
        assert result.version == session.version
        return len(threads) - before

    assert detect(0.8, inline=True) == (1 if durable else 0)
    assert detect(0.6, inline=False) == 1
    entry = store._entries[session.id]
    before = len(threads)
    results: list[Any] = []
    with entry.lock:  # another update holds the session
        writer = threading.Thread(
            target=lambda: results.append(
                store.detect(session.id, [0.7], flat_idx=np.array([2]), inline=True)
            )
        )
        writer.start()
        while len(threads) == before and writer.is_alive():  # it waits for the lock on a worker thread
            time.sleep(0.005)
        assert len(threads) == before + 1
    writer.join()
    session.belief.apply_increments(session.detection_batch([0.7], flat_idx=np.array([2])))
    assert results[0].version == session.version == 3
    assert_same_belief(store.get(session.id), session)


@pytest.mark.redis
def test_an_event_loop_update_with_redis_down_raises_store_unavailable() -> None:
    server = RedisServer(shutil.which("redis-server") or "redis-server")
    server.start()
    store = redis_store(server.url, socket_timeout_s=1.0)
    try:
        session = make_session()
        store.create(session)  # mirrored: the update would need no read
        server.stop()
        with pytest.raises(StoreUnavailable):
            store.detect(session.id, [0.9], voxels=np.array([[0, 0, 0]]), inline=True)  # on the loop
    finally:
        store.close()
        server.close()


@pytest.mark.redis
def test_event_loop_calls_after_a_redis_restart_reconnect_and_apply_each_update_once(tmp_path: Path) -> None:
    server = RedisServer(shutil.which("redis-server") or "redis-server", appendonly=True)
    server.start()
    store = redis_store(server.url)
    session = make_session()
    store.create(session)
    ijk = session.grid.flat_to_ijk(np.arange(8).reshape(-1, 1)[:, 0])
    raw = store.store  # one event loop for all the calls below

    def batch(i: int) -> Any:
        return changes.detections(np.array([0.7]), voxels=ijk[i : i + 1], max_voxels=1, inline=True)

    async def run() -> list[int]:
        # Several pooled connections on this loop, then Redis restarts under them (its AOF keeps the data).
        await asyncio.gather(*(raw.head(session.id) for _ in range(4)))
        await asyncio.gather(*(raw.update(session.id, batch(i)) for i in range(4)))
        await asyncio.to_thread(server.restart)
        versions = [(await raw.head(session.id)).version for _ in range(4)]
        for i in range(4, 8):
            versions.append((await raw.update(session.id, batch(i))).version)
        return versions

    try:
        assert asyncio.run(run()) == [4, 4, 4, 4, 5, 6, 7, 8]
        for i in range(8):
            session.belief.apply_increments(session.detection_batch([0.7], voxels=ijk[i : i + 1]))
        assert_same_belief(store.get(session.id), session, exact=False)  # each batch applied once
    finally:
        store.close()
        server.close()


@pytest.mark.redis
def test_a_commit_sent_again_is_told_it_landed_and_applies_once(redis_url: str) -> None:
    """A commit whose reply was lost is sent again (by redis-py, or after a dropped connection), even after
    another writer committed on top of it: its record says it landed, and nothing is applied twice."""
    from app.stores.redis_store import _View

    store = redis_store(redis_url)
    session = make_session("resent")
    store.create(session)
    change = changes.detections(np.array([0.9]), flat_idx=np.array([0]), max_voxels=1)
    mirrored = store._mirror.get("resent")
    view = _View.of("resent", mirrored)  # what `update` computes from, as `_attempt` does
    delta = change.compute(view)
    writes = store._writes(view, delta)
    result = delta.result("resent", view.version + 1, view.grid.n_voxels)
    commit = store._commit_of("resent", view, "", writes, result, None)
    first = store._script("commit")(keys=commit.keys, args=commit.args)
    assert store._committed("resent", first, commit, mirrored)
    store.detect("resent", [0.2], flat_idx=np.array([1]))  # another commit on top
    again = store._script("commit")(keys=commit.keys, args=commit.args)
    assert int(again[0]) == -3 and store._committed("resent", again, commit, None)  # its own record
    for p, i in ((0.9, 0), (0.2, 1)):
        session.belief.apply_increments(session.detection_batch([p], flat_idx=np.array([i])))
    assert_same_belief(store.get("resent"), session)
    store.close()


def test_the_mirror_drops_a_session_only_under_the_name_it_was_used_by() -> None:
    from app.stores.redis_mirror import Mirror, Mirrored

    def entry(version: int) -> Any:
        layer = np.zeros(4, dtype=np.float32)
        return Mirrored((version, b"t"), {}, np.zeros(0, np.int64), 4, b"{}", layer, layer.copy())

    mirror = Mirror(max_bytes=1 << 20)
    mirror.put("s", entry(2))  # another thread's commit replaced the entry an update had used (version 1)
    mirror.drop("s", (1, b"t"))
    assert mirror.get("s") is not None and mirror.get("s", (2, b"t")) is not None
    mirror.drop("s", (2, b"t"))
    assert mirror.get("s") is None
    mirror.put("s", entry(3))
    mirror.drop("s")
    assert mirror.get("s") is None


def test_an_unreachable_redis_raises_store_unavailable(caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("redis")
    port = free_port()
    store = open_store(f"redis://:s3cr3t@127.0.0.1:{port}/0")
    ops = StoreOps(store)
    for call in (
        lambda: ops.get("x"),
        lambda: ops.list(),
        lambda: ops.create(make_session()),
        lambda: ops.head("x"),  # on the event loop's client
        lambda: ops.detect("x", [0.9], flat_idx=np.array([0])),
        lambda: ops.summary("x"),
    ):
        with pytest.raises(StoreUnavailable) as raised:
            call()
        assert str(port) not in str(raised.value) and "s3cr3t" not in str(raised.value)  # a client reads it
    assert str(port) in caplog.text  # the operator does
    store.close()


def test_open_store_picks_the_implementation(tmp_path: Path) -> None:
    store = open_store(None, data_dir=tmp_path)
    assert isinstance(store, MemorySessionStore) and isinstance(store, SessionStore)
    store.close()
    with pytest.raises(InvalidInput):
        open_store("postgres://nowhere")
    assert SensorModel().tp > SensorModel().fp
    pytest.importorskip("redis")
    redis_url = f"redis://127.0.0.1:{free_port()}/0"  # nothing listens: opening connects to nothing yet
    sized = open_store(redis_url, mirror_mib=3)
    assert isinstance(sized, SessionStore) and sized._mirror.max_bytes == 3 << 20
    sized.close()


# -- head() and a target class named later -------------------------------------------------------------------


class AttributeSpy:
    """Stands in for an object and records the names of the attributes read through it."""

    def __init__(self, wrapped: Any) -> None:
        object.__setattr__(self, "_wrapped", wrapped)
        object.__setattr__(self, "read", set())

    def __getattr__(self, name: str) -> Any:
        self.read.add(name)
        return getattr(self._wrapped, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._wrapped, name, value)


def redis_commands(store: Any, call: Callable[[], Any], session_id: str | None = None) -> list[str]:
    """The commands the Redis server (on a cluster: the node holding `session_id`) executes while `call()`
    runs (read through MONITOR)."""
    marker = f"end-{uuid.uuid4().hex}"
    server = store._client
    if store.clustered:
        assert session_id is not None
        server = server.get_redis_connection(server.get_node_from_key(store._key(session_id, "meta")))
    with server.monitor() as monitor:
        call()
        server.echo(marker)
        commands = []
        while (command := monitor.next_command()["command"]) != f"ECHO {marker}":
            commands.append(command)
    return commands


def test_head_and_scene_graph_follow_updates_and_deletion(store: Any) -> None:
    def peek(session_id: str) -> tuple[str, int]:
        info = store.head(session_id)  # on an event loop, as the poll route calls it
        return info.robot_id, info.version

    store.create(make_session("peeked", robot_id="robot-9"))
    assert peek("peeked") == ("robot-9", 0)
    store.detect("peeked", [0.7], flat_idx=np.array([1]))
    store.utter("peeked", wide_mixture(np.random.default_rng(1)))
    assert peek("peeked") == ("robot-9", 2) == ("robot-9", store.get("peeked").version)
    assert store.head_and_scene_graph("peeked") == (store.head("peeked"), SCENE)
    moved = SceneGraph.model_validate({**SCENE_DICT, "objects": SCENE_DICT["objects"][1:]})
    assert store.replace_scene_graph("peeked", moved) == 3
    info, scene_graph = store.head_and_scene_graph("peeked")
    assert scene_graph == moved and (info.robot_id, info.version) == peek("peeked") == ("robot-9", 3)
    store.delete("peeked")
    for absent in ("peeked", "never-made"):
        with pytest.raises(NotFound):
            peek(absent)
        with pytest.raises(NotFound):
            store.head_and_scene_graph(absent)


def test_updates_on_one_event_loop_inline_or_not_match_the_reference_and_check_the_writer(store: Any) -> None:
    session = make_session(robot_id="robot-3")
    store.create(session)
    rng = np.random.default_rng(5)
    raw, anyone, robot_1 = store.store, Writers(), Writers("robot-1")

    async def stream() -> list[int]:  # as the observation route calls them, on one event loop
        versions = []
        for step in range(6):
            ijk = session.grid.flat_to_ijk(rng.integers(0, session.grid.n_voxels, size=40))
            labels = rng.integers(0, 2, size=40)
            how = {"voxels": ijk, "max_voxels": 40, "caller": anyone, "inline": step % 3 != 2}
            if step % 2:
                result = await raw.update(session.id, changes.labels(labels, **how))
                session.belief.apply_increments(session.observation_batch(labels, voxels=ijk))
            else:
                p = rng.uniform(0.05, 0.95, size=40)
                result = await raw.update(session.id, changes.detections(p, **how))
                session.belief.apply_increments(session.detection_batch(p, voxels=ijk))
            versions.append(result.version)
        refused = changes.detections(
            np.array([0.9]), voxels=ijk[:1], max_voxels=1, caller=robot_1, inline=True
        )
        with pytest.raises(Refused):
            await raw.update(session.id, refused)
        absent = changes.labels(np.array([1]), voxels=ijk[:1], max_voxels=1, inline=True)
        with pytest.raises(NotFound):
            await raw.update("never-made", absent)
        return versions

    assert asyncio.run(stream()) == [1, 2, 3, 4, 5, 6]
    assert anyone.asked == ["robot-3"] * 6 and robot_1.asked == ["robot-3"]
    assert_same_belief(store.get(session.id), session)


def test_memory_head_of_an_expired_session_is_not_found() -> None:
    clock = FakeClock()
    store = memory_store(ttl_s=10.0, clock=clock)
    store.create(make_session("brief"))
    clock.now += 11.0
    with pytest.raises(NotFound):
        store.head("brief")
    with pytest.raises(NotFound):
        store.head_and_scene_graph("brief")


def test_an_expired_session_s_events_go_with_it_and_a_new_one_of_its_id_starts_afresh() -> None:
    clock = FakeClock()
    store = memory_store(ttl_s=10.0, clock=clock)
    store.create(make_session("brief"))
    store.detect("brief", [0.7, 0.2], flat_idx=np.array([1, 2]))
    assert [e.kind for e in store.run(store.events.retained("brief"))] == ["created", "update"]
    clock.now += 11.0
    assert store.run(store.purge_expired()) == 1
    assert store.run(store.events.retained("brief")) == []
    store.create(make_session("brief"))
    assert [e.kind for e in store.run(store.events.retained("brief"))] == ["created"]


def test_a_replay_from_an_id_past_the_newest_event_is_not_held(store: Any) -> None:
    """Such an id is none the store gave: following from it would skip every event to come."""
    store.create(make_session("ahead"))
    store.detect("ahead", [0.7, 0.2], flat_idx=np.array([1, 2]))
    tail = store.run(store.events.tail("ahead"))
    if "." in tail:  # the memory store's "<epoch>.<n>"
        epoch, seq = tail.rsplit(".", 1)
        ahead = f"{epoch}.{int(seq) + 1000}"
    else:  # a Redis stream entry "<ms>-<n>"
        ms, seq = tail.split("-")
        ahead = f"{int(ms) + 10**6}-{seq}"
    assert store.run(store.events.replay("ahead", tail)) == []
    assert store.run(store.events.replay("ahead", ahead)) is None


def test_head_is_the_info_of_load_without_reading_the_layers(store: Any) -> None:
    session = make_session("meta-only")
    store.create(session)
    store.detect("meta-only", [0.7, 0.2], flat_idx=np.array([1, 2]))
    info = store.head("meta-only")
    assert info == store.get("meta-only").info()
    assert (info.version, info.grid, info.sensor_model, info.label_map) == (
        1,
        session.grid,
        session.sensor_model,
        LABELS,
    )
    assert store.list() == [info]
    if isinstance(store.store, MemorySessionStore):
        stored = store._entries["meta-only"].session
        spy = stored.belief = AttributeSpy(stored.belief)
        assert store.head("meta-only") == info
        assert not spy.read & {"lang", "vis", "copy"}
        store.get("meta-only")
        assert "copy" in spy.read  # the spy does see a read of the layers
    else:
        info_commands = redis_commands(store, lambda: store.head("meta-only"), "meta-only")
        touched = [c for c in info_commands if "{meta-only}" in c]
        assert touched and all(":meta" in c and ":lang" not in c and ":vis" not in c for c in touched)
        # What grounding an utterance reads: one command, on the meta hash, with the scene graph's field.
        both = redis_commands(store, lambda: store.head_and_scene_graph("meta-only"), "meta-only")
        touched = [c for c in both if "{meta-only}" in c]
        assert len(touched) == 1 and "hmget" in touched[0].lower() and ":meta" in touched[0]
        assert store.head_and_scene_graph("meta-only") == (info, SCENE)
        fresh = StoreOps(type(store.store)(store._url, prefix=store.prefix))  # no mirror: `load` reads it all
        assert any(":lang" in c for c in redis_commands(fresh, lambda: fresh.get("meta-only"), "meta-only"))
        fresh.close()
    with pytest.raises(NotFound):
        store.head("absent")


def test_a_session_without_a_target_class_takes_detections_and_refuses_labels_until_named(store: Any) -> None:
    session = new_session("robot-1", SCENE, "", label_map=LABELS, session_id="unnamed")
    store.create(session)
    assert store.head("unnamed").target_label == ""
    with pytest.raises(Conflict, match="target class is unknown"):
        store.observe("unnamed", [1, 0], flat_idx=np.array([3, 4]))
    assert store.detect("unnamed", [0.8], flat_idx=np.array([3])).version == 1
    for bad in ("", " _ ", "sofa"):  # no class at all; a class the label map does not name
        with pytest.raises(InvalidInput) as error:
            store.set_target("unnamed", bad)
        assert error.value.field == "target_label"
    assert store.head("unnamed").version == 1  # rejected changes change nothing
    assert store.set_target("unnamed", "Backpacks") == 2
    assert store.head("unnamed").target_label == "Backpacks"
    assert store.observe("unnamed", [1, 0], flat_idx=np.array([3, 4])).version == 3
    with pytest.raises(NotFound):
        store.set_target("absent", "backpack")
    reference = session.copy()
    reference.belief.apply_increments(reference.detection_batch([0.8], flat_idx=np.array([3])))
    reference.set_target_label("Backpacks")
    reference.belief.version += 1
    reference.belief.apply_increments(reference.observation_batch([1, 0], flat_idx=np.array([3, 4])))
    got = store.get("unnamed")
    assert got.target_label == "Backpacks"
    assert_same_belief(got, reference)


def test_naming_the_target_during_concurrent_updates_loses_none_of_them(store: Any) -> None:
    session = new_session("robot-1", SCENE, "", session_id="busy", limits=UNCLAMPED)
    store.create(session)
    rng = np.random.default_rng(30)
    batches = [(rng.uniform(0.3, 0.7, 50), rng.integers(0, session.grid.n_voxels, 50)) for _ in range(16)]
    errors: list[BaseException] = []

    def worker(part: list[tuple[np.ndarray, np.ndarray]]) -> None:
        try:
            for p_target, idx in part:
                store.detect("busy", p_target, flat_idx=idx)
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(batches[t::2],)) for t in range(2)]
    for t in threads:
        t.start()
    store.set_target("busy", "backpack")
    for t in threads:
        t.join()
    assert not errors
    reference = session.copy()
    for p_target, idx in batches:
        reference.belief.apply_increments(reference.detection_batch(p_target, flat_idx=idx))
    got = store.get("busy")
    assert (got.version, got.target_label) == (len(batches) + 1, "backpack")
    np.testing.assert_allclose(got.belief.vis, reference.belief.vis, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("from_snapshot", [False, True])
def test_a_target_label_set_later_survives_reopening(tmp_path: Path, from_snapshot: bool) -> None:
    data_dir = tmp_path / "data"
    # Compacting every 2 records leaves the label only in the snapshot; else only in the log.
    store = memory_store(data_dir, snapshot_every=2 if from_snapshot else 10_000)
    store.create(new_session("robot-1", SCENE, "", label_map=LABELS, session_id="later"))
    store.detect("later", [0.8], flat_idx=np.array([3]))
    assert store.set_target("later", "backpack") == 2
    store.observe("later", [1, 0], flat_idx=np.array([3, 4]))
    wal_bytes = sum(p.stat().st_size for p in data_dir.glob("wal-*.log"))
    assert (wal_bytes == 0) == from_snapshot
    before = durable_state(store)
    del store
    store = reopen(data_dir)
    assert_same_sessions(durable_state(store), before)
    assert store.head("later").target_label == "backpack"
    assert store.observe("later", [1], flat_idx=np.array([5])).version == 4
    store.close()


@pytest.mark.redis
def test_a_target_label_set_on_one_replica_is_seen_by_another(redis_url: str) -> None:
    first = redis_store(redis_url)
    second = redis_store(redis_url, prefix=first.prefix)  # another process's view of the same server
    first.create(new_session("robot-1", SCENE, "", label_map=LABELS, session_id="shared"))
    with pytest.raises(Conflict):
        second.observe("shared", [1], flat_idx=np.array([0]))
    assert first.set_target("shared", "backpack") == 1
    seen = second.head("shared")
    assert (seen.target_label, seen.version) == ("backpack", 1)
    assert second.observe("shared", [1], flat_idx=np.array([0])).version == 2
    assert first.head("shared").version == 2
    first.close()
    second.close()


# -- mapped look-alikes: labels on a mapped object of the target's class carry no evidence -----------------

LOOK_ALIKE_SCENE = SceneGraph.model_validate(
    {
        "objects": [
            {"id": "c1", "label": "chair", "center": [1.0, 1.0, 0.45], "size": [0.5, 0.5, 0.9]},
            {"id": "c2", "label": "Chairs", "center": [3.0, 1.2, 0.45], "size": [0.6, 0.4, 0.9], "yaw": 0.5},
            {"id": "t", "label": "table", "center": [2.0, 2.5, 0.4], "size": [1.2, 0.8, 0.8]},
        ],
    }
)


def brute_force_look_alikes(session: Session) -> np.ndarray:
    """Voxels whose centre lies in a box (yaw respected) of a mapped object of the target's class."""
    centres = session.grid.centers()
    inside = np.zeros(session.grid.n_voxels, dtype=bool)
    for obj in session.scene_graph.objects:
        if obj.label.lower().rstrip("s") != session.target_label:
            continue
        d = centres - np.asarray(obj.center)
        c, s = np.cos(obj.yaw), np.sin(obj.yaw)
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
        inside |= np.all(np.abs(local) <= 0.5 * np.asarray(obj.size), axis=1)
    return np.flatnonzero(inside)


def test_mapped_look_alikes_are_the_voxels_inside_same_class_boxes() -> None:
    from app.belief.session import mapped_look_alikes

    session = new_session("r", LOOK_ALIKE_SCENE, "chair", label_map=LABELS | {3: "chair"})
    expected = brute_force_look_alikes(session)
    assert len(expected) > 100
    np.testing.assert_array_equal(mapped_look_alikes(session.grid, LOOK_ALIKE_SCENE, "chair"), expected)
    assert len(mapped_look_alikes(session.grid, LOOK_ALIKE_SCENE, "backpack")) == 0
    assert len(mapped_look_alikes(session.grid, LOOK_ALIKE_SCENE, "")) == 0


def test_labels_on_mapped_look_alikes_leave_the_belief_alone(store: Any) -> None:
    labels = LABELS | {3: "chair"}
    session = new_session("r", LOOK_ALIKE_SCENE, "backpack", label_map=labels, session_id=uuid.uuid4().hex)
    store.create(session)
    chair_voxels = brute_force_look_alikes(dataclasses.replace(session, target_label="chair"))
    free = np.setdiff1d(np.arange(session.grid.n_voxels), chair_voxels)[:50]
    voxels = np.concatenate([chair_voxels, free])
    # While the target is a backpack, the chairs are ordinary voxels: "chair" there is evidence against.
    store.observe(session.id, np.full(len(voxels), 3), flat_idx=voxels)
    vis = store.layers(session.id).vis
    assert np.all(vis[voxels] < 0)
    # Once the target is a chair, the mapped chairs explain "chair" labels: no change on their voxels, while
    # unmapped voxels labelled "chair" gain log(tp/fp) and voxels labelled otherwise lose.
    store.set_target(session.id, "chair")
    before = store.layers(session.id).vis.copy()
    store.observe(session.id, np.full(len(voxels), 3), flat_idx=voxels)
    store.observe(session.id, np.zeros(len(chair_voxels), dtype=int), flat_idx=chair_voxels)
    after = store.layers(session.id).vis
    np.testing.assert_array_equal(after[chair_voxels], before[chair_voxels])
    tp, fp = session.sensor_model.tp, session.sensor_model.fp
    np.testing.assert_allclose(after[free] - before[free], np.log(tp / fp), rtol=1e-5)
    # A new scene graph without the chairs makes their voxels ordinary again.
    store.replace_scene_graph(
        session.id, SceneGraph.model_validate({"objects": [LOOK_ALIKE_SCENE.objects[2]]})
    )
    before = store.layers(session.id).vis.copy()
    store.observe(session.id, np.full(len(chair_voxels), 3), flat_idx=chair_voxels)
    assert np.all(store.layers(session.id).vis[chair_voxels] > before[chair_voxels])
