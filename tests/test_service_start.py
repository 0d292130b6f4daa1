"""Waiting for a started service follows its progress: a dead or idle process fails fast, a busy one is
waited for (what a loaded machine needs, not a fixed time)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from app.sim.service import cpu_seconds, free_port, wait_ready


def _url() -> str:
    return f"http://127.0.0.1:{free_port()}"  # nothing listens there


def test_a_process_that_exits_fails_the_wait_at_once() -> None:
    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    proc.wait()
    with pytest.raises(RuntimeError, match="exited with code 3"):
        wait_ready(_url(), proc, stall_s=60.0, timeout_s=60.0)


def test_a_process_that_makes_no_progress_fails_after_the_stall_time() -> None:
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        with pytest.raises(RuntimeError, match="used no CPU for 1 s"):
            wait_ready(_url(), proc, stall_s=1.0, timeout_s=60.0)
    finally:
        proc.kill()
        proc.wait()


def test_a_working_process_and_its_children_count_as_progress() -> None:
    spin = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.5: pass\ntime.sleep(30)"
    child = f"subprocess.Popen([sys.executable, '-c', {spin!r}])"
    parent = f"import subprocess, sys, time\n{child}\ntime.sleep(30)"
    proc = subprocess.Popen([sys.executable, "-c", parent])
    try:
        before = cpu_seconds(proc.pid)
        # It never answers: it stalls once the child idles.
        with pytest.raises(RuntimeError, match="used no CPU"):
            wait_ready(_url(), proc, stall_s=2.0, timeout_s=60.0)
        assert cpu_seconds(proc.pid) >= before + 0.4  # the child's spinning counted for the parent
    finally:
        subprocess.run(["pkill", "-P", str(proc.pid)], check=False)
        proc.kill()
        proc.wait()
