"""`make bench`: POST /v1/ground over loopback on real rooms, per grounder, with the per-stage split.

Scenes: ScanNet scene0590_00 (60 objects) and a 150-object map made of three real ScanNet rooms side by
side (the built-in proposer's target is under 20 ms on 150 objects). Sequential requests from one client
after a warm-up; every utterance is sent many times, so the proposer's phrase embeddings are warm after
the first round (label embeddings are cached per object label, as in service).
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

from app.sim.service import running_service

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


def measure(
    client: httpx.Client, scene: dict[str, Any], grounder: str, n: int, warmup: int
) -> dict[str, Any]:
    total, proposer, grounding = [], [], []
    for i in range(warmup + n):
        body = {
            "scene_graph": scene,
            "utterance": UTTERANCES[i % len(UTTERANCES)],
            "options": {"grounder": grounder},
        }
        start = time.perf_counter()
        response = client.post("/v1/ground", json=body)
        elapsed = (time.perf_counter() - start) * 1000.0
        response.raise_for_status()
        if i >= warmup:
            timings = response.json()["timings_ms"]
            total.append(elapsed)
            proposer.append(timings.get("proposer", 0.0))
            grounding.append(timings.get("grounder", 0.0))
    return {
        "p50": float(np.percentile(total, 50)),
        "p99": float(np.percentile(total, 99)),
        "proposer_p50": float(np.percentile(proposer, 50)),
        "grounder_p50": float(np.percentile(grounding, 50)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--requests", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=50)
    args = parser.parse_args()
    scenes = {
        "60-object room (scene0590_00)": load("scannet_scene0590_00.json"),
        "150-object map": map_of_150(),
    }
    env = {"VLMAP_RATE_LIMIT_PER_S": "0"}
    if (Path(__file__).resolve().parent.parent / "models" / "lsm" / "model.safetensors").is_file():
        env["VLMAP_GROUNDERS"] = '["lsm", "geometric"]'
    with running_service(env) as url, httpx.Client(base_url=url, timeout=30.0) as client:
        models = client.get("/v1/models").json()["models"]
        grounders = [m["name"] for m in models if m["role"] == "grounder" and m["name"] != "fixed"]
        proposer = next(m["name"] for m in models if m["role"] == "proposer")
        print(
            f"POST /v1/ground over loopback, sequential, proposer={proposer}; {args.requests} requests each"
        )
        print(
            f"machine: {platform.machine()}, {os.cpu_count()} CPUs, CPython {platform.python_version()}, "
            f"1-min load before: {os.getloadavg()[0]:.1f}"
        )
        print("| scene | grounder | p50 (ms) | p99 (ms) | proposer p50 (ms) | grounder p50 (ms) |")
        print("|---|---|---|---|---|---|")
        for label, scene in scenes.items():
            for grounder in grounders:
                row = measure(client, scene, grounder, args.requests, args.warmup)
                print(
                    f"| {label} | {grounder} | {row['p50']:.2f} | {row['p99']:.2f} | "
                    f"{row['proposer_p50']:.2f} | {row['grounder_p50']:.2f} |"
                )


if __name__ == "__main__":
    main()
