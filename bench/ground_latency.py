"""`make bench`: POST /v1/ground over loopback on real rooms, per grounder, with the per-stage split.

Scenes: ScanNet scene0590_00 (60 objects) and a 150-object map made of three real ScanNet rooms side by
side (the built-in proposer's target is under 20 ms on 150 objects). Sequential requests from one client
after a warm-up. Two series per scene and grounder: "repeated" sends five utterances over and over, so
every text embedding is warm after the first round (label embeddings are cached per object label, as in
service); "new" sends an utterance never sent before in every request, about a target name never asked
for before ("I left the kettle on the table"), so the proposer's phrases and the LSM's hypothesis texts go
through the text encoder in that request.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from app.sim.service import cpu_seconds, process_cpu_seconds, running_service_process
from app.vocabulary import object_nouns

SCENES = Path(__file__).resolve().parent.parent / "tests" / "resources" / "scenes"
UTTERANCES = [
    "I left my backpack on the table",  # two tables: two hypotheses
    "the remote is next to the lamp",
    "my shoes are under the desk",
    "look for the umbrella between the desk and the lamp",
    "the towel is on one of the chairs",  # several chairs
]


def load(name: str) -> dict[str, Any]:
    return json.loads((SCENES / name).read_text())


def shifted(scene: dict[str, Any], dx: float, prefix: str, limit: int | None = None) -> dict[str, Any]:
    """The scene moved dx metres along x, its ids and region prefixed (to tile rooms into one map)."""
    objects = []
    for obj in scene["objects"][:limit]:
        moved = dict(obj, id=f"{prefix}{obj['id']}", center=[obj["center"][0] + dx, *obj["center"][1:]])
        moved["region_id"] = f"{prefix}{obj['region_id']}" if obj.get("region_id") else None
        objects.append(moved)
    regions = [
        dict(r, id=f"{prefix}{r['id']}", center=[r["center"][0] + dx, *r["center"][1:]])
        for r in scene["regions"]
    ]
    return {"regions": regions, "objects": objects}


def map_of_150() -> dict[str, Any]:
    parts = [
        shifted(load("scannet_scene0590_00.json"), 0.0, "a"),
        shifted(load("scannet_scene0000_00.json"), 20.0, "b"),
        shifted(load("scannet_scene0000_00.json"), 40.0, "c", limit=23),
    ]
    scene = {"frame_id": "map", "regions": [], "objects": []}
    for part in parts:
        scene["regions"] += part["regions"]
        scene["objects"] += part["objects"]
    return scene


#: Anchors of the new utterances, all in both scenes; the target name is what is new.
NEW_TEMPLATES = ["I left the {} on the table", "the {} is next to the lamp", "my {} is under the desk"]


class NewUtterances:
    """Utterances never sent before, each about a target name not used by any earlier one."""

    def __init__(self) -> None:
        skip = {word for text in UTTERANCES for word in text.split()}
        self._names = iter(sorted(n for n in object_nouns() if n not in skip))
        self._count = 0

    def __next__(self) -> str:
        self._count += 1
        return NEW_TEMPLATES[self._count % len(NEW_TEMPLATES)].format(next(self._names))


def measure(
    client: httpx.Client,
    scene: dict[str, Any],
    grounder: str,
    n: int,
    warmup: int,
    new: NewUtterances | None = None,
    service_pid: int | None = None,
) -> dict[str, Any]:
    """Latency percentiles of `n` requests after `warmup`; with `new`, every measured request's utterance
    comes from it (the warm-up's repeat `UTTERANCES`). With the service's pid, also the CPU time per
    measured request of its request process and of its grounding workers (ms): a measure of work done that
    the host's drift moves far less than latency."""
    total, proposer, grounding = [], [], []
    own_before = all_before = float("nan")
    for i in range(warmup + n):
        if i == warmup and service_pid is not None:
            own_before, all_before = process_cpu_seconds(service_pid), cpu_seconds(service_pid)
        utterance = UTTERANCES[i % len(UTTERANCES)]
        if new is not None and i >= warmup:
            utterance = next(new)
        body = {"scene_graph": scene, "utterance": utterance, "options": {"grounder": grounder}}
        start = time.perf_counter()
        response = client.post("/v1/ground", json=body)
        elapsed = (time.perf_counter() - start) * 1000.0
        response.raise_for_status()
        if i >= warmup:
            timings = response.json()["timings_ms"]
            total.append(elapsed)
            proposer.append(timings.get("proposer", 0.0))
            grounding.append(timings.get("grounder", 0.0))
    own = workers = float("nan")
    if service_pid is not None:
        own = process_cpu_seconds(service_pid) - own_before
        workers = cpu_seconds(service_pid) - all_before - own
    return {
        "p50": float(np.percentile(total, 50)),
        "p99": float(np.percentile(total, 99)),
        "proposer_p50": float(np.percentile(proposer, 50)),
        "grounder_p50": float(np.percentile(grounding, 50)),
        "request_process_cpu_ms": 1000.0 * own / n,
        "workers_cpu_ms": 1000.0 * workers / n,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--requests", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=50)
    parser.add_argument(
        "--new-requests", type=int, default=100, help="requests per row of the new-utterance series"
    )
    args = parser.parse_args()
    new = NewUtterances()
    if 4 * args.new_requests > len(object_nouns()):  # 2 scenes x 2 grounders, each name used once
        parser.error(f"--new-requests over {len(object_nouns()) // 4}: not enough target names")
    scenes = {
        "60-object room (scene0590_00)": load("scannet_scene0590_00.json"),
        "150-object map": map_of_150(),
    }
    env = {"VLMAP_RATE_LIMIT_PER_S": "0"}
    if (Path(__file__).resolve().parent.parent / "models" / "lsm" / "model.safetensors").is_file():
        env["VLMAP_GROUNDERS"] = '["lsm", "geometric"]'
    with running_service_process(env) as (proc, url), httpx.Client(base_url=url, timeout=30.0) as client:
        models = client.get("/v1/models").json()["models"]
        grounders = [m["name"] for m in models if m["role"] == "grounder" and m["name"] != "fixed"]
        proposer = next(m["name"] for m in models if m["role"] == "proposer")
        print(
            f"POST /v1/ground over loopback, sequential, proposer={proposer}; {args.requests} requests per "
            f"repeated row, {args.new_requests} per new-utterance row"
        )
        print(
            f"machine: {platform.machine()}, {os.cpu_count()} CPUs, CPython {platform.python_version()}, "
            f"1-min load before: {os.getloadavg()[0]:.1f}"
        )
        print(
            "| scene | grounder | utterances | p50 (ms) | p99 (ms) | proposer p50 (ms) | grounder p50 (ms) "
            "| CPU per request: request process / workers (ms) |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for label, scene in scenes.items():
            for grounder in grounders:
                for series, n, source in (("repeated", args.requests, None), ("new", args.new_requests, new)):
                    row = measure(client, scene, grounder, n, args.warmup, source, proc.pid)
                    print(
                        f"| {label} | {grounder} | {series} | {row['p50']:.2f} | {row['p99']:.2f} | "
                        f"{row['proposer_p50']:.2f} | {row['grounder_p50']:.2f} | "
                        f"{row['request_process_cpu_ms']:.2f} / {row['workers_cpu_ms']:.2f} |"
                    )


if __name__ == "__main__":
    main()
