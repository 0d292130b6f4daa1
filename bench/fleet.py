"""`make bench-fleet`: a loopback fleet (robots stream batches and utterances, dashboards poll) + faults.

Phase 1 (load): N robots, each with its own session, send 10k-voxel msgpack observation batches at a fixed
rate and an utterance every few seconds; M dashboards poll the beliefs with ETags. Robots and dashboards
spread over the replicas the way a load balancer would. Reported: throughput, p50/p99 per route, errors.

Phase 2 (faults), while the fleet keeps streaming:
  - redis: the Redis server is restarted (AOF, fsync always); requests must fail cleanly (503) and succeed
    again without restarting the service;
  - kill: a service process is killed with SIGKILL and started again on its port (the embedded store's
    log, or Redis, must hold every acknowledged update);
  - disconnect: a client sends half of a declared body and hangs up.
Then no acknowledged update may be missing: every batch labels its voxels as the target with a sensor model
(tp=0.51, fp=0.5) whose increment d = log(0.51/0.5) is far from the clamps, so a voxel's vision log-weight
must lie between d * (acknowledged hits) and d * (all hits sent).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import multiprocessing
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections import defaultdict
from contextlib import ExitStack
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.client import VLMapClient
from app.sessions.batch import encode_msgpack_batch
from app.sim.service import process_cpu_seconds, start_service, wait_ready
from tests.harness import RedisServer

TP, FP = 0.51, 0.5
#: Robots send label ids, as a segmenter does. The target class is absent from the scene graph (as the service
#: assumes: no mapped look-alikes whose labels it would ignore); every voxel is labelled as the target.
LABEL_MAP = {"0": "floor", "1": "wallet"}
TARGET_ID = 1
INCREMENT = math.log(TP / FP)
SCENE = (
    Path(__file__).resolve().parent.parent / "tests" / "resources" / "scenes" / "scannet_scene0590_00.json"
)


@dataclass
class Stats:
    latencies_ms: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    status: dict[str, dict[str, int]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(int)))

    def record(self, route: str, started: float, outcome: str) -> None:
        if outcome == "200":
            self.latencies_ms[route].append((time.perf_counter() - started) * 1000.0)
        self.status[route][outcome] += 1


class RequestFailed(Exception):
    """A non-2xx answer (304 counts as success); `status` is the HTTP status."""

    def __init__(self, status: int) -> None:
        super().__init__(f"HTTP {status}")
        self.status = status


class LeanHTTPClient:
    """HTTP/1.1 over one keep-alive asyncio connection, no more than the fleet needs.

    The load generator shares the machine's two cores with the service it measures; through httpx and the
    Python client it spent about 0.4 of a core on this load, CPU the service then lacked. This client
    writes each request's bytes itself and reads the status, headers and body. What robots send is the
    same as through `AsyncVLMapClient` (`encode_msgpack_batch`); the client itself is tested elsewhere.
    """

    def __init__(self, url: str, timeout_s: float) -> None:
        host, port = url.removeprefix("http://").split(":")
        self.host, self.port, self.timeout_s = host, int(port), timeout_s
        self._streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def request(
        self, method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None
    ) -> tuple[int, dict[str, str], bytes]:
        try:
            return await asyncio.wait_for(self._exchange(method, path, body, headers or {}), self.timeout_s)
        except (TimeoutError, OSError, asyncio.IncompleteReadError, ValueError) as exc:
            await self.close()  # a broken or timed-out exchange leaves the connection unusable
            msg = f"{type(exc).__name__}: {exc}"
            raise httpx.TransportError(msg) from exc

    async def _exchange(
        self, method: str, path: str, body: bytes, headers: dict[str, str]
    ) -> tuple[int, dict[str, str], bytes]:
        if self._streams is None:
            self._streams = await asyncio.open_connection(self.host, self.port)
        reader, writer = self._streams
        lines = [f"{method} {path} HTTP/1.1", f"Host: {self.host}", f"Content-Length: {len(body)}"]
        lines += [f"{name}: {value}" for name, value in headers.items()]
        writer.write(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body)
        await writer.drain()
        status_line = await reader.readline()
        if not status_line:
            msg = "the service closed the connection"
            raise ConnectionResetError(msg)
        status = int(status_line.split()[1])
        answer: dict[str, str] = {}
        while (line := await reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            answer[name.strip().lower()] = value.strip()
        payload = await reader.readexactly(int(answer.get("content-length", "0")))
        if answer.get("connection", "").lower() == "close":
            await self.close()
        return status, answer, payload

    async def close(self) -> None:
        if self._streams is not None:
            writer = self._streams[1]
            self._streams = None
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


async def checked(response: Any) -> tuple[int, dict[str, str], bytes]:
    status, headers, body = await response
    if status >= 400:
        raise RequestFailed(status)
    return status, headers, body


@dataclass
class RobotLog:
    """What one robot sent and what the service acknowledged."""

    session_id: str
    replica: int
    sent: list[np.ndarray] = field(default_factory=list)  # flat voxel indices per batch
    acked: list[bool] = field(default_factory=list)


class Fleet:
    def __init__(self, urls: list[str], scene: dict[str, Any], args: argparse.Namespace) -> None:
        self.urls = urls
        self.scene = scene
        self.args = args
        self.stats = Stats()
        self.robots: list[RobotLog] = []
        self.stop = asyncio.Event()

    def create_sessions(self) -> None:
        for i in range(self.args.robots):
            replica = i % len(self.urls)
            with VLMapClient(self.urls[replica]) as client:
                session = client.create_session(
                    f"robot-{i}",
                    self.scene,
                    target_label="wallet",
                    sensor_model={"tp": TP, "fp": FP},
                    label_map=LABEL_MAP,
                )
            self.robots.append(RobotLog(session["id"], replica))
        self.n_voxels = session["grid"]["n_voxels"]
        self.shape = tuple(session["grid"]["shape"])

    def batch_voxels(self, rng: np.random.Generator) -> np.ndarray:
        """Flat indices of one batch: a box of about `voxels` voxels at a random place, as a camera's view
        covers a connected region (`--batch-shape box`), or voxels drawn anywhere in the grid (`random`)."""
        if self.args.batch_shape == "random":
            return np.unique(rng.integers(0, self.n_voxels, size=self.args.voxels))
        nx, ny, nz = self.shape
        depth = min(nz, 20)
        side = max(1, round(math.sqrt(self.args.voxels / depth)))
        sx, sy = min(nx, side), min(ny, -(-self.args.voxels // (depth * min(nx, side))))
        x0, y0, z0 = (int(rng.integers(0, n - s + 1)) for n, s in ((nx, sx), (ny, sy), (nz, depth)))
        i, j, k = np.meshgrid(
            np.arange(x0, x0 + sx), np.arange(y0, y0 + sy), np.arange(z0, z0 + depth), indexing="ij"
        )
        return np.ravel_multi_index((i.ravel(), j.ravel(), k.ravel()), self.shape)

    async def _call(self, route: str, coro: Any) -> Any:
        started = time.perf_counter()
        try:
            result = await coro
        except httpx.TransportError as exc:
            self.stats.record(route, started, str(exc).split(":", 1)[0])
            return None
        except RequestFailed as exc:
            self.stats.record(route, started, str(exc.status))
            return None
        self.stats.record(route, started, "200")
        return result

    async def robot(self, index: int) -> None:
        log = self.robots[index]
        period = 1.0 / self.args.rate
        rng = np.random.default_rng(self.args.seed + index)
        utterance_every = self.args.rate * 5  # batches between utterances: one every 5 s
        # Robots are not phase-locked: each starts at a random point of its batch period and of its utterance
        # cycle (all 20 in step would make every request arrive in bursts of 20 and measure the burst).
        step = int(rng.integers(0, utterance_every))
        client = LeanHTTPClient(self.urls[log.replica], timeout_s=10.0)
        base = f"/v1/sessions/{log.session_id}"
        utterance = json.dumps({"utterance": "my wallet is on the desk"}).encode()
        as_json = {"Content-Type": "application/json"}
        as_msgpack = {"Content-Type": "application/msgpack"}
        await asyncio.sleep(float(rng.uniform(0.0, period)))
        while not self.stop.is_set():
            tick = time.perf_counter()
            if step % utterance_every == 0:
                await self._call(
                    "POST /utterances",
                    checked(client.request("POST", f"{base}/utterances", utterance, as_json)),
                )
            flat = self.batch_voxels(rng)
            ijk = np.stack(np.unravel_index(flat, self.shape), axis=1).astype(np.int32)
            log.sent.append(flat)
            body = encode_msgpack_batch(voxels=ijk, labels=np.full(len(flat), TARGET_ID, dtype=np.uint32))
            result = await self._call(
                "POST /observations",
                checked(client.request("POST", f"{base}/observations?summary=false", body, as_msgpack)),
            )
            log.acked.append(result is not None)
            step += 1
            await asyncio.sleep(max(0.0, period - (time.perf_counter() - tick)))
        await client.close()

    async def dashboard(self, index: int) -> None:
        etags: dict[str, str] = {}
        client = LeanHTTPClient(self.urls[index % len(self.urls)], timeout_s=10.0)
        # Each dashboard starts its round at a different robot, as independent screens would.
        start = index * len(self.robots) // max(1, self.args.dashboards)
        order = self.robots[start:] + self.robots[:start]
        while not self.stop.is_set():
            for log in order:
                if self.stop.is_set():
                    break
                tag = etags.get(log.session_id)
                headers = {"If-None-Match": tag} if tag else {}
                path = f"/v1/sessions/{log.session_id}/belief"
                result = await self._call("GET /belief", checked(client.request("GET", path, b"", headers)))
                if result is not None:
                    status, answer, body = result
                    if status == 200:
                        json.loads(body)  # a dashboard reads the summary
                    etags[log.session_id] = answer.get("etag", tag or "")
                await asyncio.sleep(1.0 / (self.args.poll_rate * len(self.robots)))
        await client.close()

    async def run(self, duration_s: float, fault: Any = None) -> float:
        """Drive the fleet for `duration_s` (plus the time `fault()` takes); returns the seconds it ran."""
        started = time.perf_counter()
        self.stop.clear()
        tasks = [asyncio.create_task(self.robot(i)) for i in range(len(self.robots))]
        tasks += [asyncio.create_task(self.dashboard(i)) for i in range(self.args.dashboards)]
        if fault is not None:
            await asyncio.sleep(duration_s / 3)
            await fault()
            await asyncio.sleep(duration_s * 2 / 3)
        else:
            await asyncio.sleep(duration_s)
        self.stop.set()
        await asyncio.gather(*tasks)
        return time.perf_counter() - started

    def verify_no_acknowledged_update_lost(self) -> dict[str, int]:
        """Every acknowledged batch is in the belief; nothing appears that was never sent."""
        checked = lost = 0
        for log in self.robots:
            with VLMapClient(self.urls[log.replica]) as client:
                layers = client.get_belief_grid(log.session_id, layers=True)
            assert layers.vis is not None, "the service sent no vision layer"
            vis = layers.vis.astype(np.float64)
            acked = np.zeros(self.n_voxels)
            sent = np.zeros(self.n_voxels)
            for flat, ok in zip(log.sent, log.acked, strict=True):
                sent[flat] += 1
                if ok:
                    acked[flat] += 1
            tolerance = 1e-4 * (1 + sent)
            lost += int(np.sum(vis < INCREMENT * acked - tolerance))
            lost += int(np.sum(vis > INCREMENT * sent + tolerance))
            checked += int(sum(log.acked))
        return {"acknowledged_batches": checked, "voxels_inconsistent": lost}


def client_disconnects_mid_upload(url: str) -> None:
    """Declare a 1 MB body, send 1 kB of it, hang up."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as sock:
        head = (
            f"POST /v1/sessions/x/observations HTTP/1.1\r\nHost: {host}\r\n"
            "Content-Type: application/msgpack\r\n"
            "Content-Length: 1000000\r\n\r\n"
        )
        sock.sendall(head.encode() + b"\x00" * 1024)


