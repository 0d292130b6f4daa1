"""A `redis-server` for tests and benchmarks (`bench.fleet`), in a temporary directory on 127.0.0.1.

The `vlmap serve` subprocess they start beside it is `app.sim.service` (which `vlmap sim` ships with).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from app.sim.service import free_port


class RedisServer:
    """`redis-server` in a temporary directory on 127.0.0.1; `restart()` keeps the port (and AOF data)."""

    def __init__(self, binary: str, appendonly: bool = False) -> None:
        self.binary = binary
        self.appendonly = appendonly
        self.port = free_port()
        self.workdir = Path(tempfile.mkdtemp(prefix="vlmap-redis-"))
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self, timeout_s: float = 10.0) -> None:
        import redis

        args = [self.binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", ""]
        args += ["--appendonly", "yes" if self.appendonly else "no", "--appendfsync", "always"]
        self.proc = subprocess.Popen(
            [*args, "--dir", str(self.workdir)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        client = redis.Redis(port=self.port)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                try:
                    client.ping()
                    return
                except redis.ConnectionError:
                    if self.proc.poll() is not None or time.monotonic() > deadline:
                        msg = f"redis-server did not start on port {self.port}"
                        raise RuntimeError(msg) from None
                    time.sleep(0.05)
        finally:
            client.close()

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
            self.proc = None

    def restart(self) -> None:
        self.stop()
        self.start()

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.workdir, ignore_errors=True)
