"""The quick version of `make bench-fleet`: a small fleet on two replicas sharing Redis, with every fault."""

from __future__ import annotations

import shutil

import pytest

from bench import fleet


@pytest.mark.redis
@pytest.mark.skipif(
    shutil.which("redis-server") is None, reason="needs redis-server (apt-get install redis-server)"
)
def test_small_fleet_survives_redis_restart_kill_9_and_disconnects() -> None:
    results = fleet.main(
        [
            *("--robots", "3", "--dashboards", "1", "--voxels", "2000"),
            *("--duration", "3", "--fault-duration", "6", "--host-probe-s", "0.5"),
        ]
    )
    assert set(results["host_stolen"]) == {"waking", "spinning"}
    assert all(0.0 <= share <= 1.0 for share in results["host_stolen"].values())
    # Steady load: no error at all.
    for route, row in results["load"].items():
        assert row["errors"] == {}, (route, row)
        assert row["ok"] > 0
    # Redis down: only clean 503s, and requests succeed again after it comes back.
    for route, row in results["fault_redis"].items():
        assert set(row["errors"]) <= {"503"}, (route, row)
    assert results["fault_redis"]["POST /observations"]["ok"] > 0
    # A killed replica: its clients see refused connections until its process serves again, then clean
    # 503s while its models load (it is live but not ready: a load balancer routes by /readyz); nothing
    # else fails.
    for route, row in results["fault_kill"].items():
        broken = {"ConnectionRefusedError", "ConnectionResetError", "IncompleteReadError", "BrokenPipeError"}
        assert set(row["errors"]) <= broken | {"503"}, (route, row)
    # A client hanging up mid-upload harms nobody.
    for route, row in results["fault_disconnect"].items():
        assert row["errors"] == {}, (route, row)
    assert results["consistency"]["voxels_inconsistent"] == 0
    assert results["consistency"]["acknowledged_batches"] > 0