def worker_pids(parent: int) -> list[int]:
    """A replica's worker processes: its children that hold models (Linux; not the small resource tracker)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat[1]) == parent and b"spawn_main" in cmdline:
            found.append(int(entry.name))
    return sorted(found)


def machine_times() -> np.ndarray:
    """The machine's CPU time so far by state (user, nice, system, idle, iowait, irq, softirq, steal), from
    /proc/stat (Linux)."""
    return np.array([int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]])


def _spin(seconds: float) -> None:
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline:
        pass


def _ping(conn: Connection, seconds: float) -> None:
    """Ask, wait for the answer, pause 1 ms; until `seconds` have passed (then close the pair)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        conn.send_bytes(b"?")
        conn.recv_bytes()
        time.sleep(0.001)
    conn.send_bytes(b"")


def _pong(conn: Connection) -> None:
    """Answer each question after 1 ms of work."""
    while conn.recv_bytes():
        _spin(0.001)
        conn.send_bytes(b"!")


def host_steal(seconds: float = 3.0) -> dict[str, float]:
    """Shares of the machine's CPU time the hypervisor stole while, with nothing of the service running,
    (a) two pairs of processes woke each other about 500 times a second each, as requests and replies do,
    and (b) two processes spun. On a shared host (a) is often far above (b): a vCPU that wakes from idle
    waits for the host to run it, and a request's latency is a chain of such wake-ups."""
    fork = multiprocessing.get_context("fork")  # before any thread or service starts
    out = {}
    for name in ("waking", "spinning"):
        machine = machine_times()
        if name == "waking":
            children = []
            for _ in range(2):
                ours, theirs = fork.Pipe()
                children += [
                    fork.Process(target=_ping, args=(ours, seconds)),
                    fork.Process(target=_pong, args=(theirs,)),
                ]
        else:
            children = [fork.Process(target=_spin, args=(seconds,)) for _ in range(2)]
        for child in children:
            child.start()
        for child in children:
            child.join()
        spent = machine_times() - machine
        out[name] = round(float(spent[7] / max(1, spent.sum())), 2)
    return out


