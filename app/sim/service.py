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

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_service(env: dict[str, str] | None = None, port: int | None = None) -> tuple[subprocess.Popen, str]:
    """Start `vlmap serve` on 127.0.0.1 (a free port unless given); returns the process and its base URL."""
    port = port or free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env={**os.environ, "HF_HUB_OFFLINE": "1", "VLMAP_LOG_LEVEL": "WARNING", **(env or {})},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return proc, f"http://127.0.0.1:{port}"


def wait_ready(url: str, proc: subprocess.Popen | None = None, timeout_s: float = 60.0) -> None:
    """Poll /readyz until it answers 200; fail early if the process died."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            msg = f"the service exited with code {proc.returncode} before becoming ready"
            raise RuntimeError(msg)
        try:
            if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    msg = f"the service at {url} did not become ready within {timeout_s} s"
    raise RuntimeError(msg)


@contextmanager
def running_service(env: dict[str, str] | None = None, timeout_s: float = 60.0) -> Iterator[str]:
    """Yield the base URL of a ready `vlmap serve` process; stop it afterwards."""
    proc, url = start_service(env)
    try:
        wait_ready(url, proc, timeout_s)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
