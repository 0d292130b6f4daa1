"""What a replica costs: install size, time to live and to ready, resident memory at idle and with live
1M-voxel sessions, per process (the request process and each grounding worker).

Each measurement starts a fresh `vlmap serve` (default settings, the embedded store durable in a
temporary directory). With `--baseline DIR` (a checkout of other code, e.g. `git worktree add DIR REV`)
the same measurements run alternately on it and on this tree, in the same sitting, so that the machine's
drift hits both alike; the table gives the median of the rounds and their spread.

    python -m bench.footprint --runtime-venv var/bench/runtime-venv --baseline /tmp/before --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from app.sim.service import cpu_seconds, free_port

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "tests" / "resources" / "scenes" / "scannet_scene0590_00.json"
#: A 100 x 100 x 100 grid of 10 cm voxels: a 1M-voxel session (8 MB of layers).
GRID_1M = {"voxel_size": 0.1, "min_corner": [-5.0, -5.0, -1.0], "max_corner": [5.0, 5.0, 9.0]}
SESSION_LOADS = (10, 100)


def du_bytes(path: Path) -> int:
    """Bytes on disk under `path` (as du counts them)."""
    out = subprocess.run(["du", "-sb", str(path)], capture_output=True, text=True, check=True).stdout
    return int(out.split()[0])


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(stat.parent.name))
        except (OSError, ValueError):
            continue
    return sorted(out)


def processes(pid: int) -> dict[str, int]:
    """RSS of the request process and of each child that holds more than 50 MiB (the grounding workers;
    spawn's small helper processes are left out)."""
    rows = {"request": rss_bytes(pid)}
    workers = [rss_bytes(c) for c in children(pid)]
    for i, rss in enumerate(sorted((w for w in workers if w > 50 << 20), reverse=True)):
        rows[f"worker {i + 1}"] = rss
    return rows


def measure(tree: Path, data_dir: Path) -> dict[str, Any]:
    """Start the service of `tree`, time it to live and ready, then read its memory under the loads."""
    port = free_port()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "VLMAP_LOG_LEVEL": "WARNING", "VLMAP_DATA_DIR": str(data_dir)}
    env["PYTHONPATH"] = str(tree)
    url = f"http://127.0.0.1:{port}"
    start = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--port", str(port)],
        cwd=tree,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    live_s = ready_s = None
    try:
        while ready_s is None:
            if proc.poll() is not None:
                msg = f"the service of {tree} exited with code {proc.returncode}"
                raise RuntimeError(msg)
            if time.monotonic() - start > 900:
                msg = f"the service of {tree} was not ready within 900 s"
                raise RuntimeError(msg)
            try:
                if live_s is None and httpx.get(f"{url}/healthz", timeout=1.0).status_code == 200:
                    live_s = time.monotonic() - start
                if httpx.get(f"{url}/readyz", timeout=1.0).status_code == 200:
                    ready_s = time.monotonic() - start
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        time.sleep(2.0)  # let start-up garbage settle
        result: dict[str, Any] = {
            "live_s": live_s,
            "ready_s": ready_s,
            "cpu_s_to_ready": cpu_seconds(proc.pid),
            "idle": processes(proc.pid),
        }
        scene = json.loads(SCENE.read_text())
        with httpx.Client(base_url=url, timeout=120.0) as client:
            created = 0
            for load in SESSION_LOADS:
                while created < load:
                    body = {"robot_id": f"robot-{created}", "scene_graph": scene, "grid": GRID_1M}
                    response = client.post("/v1/sessions", json=body)
                    response.raise_for_status()
                    assert response.json()["grid"]["n_voxels"] == 1_000_000
                    created += 1
                time.sleep(1.0)
                result[f"sessions_{load}"] = processes(proc.pid)
        return result
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def mib(value: float) -> str:
    return f"{value / 2**20:,.0f}"


def summary(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians (and min-max) over rounds of each figure."""

    def stat(values: list[float]) -> dict[str, float]:
        return {"median": statistics.median(values), "min": min(values), "max": max(values)}

    out: dict[str, Any] = {k: stat([r[k] for r in rounds]) for k in ("live_s", "ready_s", "cpu_s_to_ready")}
    for phase in ("idle", *(f"sessions_{n}" for n in SESSION_LOADS)):
        names = sorted({name for r in rounds for name in r[phase]})
        out[phase] = {name: stat([r[phase].get(name, 0) for r in rounds]) for name in names}
        out[phase]["replica"] = stat([sum(r[phase].values()) for r in rounds])
    return out


def print_table(results: dict[str, dict[str, Any]]) -> None:
    sides = list(results)
    print("| figure | " + " | ".join(sides) + " |")
    print("|---|" + "---|" * len(sides))

    def row(label: str, get: Any, fmt: Any) -> None:
        cells = []
        for side in sides:
            s = get(results[side])
            cells.append("-" if s is None else f"{fmt(s['median'])} ({fmt(s['min'])}-{fmt(s['max'])})")
        print(f"| {label} | " + " | ".join(cells) + " |")

    row("time to live (s)", lambda r: r["live_s"], lambda v: f"{v:.1f}")
    row("time to ready (s)", lambda r: r["ready_s"], lambda v: f"{v:.1f}")
    row("CPU to ready (s)", lambda r: r["cpu_s_to_ready"], lambda v: f"{v:.1f}")
    for phase in ("idle", *(f"sessions_{n}" for n in SESSION_LOADS)):
        names = sorted({n for r in results.values() for n in r[phase]}, key=lambda n: (n != "replica", n))
        for name in names:
            row(f"RSS MiB, {phase.replace('_', ' ')}, {name}", lambda r, p=phase, n=name: r[p].get(n), mib)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--baseline", type=Path, default=None, help="a checkout of the code to compare with")
    parser.add_argument("--runtime-venv", type=Path, default=None, help="a venv with the runtime lock only")
    parser.add_argument("--dev-venv", type=Path, default=Path(sys.prefix), help="the full development venv")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args(argv)

    sizes = {"dev venv (runtime + development lock)": du_bytes(args.dev_venv)}
    if args.runtime_venv is not None:
        sizes["runtime venv (runtime lock only)"] = du_bytes(args.runtime_venv)
    print("| install | MiB |\n|---|---|")
    for name, size in sizes.items():
        print(f"| {name} | {mib(size)} |")
    print()

    trees = {"this tree": ROOT, **({"baseline": args.baseline.resolve()} if args.baseline else {})}
    rounds: dict[str, list[dict[str, Any]]] = {side: [] for side in trees}
    for i in range(args.rounds):
        for side, tree in (reversed(trees.items()) if i % 2 else trees.items()):  # alternate who goes first
            with tempfile.TemporaryDirectory() as data_dir:
                rounds[side].append(measure(tree, Path(data_dir)))
            ready = rounds[side][-1]["ready_s"]
            print(f"round {i + 1}/{args.rounds}, {side}: ready in {ready:.1f} s", flush=True)
    results = {side: summary(r) for side, r in rounds.items()}
    print()
    print_table(results)
    out = {"install_bytes": sizes, "rounds": rounds, "summary": results}
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
