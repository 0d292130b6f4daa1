"""The Redis store on a real Redis Cluster (3 masters with a replica each, started by `.ci/run`): every key
of a session in one slot, sessions spread over the masters, and a failover of the master holding a session
while a robot streams to it loses no acknowledged batch and applies none twice. The behaviour every store
shares runs on the cluster too (the `store` fixture of tests/test_stores.py)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from app.client import VLMapClient
from app.sim.service import MODEL_FREE_ENV, start_service, wait_ready
from tests.conftest import load_resource_json
from tests.test_sessions_processes import create, make_batches, retried_stream, sequential_sum
from tests.test_stores import make_session, redis_store

pytestmark = pytest.mark.redis

PARTS = ("meta", "lang", "vis", "lock", "summary", "idem", "idem_at", "commits")


def test_every_key_of_a_session_is_in_one_slot(redis_cluster_url: str) -> None:
    store = redis_store(redis_cluster_url)
    assert store.clustered
    store.create(make_session("slotted"))
    store.detect("slotted", [0.7], flat_idx=np.array([3]))
    slots = {store._client.keyslot(store._key("slotted", part)) for part in PARTS}
    assert len(slots) == 1
    stored = [part for part in PARTS if store._client.exists(store._key("slotted", part))]
    assert set(stored) >= {"meta", "vis", "idem", "commits"}
    store.close()


def test_sessions_spread_over_the_masters_and_list_from_all(redis_cluster_url: str) -> None:
    store = redis_store(redis_cluster_url)
    ids = [f"spread-{i}" for i in range(24)]
    for sid in ids:
        store.create(make_session(sid, robot_id="fleet"))
    masters = {store._client.get_node_from_key(store._key(sid, "meta")).name for sid in ids}
    assert len(masters) == 3
    assert sorted(i.id for i in store.list("fleet")) == sorted(ids)
    for sid in ids[:12]:
        store.delete(sid)
    assert sorted(i.id for i in store.list("fleet")) == sorted(ids[12:])
    store.close()


def _replica_of(client: Any, key: str) -> Any:
    """A redis-py client of the replica of the master holding `key`'s slot."""
    slot = client.keyslot(key)
    for low, high, _master, replica, *_ in client.get_default_node().redis_connection.execute_command(
        "CLUSTER SLOTS"
    ):
        if low <= slot <= high:
            return client.get_redis_connection(client.get_node(replica[0].decode(), replica[1]))
    msg = f"no replica serves slot {slot}"
    raise AssertionError(msg)


def test_a_failover_of_the_master_holding_a_session_mid_stream_applies_every_batch_once(
    redis_cluster_url: str,
) -> None:
    scene = load_resource_json("scenes/two_rooms.json")
    proc, url = start_service({**MODEL_FREE_ENV, "VLMAP_STORE": redis_cluster_url})
    probe = redis_store(redis_cluster_url)
    try:
        wait_ready(url, proc)
        session_id, shape = create(url, scene)
        batches = make_batches(shape, seed=5)[:300]
        sender, acknowledged = retried_stream(url, session_id, batches, timeout_s=10.0, wait_for=100)
        replica = _replica_of(probe._client, probe._key(session_id, "meta"))
        replica.execute_command("CLUSTER FAILOVER")  # the replica takes over, the master becomes its replica
        deadline = time.monotonic() + 30
        while replica.execute_command("ROLE")[0] != b"master":
            assert time.monotonic() < deadline, "the failover did not complete"
            time.sleep(0.05)
        switched_at = len(acknowledged)
        sender.join(timeout=120)
        assert not sender.is_alive() and acknowledged == list(range(len(batches)))
        assert switched_at < len(batches), "the stream ended before the new master served it"
        with VLMapClient(url) as client:
            grid = client.get_belief_grid(session_id, layers=True)
    finally:
        probe.close()
        proc.kill()
        proc.wait()
    assert grid.version == len(batches)
    np.testing.assert_array_equal(grid.vis, sequential_sum(shape, batches))
