"""`python -m bench.fusion_kernel`: speed of the VL-Map belief on a 1 M-voxel grid, in process.

Prints what it measures (median and best of `--repeats` runs):
- vision kernel: voxel updates per second of `fusion.apply_increments` with 100k-voxel batches (random
  voxels, the cache-hostile case, and one contiguous 100k-voxel box), and of the whole observation path
  (label ids -> increments -> apply) of `Session`;
- language update: one utterance with a 5-component mixture (`BeliefState.apply_utterance`);
- summary: `summarize` with the scene graph of a real AI2-THOR room (25 objects);
- memory per session: the layers' bytes and what tracemalloc sees for a whole stored session;
- the durable memory store's acknowledged update (log append + fsync) for a 100k-voxel batch, and the
  Redis store's when `--redis-url` is given: each `await store.update(...)` of the change the service makes
  (`app.sessions.changes`), on one event loop (a batch this large is not inline: it runs on a worker thread,
  as in the service); the Redis utterance includes its term's computation on the grid, as the service's
  utterance does before its update.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import platform
import statistics
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import anyio.to_thread
import numpy as np

from app.allocator import keep_freed_buffers
from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import BeliefState, language_log_likelihood, new_session
from app.belief.summary import summarize
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph
from app.sessions import changes

SCENE = (
    Path(__file__).resolve().parent.parent / "tests" / "resources" / "belief" / "ai2thor_living_rooms_01.json"
)
SHAPE = (100, 100, 100)
BATCH = 100_000


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median, best) seconds of `repeats` calls after one warm-up call."""
    fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples), min(samples)


def load_scene() -> SceneGraph:
    raw = json.loads(SCENE.read_text(encoding="utf-8"))
    keep = ("id", "label", "center", "size")
    return SceneGraph.model_validate({"objects": [{k: o[k] for k in keep} for o in raw["objects"]]})


