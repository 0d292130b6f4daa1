"""`python -m bench.fusion_ab --baseline DIR`: this checkout's fusion kernels against another's, alternating.

DIR is a checkout of the code to compare with (`git worktree add /tmp/before COMMIT`, or
`git archive COMMIT | tar -x -C /tmp/before`). Each round runs the same measurement once in a process
importing DIR's `app` and once in a process importing this checkout's, one after the other (A B A B ...),
so that both see the same moments of a shared host. The measurement uses only what both versions have
(`new_session`, `Session.observation_batch`, `BeliefState.apply_increments` / `apply_utterance`,
`fusion.apply_increments`): a stream of 20 batches of 100k random voxels with label ids (the observation
path, alternating with the bare update of the same batch) and 20 utterances of bench.fusion_kernel's
5-component mixture on its 1M-voxel grid. Prints one line per run and, with --json, one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent

MEASURE = r"""
import json, statistics, sys, time
from pathlib import Path
import numpy as np
import app
from app.allocator import keep_freed_buffers
from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import BeliefState, new_session
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph

keep_freed_buffers()
raw = json.loads(Path(sys.argv[1]).read_text(encoding="utf-8"))
scene = SceneGraph.model_validate(
    {"objects": [{k: o[k] for k in ("id", "label", "center", "size")} for o in raw["objects"]]}
)
rng = np.random.default_rng(0)
low, _ = scene.bounds()
grid = VoxelGrid(origin=tuple(low - 0.5), shape=(100, 100, 100), voxel_size=0.1)
n = grid.n_voxels
labels = {0: "floor", 1: "RemoteControl", 2: "sofa"}
session = new_session("ab", scene, "remote control", label_map=labels, grid=grid)
batches = [(rng.integers(0, n, 100_000), rng.integers(0, 3, 100_000)) for _ in range(20)]
layer = np.zeros(n, np.float32)
increments = [fusion.vision_increments(ids == 1, 0.9, 0.05) for _, ids in batches]
path_s, bare_s = [], []
session.belief.apply_increments(session.observation_batch(batches[0][1], flat_idx=batches[0][0]))
for (idx, ids), inc in zip(batches, increments):
    start = time.perf_counter()
    fusion.apply_increments(layer, idx, inc, -10.0, 20.0)
    bare_s.append(time.perf_counter() - start)
    start = time.perf_counter()
    session.belief.apply_increments(session.observation_batch(ids, flat_idx=idx))
    path_s.append(time.perf_counter() - start)
gaussians = []
for i in rng.choice(len(scene.objects), 5, replace=False):  # bench.fusion_kernel.five_component_mixture
    a = rng.normal(size=(3, 3)) * 0.2
    top = np.asarray(scene.objects[i].center) + np.array([0.0, 0.0, 0.5 * scene.objects[i].size[2] + 0.1])
    gaussians.append(Gaussian(top, a @ a.T + 0.01 * np.eye(3)))
mixture = GaussianMixture.from_components(rng.uniform(0.2, 1.0, 5), gaussians)
belief = BeliefState(grid)
belief.apply_utterance(mixture)
lang_s, lang_cpu = [], []
for _ in range(20):
    start, cpu = time.perf_counter(), time.thread_time()
    belief.apply_utterance(mixture)
    lang_s.append(time.perf_counter() - start)
    lang_cpu.append(time.thread_time() - cpu)
med = statistics.median
print(json.dumps({
    "app": str(Path(app.__file__).parent.parent),
    "observation_path_updates_per_s": 1e5 / med(path_s),
    "bare_update_updates_per_s": 1e5 / med(bare_s),
    "path_over_bare_time": med([p / b for p, b in zip(path_s, bare_s)]),
    "language_update_ms": med(lang_s) * 1e3,
    "language_update_best_ms": min(lang_s) * 1e3,
    "language_update_cpu_ms": med(lang_cpu) * 1e3,
}))
"""


def run(tree: Path) -> dict[str, float | str]:
    """One measurement in a fresh process importing `tree`'s app."""
    env = {**os.environ, "PYTHONPATH": str(tree), "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    scene = HERE / "tests" / "resources" / "belief" / "ai2thor_living_rooms_01.json"
    done = subprocess.run(
        [sys.executable, "-c", MEASURE, str(scene)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    result: dict[str, float | str] = json.loads(done.stdout)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--baseline", type=Path, required=True, help="a checkout of the code to compare with")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    runs: dict[str, list[dict[str, float | str]]] = {"baseline": [], "this": []}
    for _ in range(args.rounds):
        for name, tree in (("baseline", args.baseline.resolve()), ("this", HERE)):
            result = run(tree)
            runs[name].append(result)
            print(
                f"{name:8s} (load {os.getloadavg()[0]:.1f}): observation path "
                f"{float(result['observation_path_updates_per_s']) / 1e6:.1f} M/s, "
                f"{float(result['path_over_bare_time']):.2f}x the bare update's time; language update "
                f"{float(result['language_update_ms']):.2f} ms median (best "
                f"{float(result['language_update_best_ms']):.2f}, CPU "
                f"{float(result['language_update_cpu_ms']):.2f})",
                file=sys.stderr if args.json else sys.stdout,
            )
    if args.json:
        print(json.dumps(runs))


if __name__ == "__main__":
    main()
