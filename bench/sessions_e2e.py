"""Sessions end to end over loopback: 100k-voxel msgpack batches, summary polls of a 1M-voxel belief,
memory per session and how many 1M-voxel sessions a 24 GB machine holds.

One `vlmap serve` process with the embedded durable store (every batch fsync'd before its answer).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from app.client import VLMapClient
from app.sim.service import start_service, wait_ready

SCENE = (
    Path(__file__).resolve().parent.parent / "tests" / "resources" / "scenes" / "scannet_scene0590_00.json"
)
MACHINE_BYTES = 24 * 2**30


def pctl(samples: list[float]) -> str:
    p50, p99 = np.percentile(samples, [50, 99])
    return f"p50 {p50:.2f} ms, p99 {p99:.2f} ms, mean {np.mean(samples):.2f} ms (n={len(samples)})"


def rss_of(pid: int) -> int:
    """Resident set size of a process, bytes (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    msg = f"no VmRSS for process {pid}"
    raise RuntimeError(msg)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batches", type=int, default=200)
    parser.add_argument("--polls", type=int, default=300)
    parser.add_argument("--sessions", type=int, default=6, help="1M-voxel sessions created to measure memory")
    args = parser.parse_args()
    scene = json.loads(SCENE.read_text())
    one_million = {"voxel_size": 0.1, "min_corner": [-5.0, -5.0, 0.0], "max_corner": [5.0, 5.0, 10.0]}
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as data_dir:
        proc, url = start_service({"VLMAP_DATA_DIR": data_dir})
        wait_ready(url, proc)
        try:
            client = VLMapClient(url, timeout_s=60.0)
            base_rss = rss_of(proc.pid)
            session = client.create_session(
                "bench",
                scene,
                target_label="backpack",
                grid=one_million,
                label_map={"0": "floor", "1": "backpack"},
            )
            sid, n = session["id"], session["grid"]["n_voxels"]
            client.send_utterance(sid, "I left my backpack on the desk")
            shape = tuple(session["grid"]["shape"])
            batch_ms: dict[bool, list[float]] = {True: [], False: []}  # by "summary in the answer"
            for i in range(args.batches):
                flat = rng.choice(n, size=100_000, replace=False)
                ijk = np.stack(np.unravel_index(flat, shape), axis=1).astype(np.int32)
                labels = (rng.random(100_000) < 0.01).astype(np.uint32)  # label-map ids, as a segmenter emits
                with_summary = i % 2 == 0
                start = time.perf_counter()
                client.send_observations(sid, summary=with_summary, voxels=ijk, labels=labels, stamp=float(i))
                batch_ms[with_summary].append((time.perf_counter() - start) * 1000)
            fresh_ms, later_ms, poll_ms, cached_ms = [], [], [], []
            etag = None
            one_voxel = np.zeros((1, 3), dtype=np.int32)

            def new_version() -> None:  # a one-voxel batch: the whole 1M-voxel posterior changes
                client.send_observations(sid, summary=False, voxels=one_voxel, labels=np.zeros(1, np.uint32))

            for _ in range(args.polls):
                # Polled right after the update: the background summary (this session is watched) races
                # with the poll, which summarises the 1M voxels itself if it gets there first.
                new_version()
                start = time.perf_counter()
                client.get_belief(sid)
                fresh_ms.append((time.perf_counter() - start) * 1000)
                # Polled 50 ms after the update, as a dashboard not in step with the robot mostly is.
                new_version()
                time.sleep(0.05)
                start = time.perf_counter()
                client.get_belief(sid)
                later_ms.append((time.perf_counter() - start) * 1000)
                start = time.perf_counter()
                _, etag = client.get_belief(sid)
                poll_ms.append((time.perf_counter() - start) * 1000)
                start = time.perf_counter()
                client.get_belief(sid, etag)
                cached_ms.append((time.perf_counter() - start) * 1000)
            for _ in range(args.sessions - 1):
                client.create_session("bench", scene, target_label="backpack", grid=one_million)
            per_session = (rss_of(proc.pid) - base_rss) / args.sessions
            client.close()
        finally:
            proc.terminate()
            proc.wait()
    print(
        f"session grid: {n} voxels (0.1 m), embedded store with fsync per batch, loopback, sequential client"
    )
    for with_summary, label in (
        (False, "summary=false, as at sensor rate"),
        (True, "the answer carries the summary"),
    ):
        samples = batch_ms[with_summary]
        print(
            f"POST /observations, 100k-voxel msgpack batch, int32 voxels, uint32 label ids ({label}): "
            f"{pctl(samples)}"
        )
        print(f"  = {100_000 / (np.mean(samples) / 1000) / 1e6:.1f} M voxel updates/s end to end")
    print(f"GET /belief summary of the 1M-voxel session right after an update: {pctl(fresh_ms)}")
    print(f"GET /belief summary of the 1M-voxel session 50 ms after an update: {pctl(later_ms)}")
    print(f"GET /belief summary again, same version (cached per version): {pctl(poll_ms)}")
    print(f"GET /belief with a matching ETag (304): {pctl(cached_ms)}")
    print(f"memory per 1M-voxel session (service RSS growth / sessions): {per_session / 2**20:.1f} MiB")
    print(
        f"1M-voxel sessions a 24 GiB machine holds (less the {base_rss / 2**20:.0f} MiB base process): "
        f"{int((MACHINE_BYTES - base_rss) / per_session)}"
    )


if __name__ == "__main__":
    main()