def cpu_per_request(
    cores: dict[str, float], load: dict[str, Any], seconds: float
) -> dict[str, dict[str, float]]:
    """Each process's CPU-seconds over the load phase per 1,000 acknowledged observation batches and per 1,000
    belief polls: work done, which a noisy host's tails do not show. The traffic is mixed, so each figure
    carries all of the process's work (batches, polls and utterances) of the phase."""
    batches = max(1, int(load.get("POST /observations", {}).get("ok", 0)))
    polls = max(1, int(load.get("GET /belief", {}).get("ok", 0)))
    return {
        name: {
            "batches": round(1000 * c * seconds / batches, 3),
            "polls": round(1000 * c * seconds / polls, 3),
        }
        for name, c in cores.items()
    }


def cpu_shares(pids: dict[str, int | None], run: Any, seconds: float) -> dict[str, float]:
    """Run `run()` and return how many cores each process kept busy on average meanwhile, and the shares of
    the machine's CPU time that were idle and stolen by the hypervisor (a virtual machine's neighbours)."""
    before = {name: process_cpu_seconds(pid) for name, pid in pids.items()}
    machine = machine_times()
    run()
    spent = machine_times() - machine
    shares = {
        name: round((process_cpu_seconds(pid) - before[name]) / seconds, 2) for name, pid in pids.items()
    }
    total = max(1, int(spent.sum()))
    return shares | {"machine idle": round(spent[3] / total, 2), "machine stolen": round(spent[7] / total, 2)}


