"""`python -m bench.fusion_kernel`: the VL-Map belief's speed on a 1 M-voxel grid, in process, beside OctoMap.

Prints what it measures (median, and the spread as best / p90 of the samples):
- the observation path against the bare vision update on one stream of 100k-voxel batches (random voxels,
  the cache-hostile case; label ids of which 5% name the target), alternating batch by batch: the whole
  path of `Session` (label ids -> increments -> look-alike filter -> `fusion.apply_increments`) and the
  bare update of the same batch's increments; and the bare update on one contiguous 100k-voxel box;
- OctoMap on the same stream (`bench/octomap_harness.cpp`, built by `make bench` against Debian's
  liboctomap-dev; skipped with a message when it is not built): `OcTree::updateNode(key, hit)` per voxel,
  hit where the label names the target; the rates' ratio, and the bytes of state per voxel of both;
- language update: one utterance with a 5-component mixture (`BeliefState.apply_utterance`);
- summary: `summarize` with the scene graph of a real AI2-THOR room (25 objects);
- memory per session: the layers' bytes and what tracemalloc sees for a whole stored session;
- the durable memory store's acknowledged update (log append + fsync) for a 100k-voxel batch, and the
  Redis store's when `--redis-url` is given: each `await store.update(...)` of the change the service makes
  (`app.sessions.changes`), on one event loop (a batch this large is not inline: it runs on a worker thread,
  as in the service); the Redis utterance includes its term's computation on the grid, as the service's
  utterance does before its update.

The path and the language update are also timed in CPU time (this thread's): on a shared host the wall time
includes whatever else the host ran meanwhile. `--json` prints one JSON object of the figures on stdout
instead (the text goes to stderr); `--profile` adds the observation path step by step.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import anyio.to_thread
import numpy as np

from app.allocator import keep_freed_buffers
from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import BeliefState, Session, _drop, language_log_likelihood, new_session
from app.belief.summary import summarize
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph
from app.sessions import changes

SCENE = (
    Path(__file__).resolve().parent.parent / "tests" / "resources" / "belief" / "ai2thor_living_rooms_01.json"
)
SHAPE = (100, 100, 100)
BATCH = 100_000
HARNESS = Path(__file__).resolve().parent.parent / "var" / "bench" / "octomap_harness"
TARGET_ID = 1  # "RemoteControl" in the bench's label map


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median, best) seconds of `repeats` calls after one warm-up call."""
    samples = timed_samples(fn, repeats)
    return statistics.median(samples), min(samples)


def timed_samples(
    fn: Callable[[], object], repeats: int, clock: Callable[[], float] = time.perf_counter
) -> list[float]:
    """Seconds of each of `repeats` calls after one warm-up call, by `clock` (wall time by default)."""
    fn()
    samples = []
    for _ in range(repeats):
        start = clock()
        fn()
        samples.append(clock() - start)
    return samples


def spread(samples: list[float]) -> dict[str, float]:
    """Median, best and 90th percentile of seconds."""
    ordered = sorted(samples)
    return {
        "median": statistics.median(ordered),
        "best": ordered[0],
        "p90": ordered[min(len(ordered) - 1, round(0.9 * (len(ordered) - 1)))],
    }


def rates(samples: list[float], voxels: int) -> str:
    s = spread(samples)
    return (
        f"{voxels / s['median'] / 1e6:.1f} M voxel updates/s median ({s['median'] * 1e3:.2f} ms; best "
        f"{voxels / s['best'] / 1e6:.1f} M/s, p90 {voxels / s['p90'] / 1e6:.1f} M/s)"
    )


