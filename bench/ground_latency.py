"""`make bench`: latency of POST /v1/ground over loopback for a real 60-object scene (ScanNet scene0590_00).

Sequential requests from one client, after a warm-up; prints p50/p99 per utterance kind and overall.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import httpx
import numpy as np

from app.api.launcher import running_service

SCENE = (
    Path(__file__).resolve().parent.parent / "tests" / "resources" / "scenes" / "scannet_scene0590_00.json"
)
UTTERANCES = [
    "I left my backpack on the table",  # two tables: two hypotheses
    "the remote is next to the lamp",
    "my shoes are under the desk",
    "look for the umbrella between the desk and the lamp",
    "the towel is on one of the chairs",  # three chairs
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--requests", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=50)
    args = parser.parse_args()
    scene = json.loads(SCENE.read_text())
    with running_service() as url, httpx.Client(base_url=url, timeout=30.0) as client:
        model = client.get("/v1/models").json()["models"][0]
        for i in range(args.warmup):
            client.post(
                "/v1/ground", json={"scene_graph": scene, "utterance": UTTERANCES[i % len(UTTERANCES)]}
            )
        samples: list[float] = []
        for i in range(args.requests):
            body = {"scene_graph": scene, "utterance": UTTERANCES[i % len(UTTERANCES)]}
            start = time.perf_counter()
            response = client.post("/v1/ground", json=body)
            samples.append((time.perf_counter() - start) * 1000.0)
            response.raise_for_status()
    p50, p99 = np.percentile(samples, [50, 99])
    n_objects = len(scene["objects"])
    print(f"POST /v1/ground, {n_objects}-object scene, grounder={model['name']}, loopback, sequential")
    print(f"machine: {platform.machine()}, {platform.python_implementation()} {platform.python_version()}")
    print(f"requests: {len(samples)}  p50: {p50:.2f} ms  p99: {p99:.2f} ms  mean: {np.mean(samples):.2f} ms")


if __name__ == "__main__":
    main()