_SERVER_ROUTES = {
    "POST /observations": ('method="POST"', "/observations"),
    "GET /belief": ('method="GET"', "/belief"),
    "POST /utterances": ('method="POST"', "/utterances"),
}


def server_seconds(urls: list[str]) -> dict[str, tuple[float, float]]:
    """(sum of seconds, count) per route from the replicas' request-duration histograms (/metrics)."""
    totals = {route: [0.0, 0.0] for route in _SERVER_ROUTES}
    for url in urls:
        for line in httpx.get(f"{url}/metrics", timeout=10).text.splitlines():
            if not line.startswith("vlmap_http_request_duration_seconds_"):
                continue
            for route, (method, path) in _SERVER_ROUTES.items():
                if method in line and f'{path}"' in line:
                    if line.startswith("vlmap_http_request_duration_seconds_sum"):
                        totals[route][0] += float(line.rsplit(" ", 1)[1])
                    elif line.startswith("vlmap_http_request_duration_seconds_count"):
                        totals[route][1] += float(line.rsplit(" ", 1)[1])
    return {route: (total, count) for route, (total, count) in totals.items()}


def summarise(stats: Stats) -> dict[str, Any]:
    out = {}
    for route, samples in sorted(stats.latencies_ms.items()):
        arr = np.asarray(samples)
        out[route] = {
            "ok": len(arr),
            "p50_ms": round(float(np.percentile(arr, 50)), 2),
            "p99_ms": round(float(np.percentile(arr, 99)), 2),
            "errors": {k: v for k, v in stats.status[route].items() if k != "200"},
        }
    return out