def alternate_bare_and_path(
    session: Session, batches: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[list[float], list[float], list[float]]:
    """Seconds per batch of the bare update (`fusion.apply_increments` of the batch's increments on a layer
    of its own) and of the session's whole observation path, alternating batch by batch, so that the ratio
    is of the same moments of a shared host; and the path's CPU seconds per batch (this thread's: not the
    time the host ran something else)."""
    tp, fp = session.sensor_model.tp, session.sensor_model.fp
    increments = [fusion.vision_increments(labels == TARGET_ID, tp, fp) for _, labels in batches]
    layer = np.zeros(session.grid.n_voxels, dtype=fusion.LAYER_DTYPE)
    lo, hi = session.belief.limits.vis_min, session.belief.limits.vis_max

    def bare(b: int) -> None:
        fusion.apply_increments(layer, batches[b][0], increments[b], lo, hi)

    def path(b: int) -> None:
        idx, labels = batches[b]
        session.belief.apply_increments(session.observation_batch(labels, flat_idx=idx))

    bare(0)  # warm-up
    path(0)
    bare_s: list[float] = []
    path_s: list[float] = []
    cpu_s: list[float] = []
    for b in range(len(batches)):
        start = time.perf_counter()
        bare(b)
        bare_s.append(time.perf_counter() - start)
        start, cpu = time.perf_counter(), time.thread_time()
        path(b)
        path_s.append(time.perf_counter() - start)
        cpu_s.append(time.thread_time() - cpu)
    return bare_s, path_s, cpu_s


def profile_path(session: Session, batches: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Median ms of each step of the observation path on the stream, the steps timed one after the other
    per batch: where the path's time goes beyond the bare update (np.add.at and the clamp)."""
    observer, belief = session.observer, session.belief
    tp, fp = session.sensor_model.tp, session.sensor_model.fp
    lo, hi = belief.limits.vis_min, belief.limits.vis_max
    names = (
        "label ids -> increments (one table lookup, id checks)",
        "voxel index checks and int64 copy",
        "look-alike test and drop",
        "apply: np.add.at",
        "apply: clamp (whole layer)",
    )
    steps: list[list[float]] = [[] for _ in names]
    for idx, labels in [batches[0], *batches]:  # the first once more, as a warm-up
        ticks = [time.perf_counter()]
        increments = observer._id_increments(labels, tp, fp)
        assert increments is not None
        ticks.append(time.perf_counter())
        flat, _ = observer.voxel_indices(len(labels), None, idx, BATCH)
        ticks.append(time.perf_counter())
        explained = observer._explained(flat)
        if explained.any():
            flat, increments = _drop(flat, explained), _drop(increments, explained)
        ticks.append(time.perf_counter())
        np.add.at(belief.vis, flat, increments)
        ticks.append(time.perf_counter())
        np.clip(belief.vis, lo, hi, out=belief.vis)
        ticks.append(time.perf_counter())
        for samples, start, stop in zip(steps, ticks[:-1], ticks[1:], strict=True):
            samples.append(stop - start)
    profile = {name: statistics.median(s[1:]) * 1e3 for name, s in zip(names, steps, strict=True)}
    profile["total"] = sum(profile.values())
    return profile


def report_octomap(
    octomap: dict[str, Any], path_s: list[float], vlmap_bytes: int, n: int, say: Callable[[str], None]
) -> dict[str, Any]:
    """Say the OctoMap figures beside VL-Map's path; the figures for --json."""
    eager, lazy, path = spread(octomap["seconds"]), spread(octomap["lazy_seconds"]), spread(path_s)
    say(
        f"OctoMap OcTree::updateNode(key, hit) on the same stream: {rates(octomap['seconds'], BATCH)}; "
        f"with lazy_eval and updateInnerOccupancy per batch: {rates(octomap['lazy_seconds'], BATCH)}"
    )
    ratio, lazy_ratio = eager["median"] / path["median"], lazy["median"] / path["median"]
    say(f"VL-Map observation path / OctoMap rate: {ratio:.0f}x ({lazy_ratio:.0f}x against lazy_eval)")
    leaves, used = int(octomap["leaves"]), int(octomap["memory_bytes"])
    say(
        f"state per voxel: VL-Map {vlmap_bytes / n:.1f} bytes (two float32 layers, every voxel of the grid); "
        f"OctoMap {used / leaves:.1f} bytes per known leaf ({leaves:,} leaves after the stream, memoryUsage "
        f"{used:,} bytes, node {octomap['node_bytes']} bytes), {used / n:.1f} per grid voxel"
    )
    return {
        "octomap_updates_per_s": BATCH / eager["median"],
        "octomap_lazy_updates_per_s": BATCH / lazy["median"],
        "vlmap_over_octomap_rate": ratio,
        "vlmap_over_octomap_lazy_rate": lazy_ratio,
        "octomap_bytes_per_known_voxel": used / leaves,
        "octomap_bytes_per_grid_voxel": used / n,
        "octomap_leaves": leaves,
    }


def write_stream(path: Path, grid: VoxelGrid, batches: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """The batches as bench/octomap_harness.cpp reads them: voxel coordinates and hit (label = target)."""
    with path.open("wb") as out:
        out.write(b"VLMS" + np.array([len(batches), BATCH], "<u4").tobytes())
        out.write(np.array([grid.voxel_size], "<f8").tobytes())
        for idx, labels in batches:
            out.write(grid.flat_to_ijk(idx).astype("<u2").tobytes())
            out.write((labels == TARGET_ID).astype("u1").tobytes())


def run_octomap(
    harness: Path, grid: VoxelGrid, batches: list[tuple[np.ndarray, np.ndarray]], say: Callable[[str], None]
) -> dict[str, Any] | None:
    """The harness's figures for the stream, None (with the reason said) where it is not built."""
    if not harness.is_file():
        say(
            f"OctoMap: skipped, no harness at {harness} (`make bench` builds bench/octomap_harness.cpp when "
            "a C++ compiler and Debian's liboctomap-dev are there)"
        )
        return None
    with tempfile.TemporaryDirectory() as tmp:
        stream = Path(tmp) / "stream.bin"
        write_stream(stream, grid, batches)
        done = subprocess.run(
            [str(harness), str(stream)], capture_output=True, text=True, timeout=900, check=False
        )
    if done.returncode != 0:
        say(f"OctoMap: skipped, the harness failed ({done.returncode}): {done.stderr.strip()[:300]}")
        return None
    result: dict[str, Any] = json.loads(done.stdout)
    return result


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
    parser.add_argument("--repeats", type=int, default=20, help="batches in the stream, samples per figure")
    parser.add_argument("--redis-url", default=None, help="also time the Redis store on this server")
    parser.add_argument("--octomap-harness", type=Path, default=HARNESS, help="the built OctoMap harness")
    parser.add_argument("--json", action="store_true", help="print one JSON object of the figures")
    parser.add_argument("--profile", action="store_true", help="time the observation path step by step")
    args = parser.parse_args()
    figures: dict[str, Any] = {}

    def say(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    keep_freed_buffers()  # as the service does (app.allocator)
    rng = np.random.default_rng(0)
    scene = load_scene()
    low, _ = scene.bounds()
    grid = VoxelGrid(origin=tuple(low - 0.5), shape=SHAPE, voxel_size=0.1)
    n = grid.n_voxels
    cpu = platform.processor() or platform.machine()
    load = os.getloadavg()[0]
    say(f"platform: {cpu}, {os.cpu_count()} CPUs, 1-min load {load:.1f}, numpy {np.__version__}")
    say(f"grid: {SHAPE} = {n:,} voxels of {grid.voxel_size} m, layers {np.dtype(fusion.LAYER_DTYPE).name}")
    figures.update(cpus=os.cpu_count(), load_1min_before=load, numpy=np.__version__, grid_voxels=n)

    # One stream of batches for every method: random voxels, label ids 0-2 (1, a third, names the target).
    label_map = {0: "floor", TARGET_ID: "RemoteControl", 2: "sofa"}
    session = new_session("bench", scene, "remote control", label_map=label_map, grid=grid)
    batches = [(rng.integers(0, n, BATCH), rng.integers(0, 3, BATCH)) for _ in range(args.repeats)]
    bare_s, path_s, path_cpu = alternate_bare_and_path(session, batches)
    layer = np.zeros(n, dtype=fusion.LAYER_DTYPE)
    lo, hi = fusion.VIS_LOG_MIN, fusion.VIS_LOG_MAX
    bare_increments = fusion.vision_increments(batches[0][1] == TARGET_ID, 0.9, 0.05)  # one batch's
    ratios = sorted(p / q for p, q in zip(path_s, bare_s, strict=True))
    say(f"vision kernel alone (fusion.apply_increments), {BATCH:,} random voxels: {rates(bare_s, BATCH)}")
    say(
        f"observation path (label ids -> increments -> look-alike filter -> apply), same batches: "
        f"{rates(path_s, BATCH)}; path / kernel time {statistics.median(ratios):.2f} median; CPU time "
        f"{statistics.median(path_cpu) * 1e3:.2f} ms median ({BATCH / statistics.median(path_cpu) / 1e6:.1f} "
        "M/s)"
    )
    figures.update(
        bare_update_updates_per_s=BATCH / spread(bare_s)["median"],
        observation_path_updates_per_s=BATCH / spread(path_s)["median"],
        observation_path_best_updates_per_s=BATCH / spread(path_s)["best"],
        observation_path_p90_updates_per_s=BATCH / spread(path_s)["p90"],
        observation_path_over_bare_time=statistics.median(ratios),
        observation_path_cpu_updates_per_s=BATCH / statistics.median(path_cpu),
    )
    if args.profile:
        profile = profile_path(session, batches)
        say("observation path, step by step (median ms per 100k-voxel batch):")
        for name, ms in profile.items():
            say(f"  {name}: {ms:.3f} ms ({ms / profile['total']:.0%})")
        figures["observation_path_profile_ms"] = profile
    box = np.zeros(SHAPE, dtype=bool)
    box[10:50, 10:60, 10:60] = True  # 40 * 50 * 50 = 100k voxels, like one camera frustum
    box_idx = np.flatnonzero(box)
    box_s = timed_samples(
        lambda: fusion.apply_increments(layer, box_idx, bare_increments, lo, hi), args.repeats
    )
    say(f"vision kernel alone, one contiguous {BATCH:,}-voxel box: {rates(box_s, BATCH)}")

    octomap = run_octomap(args.octomap_harness, grid, batches, say)
    figures.update(octomap_updates_per_s=None, octomap_lazy_updates_per_s=None, vlmap_over_octomap_rate=None)
    figures["vlmap_bytes_per_voxel"] = session.belief.nbytes / n
    if octomap is not None:
        figures.update(report_octomap(octomap, path_s, session.belief.nbytes, n, say))

    mixture = five_component_mixture(scene, rng)
    belief = BeliefState(grid)
    lang_s = spread(timed_samples(lambda: belief.apply_utterance(mixture), args.repeats))
    lang_cpu = spread(timed_samples(lambda: belief.apply_utterance(mixture), args.repeats, time.thread_time))
    say(
        f"language update, 5-component mixture on {n:,} voxels: {lang_s['median'] * 1e3:.2f} ms median "
        f"(best {lang_s['best'] * 1e3:.2f}, p90 {lang_s['p90'] * 1e3:.2f}); CPU time "
        f"{lang_cpu['median'] * 1e3:.2f} ms median (best {lang_cpu['best'] * 1e3:.2f})"
    )
    figures.update(
        language_update_cpu_ms=lang_cpu["median"] * 1e3,
        language_update_ms_1m_voxels=lang_s["median"] * 1e3,
        language_update_best_ms=lang_s["best"] * 1e3,
        language_update_p90_ms=lang_s["p90"] * 1e3,
    )

    belief.vis[:] = session.belief.vis
    med, best = timed(lambda: summarize(grid, belief.lang, belief.vis, scene), args.repeats)
    med_bare, best_bare = timed(lambda: summarize(grid, belief.lang, belief.vis), args.repeats)
    say(
        f"summary with {len(scene.objects)} objects: {med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best; "
        f"without places: {med_bare * 1e3:.2f} ms median, {best_bare * 1e3:.2f} ms best"
    )
    figures.update(summary_ms=med * 1e3, summary_without_places_ms=med_bare * 1e3)

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
    say(
        f"memory per session: layers {belief.nbytes:,} bytes; a stored session as tracemalloc sees it "
        f"{after - before:,} bytes"
    )
    figures.update(session_layer_bytes=belief.nbytes, stored_session_bytes=after - before)
    store.close()

    def observe(target: SessionStore, session_id: str) -> Callable[[], object]:
        """One acknowledged update of a 100k-voxel labelled batch (not inline: the service's change)."""
        change = changes.labels(batches[0][1], flat_idx=batches[0][0], max_voxels=BATCH)
        return lambda: runner.run(target.update(session_id, change))

    with tempfile.TemporaryDirectory() as data_dir:
        durable = MemorySessionStore(data_dir, snapshot_every=10**9, snapshot_bytes=2**40)
        stored = new_session("bench", scene, "remote control", label_map=label_map, grid=grid)
        runner.run(durable.create(stored))
        med, best = timed(observe(durable, stored.id), max(3, args.repeats // 2))
        say(
            f"durable memory store, acknowledged {BATCH:,}-voxel update (log + fsync + apply): "
            f"{med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best (data dir on {data_dir})"
        )
        figures["durable_update_ms"] = med * 1e3
        durable.close()

    if args.redis_url:
        from app.stores.redis_store import RedisSessionStore

        redis_store = RedisSessionStore(args.redis_url, prefix=f"bench-{os.getpid()}")
        runner.run(redis_store.create(stored))
        med, best = timed(observe(redis_store, stored.id), max(3, args.repeats // 2))
        say(f"redis store, {BATCH:,}-voxel update: {med * 1e3:.2f} ms median, {best * 1e3:.2f} ms best")
        figures["redis_update_ms"] = med * 1e3

        async def utter() -> None:
            log_likelihood = language_log_likelihood(grid, mixture)  # as the service computes it first
            await redis_store.update(stored.id, changes.utterance(mixture, log_likelihood, grid))

        med, best = timed(lambda: runner.run(utter()), 3)
        say(f"redis store, utterance on {n:,} voxels: {med * 1e3:.1f} ms median, {best * 1e3:.1f} ms best")
        figures["redis_utterance_ms"] = med * 1e3
        runner.run(redis_store.delete(stored.id))
        redis_store.close()
    runner.close()
    figures["load_1min_after"] = os.getloadavg()[0]
    if args.json:
        print(json.dumps(figures))


if __name__ == "__main__":
    main()
