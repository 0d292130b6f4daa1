"""Start `vlmap serve` as a subprocess on a loopback port: what `vlmap sim` runs when given no `--url`.

Tests and benchmarks start their services with these too (their redis-server is `tests.harness`): real
processes, real sockets, nothing outside 127.0.0.1.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(
    env: dict[str, str] | None = None, port: int | None = None
) -> tuple[subprocess.Popen[bytes], str]:
    """Start `vlmap serve` on 127.0.0.1 (a free port unless given); returns the process and its base URL."""
    port = port or free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env={**os.environ, "HF_HUB_OFFLINE": "1", "VLMAP_LOG_LEVEL": "WARNING", **(env or {})},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return proc, f"http://127.0.0.1:{port}"


#: How long a starting service may use no CPU at all before it counts as stuck (seconds): loading the
#: models is CPU work, so a process that makes no progress for this long is not loading.
STALL_S = 30.0
#: The most a start may take however busy the machine (seconds).
MAX_START_S = 900.0


def _stat(path: Path) -> list[str] | None:
    """The fields of a /proc/<pid>/stat after the command name (state, parent pid, ...), None once gone."""
    try:
        return path.read_text().rsplit(")", 1)[1].split()
    except OSError:  # exited
        return None


def _cpu(fields: list[str]) -> float:
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime, in ticks


def process_cpu_seconds(pid: int | None = None) -> float:
    """CPU time (user + system, seconds) of one process so far, this one when `pid` is None; 0 once it is
    gone. Linux /proc."""
    if pid is None:
        times = os.times()
        return times.user + times.system
    fields = _stat(Path(f"/proc/{pid}/stat"))
    return 0.0 if fields is None else _cpu(fields)


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system, seconds) of a process and of its live children (the grounding workers);
    0 once it is gone. Linux /proc."""
    total = 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        fields = _stat(stat)
        if fields is not None and (int(stat.parent.name) == pid or int(fields[1]) == pid):  # [1]: the parent
            total += _cpu(fields)
    return total


def wait_ready(
    url: str,
    proc: subprocess.Popen[bytes] | None = None,
    stall_s: float = STALL_S,
    timeout_s: float = MAX_START_S,
) -> None:
    """Poll /readyz until it answers 200, for as long as the starting process keeps working: a busy
    machine loads the models more slowly, so the wait follows the process's CPU progress rather than a
    fixed time. Fails early if the process died, or made no progress for `stall_s`."""
    start = time.monotonic()
    progress, last_cpu = start, -1.0
    while time.monotonic() - start < timeout_s:
        if proc is not None and proc.poll() is not None:
            msg = f"the service exited with code {proc.returncode} before becoming ready"
            raise RuntimeError(msg)
        try:
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        now = time.monotonic()
        if proc is not None:
            cpu = cpu_seconds(proc.pid)
            if cpu > last_cpu:
                progress, last_cpu = now, cpu
            elif now - progress > stall_s:
                msg = f"the service at {url} used no CPU for {stall_s:g} s without becoming ready"
                raise RuntimeError(msg)
        time.sleep(0.1)
    msg = f"the service at {url} did not become ready within {timeout_s:g} s"
    raise RuntimeError(msg)


#: The settings of a service on the model-free parts (geometric grounder, lexical proposer, no worker
#: process): ready in seconds, for what measures the service rather than the models.
MODEL_FREE_ENV = {
    "VLMAP_GROUNDER": "geometric",
    "VLMAP_GROUNDERS": '["geometric"]',
    "VLMAP_PROPOSER": "lexical",
    "VLMAP_WORKER_PROCESSES": "0",
}


@contextmanager
def running_service(env: dict[str, str] | None = None, timeout_s: float = MAX_START_S) -> Iterator[str]:
    """Yield the base URL of a ready `vlmap serve` process; stop it afterwards."""
    with running_service_process(env, timeout_s) as (_, url):
        yield url


@contextmanager
def running_service_process(
    env: dict[str, str] | None = None, timeout_s: float = MAX_START_S
) -> Iterator[tuple[subprocess.Popen[bytes], str]]:
    """`running_service`, yielding the process too (to measure its CPU time)."""
    proc, url = start_service(env)
    try:
        wait_ready(url, proc, timeout_s=timeout_s)
        yield proc, url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