def print_table(title: str, summary: dict[str, Any], seconds: float) -> None:
    print(f"\n{title}")
    print("| route | ok | req/s | p50 (ms) | p99 (ms) | errors |")
    print("|---|---|---|---|---|---|")
    for route, row in summary.items():
        errors = ", ".join(f"{k}: {v}" for k, v in row["errors"].items()) or "0"
        print(
            f"| {route} | {row['ok']} | {row['ok'] / seconds:.1f} | {row['p50_ms']} | {row['p99_ms']} "
            f"| {errors} |"
        )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--robots", type=int, default=20)
    parser.add_argument("--dashboards", type=int, default=5)
    parser.add_argument("--rate", type=int, default=2, help="batches per second per robot")
    parser.add_argument(
        "--poll-rate", type=float, default=2.0, help="polls per second of each robot's belief, per dashboard"
    )
    parser.add_argument("--voxels", type=int, default=10_000, help="voxels per batch")
    parser.add_argument(
        "--batch-shape",
        choices=["box", "random"],
        default="box",
        help="each batch a box of voxels, as one camera view (default), or voxels anywhere in the grid",
    )
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of steady load")
    parser.add_argument(
        "--fault-duration", type=float, default=15.0, help="seconds of load around each fault"
    )
    parser.add_argument("--replicas", type=int, default=2)
    parser.add_argument(
        "--worker-processes", type=int, default=1, help="grounding worker processes per replica"
    )
    parser.add_argument("--store", choices=["redis", "memory"], default="redis")
    parser.add_argument("--faults", default="redis,kill,disconnect", help="comma list, or empty for none")
    parser.add_argument(
        "--host-probe-s",
        type=float,
        default=3.0,
        help="seconds of each host probe run before the service starts (CPU stolen while waking, spinning)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    return parser


def _start_store(
    args: argparse.Namespace, parser: argparse.ArgumentParser, stack: ExitStack, env: dict[str, str]
) -> RedisServer | None:
    """The store the replicas share, named in `env`: a Redis server (returned) or a data directory."""
    if args.store != "redis":
        env["VLMAP_DATA_DIR"] = stack.enter_context(tempfile.TemporaryDirectory())
        return None
    binary = shutil.which("redis-server")
    if binary is None:
        parser.error("redis-server is not installed")
    redis_server = RedisServer(binary, appendonly=True)
    redis_server.start()
    stack.callback(redis_server.close)
    env["VLMAP_STORE"] = redis_server.url
    return redis_server


def _fleet_pids(
    procs: list[subprocess.Popen[bytes]], redis_server: RedisServer | None
) -> dict[str, int | None]:
    """The processes whose CPU the run measures, by name (None: this one)."""
    pids: dict[str, int | None] = {"load generator": None}
    pids |= {f"replica {i + 1}": proc.pid for i, proc in enumerate(procs)}
    pids |= {
        f"replica {i + 1} worker {j + 1}": child
        for i, proc in enumerate(procs)
        for j, child in enumerate(worker_pids(proc.pid))
    }
    if redis_server is not None and redis_server.proc is not None:
        pids["redis"] = redis_server.proc.pid
    return pids


def _start_replicas(
    n: int, env: dict[str, str], stack: ExitStack
) -> tuple[list[subprocess.Popen[bytes]], list[str]]:
    """`n` services started and ready, (processes, URLs); `stack` kills those still running at its end (a
    fault may replace a process in the list)."""
    procs, urls = [], []
    for _ in range(n):
        proc, url = start_service(env)
        procs.append(proc)
        urls.append(url)

    def stop_replicas() -> None:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()

    stack.callback(stop_replicas)
    for proc, url in zip(procs, urls, strict=True):
        wait_ready(url, proc)
    return procs, urls


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = _parser()
    args = parser.parse_args(argv)
    faults = [f for f in args.faults.split(",") if f]
    if args.store == "memory" and args.replicas != 1:
        parser.error("the embedded store serves one process: use --replicas 1 with --store memory")
    scene = json.loads(SCENE.read_text())
    results: dict[str, Any] = {"config": vars(args) | {"json": str(args.json)}}
    results["host_stolen"] = host_steal(args.host_probe_s)
    print(
        "Host before the run, nothing of ours running: CPU stolen by the hypervisor "
        f"{results['host_stolen']['waking']:.0%} while processes woke each other, "
        f"{results['host_stolen']['spinning']:.0%} while they spun"
    )
    with ExitStack() as stack:
        env: dict[str, str] = {
            "VLMAP_RATE_LIMIT_PER_S": "0",
            "VLMAP_LOG_LEVEL": "WARNING",
            "VLMAP_WORKER_PROCESSES": str(args.worker_processes),
        }
        redis_server = _start_store(args, parser, stack, env)
        procs, urls = _start_replicas(args.replicas, env, stack)
        fleet = Fleet(urls, scene, args)
        fleet.create_sessions()
        print(
            f"{args.robots} robots ({args.rate} batches/s of {args.voxels} voxels each), "
            f"{args.dashboards} dashboards, {args.replicas} replica(s), store={args.store}, "
            f"grid of {fleet.n_voxels} voxels; {args.duration:.0f} s"
        )
        pids = _fleet_pids(procs, redis_server)
        served_before = server_seconds(urls)
        results["cpu_cores_busy"] = cpu_shares(
            pids, lambda: asyncio.run(fleet.run(args.duration)), args.duration
        )
        results["load"] = summarise(fleet.stats)
        print_table(f"Load ({args.duration:.0f} s)", results["load"], args.duration)
        shares = dict(results["cpu_cores_busy"])
        idle, stolen = shares.pop("machine idle"), shares.pop("machine stolen")
        busy = ", ".join(f"{name} {cores}" for name, cores in shares.items())
        print(f"Cores kept busy on average ({os.cpu_count()} on this machine): {busy}")
        print(f"Share of the machine's CPU time idle: {idle:.0%}, stolen by the hypervisor: {stolen:.0%}")
        results["cpu_s_per_1000"] = cpu_per_request(shares, results["load"], args.duration)
        per = ", ".join(f"{n} {c['batches']} / {c['polls']}" for n, c in results["cpu_s_per_1000"].items())
        print(
            f"CPU-seconds per 1,000 batches / per 1,000 polls (each process's whole CPU over the load): {per}"
        )
        served_after = server_seconds(urls)
        results["server_mean_ms"] = {
            route: round(
                1000 * (served_after[route][0] - before[0]) / max(1.0, served_after[route][1] - before[1]), 2
            )
            for route, before in served_before.items()
        }
        inside = ", ".join(f"{route} {ms} ms" for route, ms in results["server_mean_ms"].items())
        print(f"Mean time inside the service (its own request histograms): {inside}")

        async def restart_redis() -> None:
            assert redis_server is not None
            await asyncio.to_thread(redis_server.stop)
            await asyncio.sleep(2.0)
            await asyncio.to_thread(redis_server.start)

        async def kill_service() -> None:
            victim = len(procs) - 1
            os.kill(procs[victim].pid, signal.SIGKILL)
            await asyncio.to_thread(procs[victim].wait)
            port = int(urls[victim].rsplit(":", 1)[1])
            procs[victim], _ = start_service(env, port=port)
            await asyncio.to_thread(wait_ready, urls[victim], procs[victim])

        async def disconnect() -> None:
            await asyncio.to_thread(client_disconnects_mid_upload, urls[0])

        available = {"redis": restart_redis, "kill": kill_service, "disconnect": disconnect}
        for name in faults:
            if name == "redis" and redis_server is None:
                continue
            fleet.stats = Stats()
            seconds = asyncio.run(fleet.run(args.fault_duration, available[name]))
            results[f"fault_{name}"] = summarise(fleet.stats)
            results[f"fault_{name}_seconds"] = round(seconds, 1)
            print_table(f"Fault: {name} ({seconds:.0f} s around it)", results[f"fault_{name}"], seconds)
        results["consistency"] = fleet.verify_no_acknowledged_update_lost()
        print(f"\nConsistency after all phases: {results['consistency']}")
        for url in urls:
            assert httpx.get(f"{url}/readyz", timeout=5).status_code == 200, (
                f"{url} is not ready after the faults"
            )
        print("Every replica is ready after the faults (none was restarted for the Redis fault).")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
