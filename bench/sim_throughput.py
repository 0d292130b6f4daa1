"""`python -m bench.sim_throughput`: closed-loop episodes per minute, service included, on this machine.

Runs `vlmap sim`'s loop (app.sim.runner) against a `vlmap serve` process on loopback that it starts itself,
for a few ScanNet episodes of the unseen validation cases, every method the service can load (the LSM only
when models/lsm holds weights), and prints episodes per minute (an episode = all methods on it), the time a
50-episode x 100-step run would take at that rate (the issue's target: under 10 minutes), and where the time
went: camera ray casts and the simulated segmenter (realistic perception by default; computed in a
background thread while the service works), the main thread waiting for those frames, the HTTP calls by
kind, and the rest.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from app.client import VLMapClient
from app.settings import Settings
from app.sim.runner import SimConfig, load_episodes, run_simulation
from app.sim.service import running_service

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENES = REPO / "data" / "cases" / "val_unseen.jsonl"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scenes", type=Path, default=DEFAULT_SCENES, help="grounding cases (vlmap data build)"
    )
    parser.add_argument("--source", default="scannet")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument(
        "--methods", default=None, help="default: vision-only,geometric,fixed (+ lsm if loadable)"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not args.scenes.exists():
        parser.error(
            f"{args.scenes} does not exist: build the cases first (vlmap data build) or pass --scenes"
        )
    lsm_ready = (Settings().model_dir / "lsm").is_dir()
    if args.methods is None:
        methods = ["vision-only", *(["lsm"] if lsm_ready else []), "geometric", "fixed"]
    else:
        methods = args.methods.split(",")
    episodes = load_episodes(args.scenes, args.source, args.seed)
    config = SimConfig(n_steps=args.steps, seed=args.seed)
    grounders = sorted({"geometric", "fixed", *(["lsm"] if "lsm" in methods else [])})
    with tempfile.TemporaryDirectory(prefix="vlmap-bench-") as data_dir:
        env = {
            "VLMAP_DATA_DIR": data_dir,
            "VLMAP_RATE_LIMIT_PER_S": "0",
            "VLMAP_GROUNDERS": json.dumps(grounders),
        }
        started = time.perf_counter()
        with running_service(env) as url, VLMapClient(url, timeout_s=120.0) as client:
            startup = time.perf_counter() - started
            result = run_simulation(client, episodes, args.episodes, methods, config, progress=False)
    seconds = dict(result.seconds)
    wall = seconds["wall"]
    n = len(result.records)
    per_minute = 60.0 * n / wall
    http = {k: v for k, v in seconds.items() if k.startswith("http_")}
    waiting = seconds.get("frames_wait", 0.0)
    n_posts = n * len(methods) * args.steps
    ms_per_post = 1000.0 * http.get("http_observations", 0.0) / max(n_posts, 1)
    frames = ", ".join(f"{k} {seconds.get(k, 0.0):.1f}" for k in ("world", "camera", "noise"))
    print(f"vlmap sim: {n} episodes x {args.steps} steps x {len(methods)} methods ({', '.join(methods)})")
    print(f"machine: {os.cpu_count()} CPUs, {platform.machine()}, Python {platform.python_version()}")
    print(f"service start: {startup:.1f} s (not counted below); skipped episodes: {dict(result.skips)}")
    print(
        f"wall: {wall:.1f} s -> {per_minute:.2f} episodes/min; 50 such episodes: {50.0 / per_minute:.1f} min"
    )
    print(f"observation batches: {n_posts}, {ms_per_post:.1f} ms per round trip")
    print("breakdown (s):")
    print(f"  frames in the background thread: {frames}")
    print(f"  main thread waiting for frames: {waiting:.1f}")
    for kind, value in sorted(http.items()):
        print(f"  {kind}: {value:.1f} ({100.0 * value / wall:.0f}% of wall)")
    print(f"  other (client-side bookkeeping): {wall - sum(http.values()) - waiting:.1f}")


if __name__ == "__main__":
    main()