def five_component_mixture(scene: SceneGraph, rng: np.random.Generator) -> GaussianMixture:
    anchors = rng.choice(len(scene.objects), 5, replace=False)
    gaussians = []
    for i in anchors:
        a = rng.normal(size=(3, 3)) * 0.2
        lift = np.array([0.0, 0.0, 0.5 * scene.objects[i].size[2] + 0.1])  # just above the object's top
        top = np.asarray(scene.objects[i].center) + lift
        gaussians.append(Gaussian(top, a @ a.T + 0.01 * np.eye(3)))
    return GaussianMixture.from_components(rng.uniform(0.2, 1.0, 5), gaussians)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--redis-url", default=None, help="also time the Redis store on this server")
    args = parser.parse_args()
    keep_freed_buffers()  # as the service does (app.allocator)
    rng = np.random.default_rng(0)
    scene = load_scene()
    low, _ = scene.bounds()
    grid = VoxelGrid(origin=tuple(low - 0.5), shape=SHAPE, voxel_size=0.1)
    n = grid.n_voxels
    cpu = platform.processor() or platform.machine()
    print(
        f"platform: {cpu}, {os.cpu_count()} CPUs, 1-min load {os.getloadavg()[0]:.1f}, numpy {np.__version__}"
    )
    print(f"grid: {SHAPE} = {n:,} voxels of {grid.voxel_size} m, layers {np.dtype(fusion.LAYER_DTYPE).name}")

    layer = np.zeros(n, dtype=fusion.LAYER_DTYPE)
    random_idx = rng.integers(0, n, BATCH)
    increments = fusion.vision_increments(rng.random(BATCH) < 0.05, 0.9, 0.05)
    box = np.zeros(SHAPE, dtype=bool)
    box[10:50, 10:60, 10:60] = True  # 40 * 50 * 50 = 100k voxels, like one camera frustum
    box_idx = np.flatnonzero(box)

    def kernel(idx: np.ndarray) -> Callable[[], None]:
        return lambda: fusion.apply_increments(layer, idx, increments, fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX)

    for name, idx in (("random voxels", random_idx), ("contiguous box", box_idx)):
        med, best = timed(kernel(idx), args.repeats)
        print(
            f"vision kernel, {BATCH:,}-voxel batch, {name}: {BATCH / med / 1e6:.1f} M voxel updates/s median "
            f"({med * 1e3:.2f} ms), {BATCH / best / 1e6:.1f} M/s best"
        )

    label_map = {0: "floor", 1: "RemoteControl", 2: "sofa"}
    session = new_session("bench", scene, "remote control", label_map=label_map, grid=grid)
    labels = rng.integers(0, 3, BATCH)

    def observation_path() -> None:
        session.belief.apply_increments(session.observation_batch(labels, flat_idx=random_idx))

    med, best = timed(observation_path, args.repeats)
    print(
        f"observation path (label ids -> increments -> apply), {BATCH:,} random voxels: "
        f"{BATCH / med / 1e6:.1f} M voxel updates/s median ({med * 1e3:.2f} ms), "
        f"{BATCH / best / 1e6:.1f} M/s best"
    )

    mixture = five_component_mixture(scene, rng)
    belief = BeliefState(grid)
    med, best = timed(lambda: belief.apply_utterance(mixture), max(3, args.repeats // 4))
    print(f"language update, 5-component mixture: {med * 1e3:.1f} ms median, {best * 1e3:.1f} ms best")

    belief.vis[:] = session.belief.vis
    med, best = timed(lambda: summarize(grid, belief.lang, belief.vis, scene), args.repeats)
    med_bare, best_bare = timed(lambda: summarize(grid, belief.lang, belief.vis), args.repeats)
    print(
        f"summary with {len(scene.objects)} objects: {med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best; "
        f"without places: {med_bare * 1e3:.2f} ms median, {best_bare * 1e3:.2f} ms best"
    )

    from app.stores import MemorySessionStore, SessionStore

    # The stores are async: one event loop runs every call below, started (with a worker thread) before
    # tracemalloc looks, so that the figure is the session's, not the loop's.
    runner = asyncio.Runner()
    warm = MemorySessionStore()
    tiny = VoxelGrid(origin=tuple(low), shape=(1, 1, 1), voxel_size=0.1)
    runner.run(warm.create(new_session("warm-up", scene, "", grid=tiny)))
    warm.close()
    tracemalloc.start()
    before, _ = tracemalloc.get_traced_memory()
    store = MemorySessionStore()
    fresh = new_session("bench", scene, "remote control", label_map=label_map, grid=grid)
    runner.run(store.create(fresh))
    del fresh
    runner.run(anyio.to_thread.run_sync(gc.collect))  # the worker thread lets go of its last job (`fresh`)
    after, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(
        f"memory per session: layers {belief.nbytes:,} bytes; a stored session as tracemalloc sees it "
        f"{after - before:,} bytes"
    )
    store.close()

    def observe(target: SessionStore, session_id: str) -> Callable[[], object]:
        """One acknowledged update of a 100k-voxel labelled batch (not inline: the service's change)."""
        change = changes.labels(labels, flat_idx=random_idx, max_voxels=BATCH)
        return lambda: runner.run(target.update(session_id, change))

    with tempfile.TemporaryDirectory() as data_dir:
        durable = MemorySessionStore(data_dir, snapshot_every=10**9, snapshot_bytes=2**40)
        stored = new_session("bench", scene, "remote control", label_map=label_map, grid=grid)
        runner.run(durable.create(stored))
        med, best = timed(observe(durable, stored.id), max(3, args.repeats // 2))
        print(
            f"durable memory store, acknowledged {BATCH:,}-voxel update (log + fsync + apply): "
            f"{med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best (data dir on {data_dir})"
        )
        durable.close()

    if args.redis_url:
        from app.stores.redis_store import RedisSessionStore

        redis_store = RedisSessionStore(args.redis_url, prefix=f"bench-{os.getpid()}")
        runner.run(redis_store.create(stored))
        med, best = timed(observe(redis_store, stored.id), max(3, args.repeats // 2))
        print(f"redis store, {BATCH:,}-voxel update: {med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best")

        async def utter() -> None:
            log_likelihood = language_log_likelihood(grid, mixture)  # as the service computes it first
            await redis_store.update(stored.id, changes.utterance(mixture, log_likelihood, grid))

        med, best = timed(lambda: runner.run(utter()), 3)
        print(f"redis store, utterance on {n:,} voxels: {med * 1e3:.1f} ms median, {best * 1e3:.1f} ms best")
        runner.run(redis_store.delete(stored.id))
        redis_store.close()
    runner.close()


if __name__ == "__main__":
    main()
