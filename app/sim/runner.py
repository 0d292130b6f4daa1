"""Closed-loop episodes against a running VL-Map service: one simulated robot, one session per method.

Identical episodes. For each episode the runner computes ONE seeded trajectory (`app.sim.policy`) and ONE
seeded stream of labelled camera frames (`Camera`, then the perception model: `Segmenter` for "realistic",
the default, or `LabelNoise` for "ideal") before any request is made, and sends exactly these frames to one
session per method, so methods differ only in the utterance's language likelihood. The random streams of an
episode are seeded by (seed, crc32(episode id)): an episode's frames do not depend on which other episodes
run, nor in which order, nor on the methods compared.

Per episode and method (`run_method`):

1. POST /v1/sessions: the episode's scene graph without the target, the grid (voxel size and margin; the
   session's grid must equal `Episode.service_grid`, else the run stops), the target class, the sensor model
   (`SimConfig.sensor_model`: the ideal noise's own (tp, fp), or the realistic segmenter's true rates
   mis-specified by its factor) and a label map (the world's classes, "free" and "unknown");
2. language methods: POST .../utterances with the method's options (`METHOD_OPTIONS`: the grounder, and
   for scaffolded-llm the LLM proposer); vision-only sends no utterance;
3. one msgpack observation batch per frame: the observed voxels' (i, j, k) and their noisy label ids, free
   voxels labelled "free". Every answer carries the posterior summary, whose MAP voxel gives the argmax
   distance;
4. at the checkpoints (step 0 = after the utterance, then `n_checkpoints` evenly spaced steps, the last one
   included) the whole posterior is read (GET .../belief?format=grid) for the target mass: reading the
   1-4 MB grid after every step would cost more than the step itself;
5. DELETE the session.

Skipped episodes (counted by reason, never run): too little free floor for the robot (`min_free_floor_m2`),
a target with no voxel on the service's grid, a grid beyond the voxel limit, no utterance while a
language method is compared, or an utterance the service refuses to read (a 413 or 422: over its length
limit); an episode skipped half-way through its methods leaves no record.
"""

from __future__ import annotations

import json
import logging
import time
import zlib
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_VOXEL_SIZE_M, VoxelGrid
from app.client import VLMapClient, VLMapHTTPError
from app.errors import LimitExceeded
from app.sim.camera import Camera, CameraConfig
from app.sim.metrics import EpisodeOutcome, box_distance, target_mass
from app.sim.noise import UNKNOWN_LABEL, LabelNoise
from app.sim.perception import PERCEPTION_MODELS, PerceptionConfig, RateCounts, Segmenter
from app.sim.policy import PolicyConfig, trajectory
from app.sim.scenes import Episode
from app.sim.world import FREE, FREE_LABEL
from app.vocabulary import class_key

log = logging.getLogger("vlmap.sim")

#: Method name -> the options its utterance is sent with (None: no utterance). LSM, geometric and fixed use
#: the built-in proposer; Scaffolded-LLM asks the LLM for the hypotheses and their Gaussians, LLM-E2E for
#: the whole mixture at once (the reference's foundation-model baselines).
METHOD_OPTIONS: dict[str, dict[str, str] | None] = {
    "vision-only": None,
    "lsm": {"grounder": "lsm"},
    "geometric": {"grounder": "geometric"},
    "fixed": {"grounder": "fixed"},
    "scaffolded-llm": {"grounder": "scaffolded-llm", "proposer": "llm"},
    "llm-e2e": {"grounder": "llm-e2e"},
}
#: Methods that need a service started with an LLM endpoint (VLMAP_LLM_URL).
LLM_METHODS = ("scaffolded-llm", "llm-e2e")
DEFAULT_METHODS = ("vision-only", "lsm", "geometric", "fixed")


class SimError(Exception):
    """The simulation cannot run as asked (methods unavailable, a service that disagrees on the grid)."""


class EpisodeSkipped(Exception):
    """An episode unfit for the simulation; `reason` is a short key for the skip counts."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def check_methods(methods: Sequence[str]) -> tuple[str, ...]:
    """The methods, validated and deduplicated in order; SimError names what is unknown or unavailable."""
    out = tuple(dict.fromkeys(methods))
    if not out:
        msg = "give at least one method"
        raise SimError(msg)
    for method in out:
        if method not in METHOD_OPTIONS:
            msg = f"unknown method {method!r}; choose from {list(METHOD_OPTIONS)}"
            raise SimError(msg)
    return out


def needs_utterance(methods: Sequence[str]) -> bool:
    return any(METHOD_OPTIONS[m] is not None for m in methods)


def needed_parts(methods: Sequence[str]) -> tuple[set[str], set[str]]:
    """(grounders, proposers other than the built-in one) that the methods' utterances need."""
    options = [METHOD_OPTIONS[m] or {} for m in methods]
    grounders = {o["grounder"] for o in options if "grounder" in o}
    return grounders, {o["proposer"] for o in options if "proposer" in o}


def load_episodes(
    path: str | Path | Sequence[str | Path],
    source: str | None = None,
    seed: int = 0,
    max_target_size: float | None = None,
) -> list[Episode]:
    """Every episode a scenes path (or several, read in the order given) holds, in a seeded random order;
    only those of `source` when given, and only those whose target's largest side is at most
    `max_target_size` metres when given.

    - a folder: VLA-3D scenes (one episode per target candidate, no utterance);
    - a JSONL file of grounding cases (`app.data.cases`; lines with "case_id" and "utterance"): one episode
      per case, its utterance included;
    - another JSONL file: raw ScanNet or AI2-THOR layouts (one episode per target candidate, no utterance).
      Language methods need utterances: build grounding cases from the layouts (`vlmap data build`).
    """
    if not isinstance(path, str | Path):
        episodes = [e for p in path for e in _episodes_of(Path(p))]  # pooled in file order, then shuffled
    else:
        episodes = _episodes_of(Path(path))
    if source is not None:
        episodes = [e for e in episodes if e.source == source]
    if max_target_size is not None:
        episodes = [e for e in episodes if max(e.target.size) <= max_target_size]
    order = np.random.default_rng(seed).permutation(len(episodes))
    return [episodes[k] for k in order]


def _episodes_of(path: Path) -> list[Episode]:
    """The episodes of one scenes path, in file order (`load_episodes`)."""
    from app.sim.scenes import episodes_from_cases, load_layout_scenes, load_vla3d_scenes

    if path.is_dir():
        episodes = [s.episode(t) for s in load_vla3d_scenes(path) for t in s.candidate_target_ids]
    else:
        with path.open(encoding="utf-8") as fh:
            first = next((line for line in fh if line.strip()), None)
        if first is None:
            msg = f"{path} holds nothing"
            raise SimError(msg)
        head = json.loads(first)
        if "case_id" in head and "utterance" in head:
            episodes = list(episodes_from_cases(path))
        else:
            episodes = [s.episode(t) for s in load_layout_scenes(path) for t in s.candidate_target_ids]
    return episodes


@dataclass(frozen=True)
class SimConfig:
    """Everything that shapes an episode's frames and the checkpoints, shared by all methods.

    `perception` picks the model that labels the frames: "realistic" (`app.sim.perception`, parameters in
    `segmenter`) or "ideal" (`noise`: independent per-voxel flips at exactly the rates the service is told,
    the model of the earlier tables, which it reproduces draw for draw).
    """

    n_steps: int = 100
    seed: int = 0
    voxel_size: float = DEFAULT_VOXEL_SIZE_M
    margin: float = DEFAULT_MARGIN_M
    perception: str = "realistic"
    noise: LabelNoise = field(default_factory=LabelNoise)
    segmenter: PerceptionConfig = field(default_factory=PerceptionConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    min_free_floor_m2: float = 2.0
    n_checkpoints: int = 20

    def __post_init__(self) -> None:
        if self.n_steps < 1 or self.n_checkpoints < 1:
            msg = f"need n_steps >= 1 and n_checkpoints >= 1, got {self.n_steps} and {self.n_checkpoints}"
            raise SimError(msg)
        if self.perception not in PERCEPTION_MODELS:
            msg = f"unknown perception model {self.perception!r}; choose from {list(PERCEPTION_MODELS)}"
            raise SimError(msg)

    @property
    def sensor_model(self) -> tuple[float, float]:
        """(tp, fp) the service's sessions are told: the ideal noise's own rates, or the realistic
        segmenter's true rates mis-specified by its factor (`PerceptionConfig.sensor_model`)."""
        if self.perception == "ideal":
            return self.noise.tp, self.noise.fp
        return self.segmenter.sensor_model

    @property
    def checkpoints(self) -> tuple[int, ...]:
        """Steps after which the posterior is read: 0, then n_checkpoints evenly spaced up to n_steps."""
        k = np.arange(self.n_checkpoints + 1)
        return tuple(sorted({int(s) for s in np.rint(k * self.n_steps / self.n_checkpoints)}))


@dataclass(frozen=True)
class Frame:
    """One camera frame as the service receives it."""

    voxels: np.ndarray  # (M, 3) int32 voxel indices of the service's grid
    label_ids: np.ndarray  # (M,) uint32 noisy labels, ids of `PreparedEpisode.label_map`
    sees_target: bool  # a ray stopped on one of the target's voxels


@dataclass(frozen=True)
class PreparedEpisode:
    """An episode with its frames computed, ready to be sent to any number of sessions."""

    episode: Episode
    grid: VoxelGrid
    target_flat: np.ndarray  # (n_t,) the target's voxels on the grid
    label_map: dict[int, str]
    frames: tuple[Frame, ...]
    free_floor_m2: float
    seconds: dict[str, float]  # world, camera (ray casts), noise
    rates: RateCounts = field(default_factory=RateCounts)  # what the labels of the frames realised

    @property
    def target_seen(self) -> bool:
        return any(f.sees_target for f in self.frames)

    @property
    def first_seen_step(self) -> int | None:
        """1-based step of the first frame that saw the target."""
        return next((t for t, f in enumerate(self.frames, start=1) if f.sees_target), None)


def episode_rngs(seed: int, episode_id: str) -> tuple[np.random.Generator, np.random.Generator]:
    """(trajectory, label noise) generators of an episode: independent of the other episodes."""
    trajectory_seed, noise_seed = np.random.SeedSequence([seed, zlib.crc32(episode_id.encode())]).spawn(2)
    return np.random.default_rng(trajectory_seed), np.random.default_rng(noise_seed)


def prepare_episode(
    episode: Episode, config: SimConfig, camera: Camera | None = None, require_utterance: bool = False
) -> PreparedEpisode:
    """Build the world on the service's grid and compute the episode's frames; EpisodeSkipped if unfit."""
    if require_utterance and not episode.utterance:
        reason = "no_utterance"
        raise EpisodeSkipped(reason, episode.episode_id)
    started = time.perf_counter()
    try:
        grid = episode.service_grid(voxel_size=config.voxel_size, margin=config.margin)
    except LimitExceeded as exc:
        reason = "grid_too_large"
        raise EpisodeSkipped(reason, str(exc)) from None
    world = episode.world(grid)
    target_flat = world.object_voxels(episode.target.id)
    if len(target_flat) == 0:
        reason = "target_has_no_voxels"
        raise EpisodeSkipped(reason, episode.episode_id)
    free_floor = world.free_floor_area
    if free_floor < config.min_free_floor_m2:
        reason = "too_little_free_floor"
        raise EpisodeSkipped(reason, f"{episode.episode_id}: {free_floor:.2f} m^2")
    trajectory_rng, noise_rng = episode_rngs(config.seed, episode.episode_id)
    poses = trajectory(world, config.n_steps, trajectory_rng, config.policy)
    names = sorted({*world.labels, FREE_LABEL, UNKNOWN_LABEL, episode.target.label})
    id_of = {name: k for k, name in enumerate(names)}
    camera = camera or Camera(config.camera)
    is_target_voxel = np.zeros(grid.n_voxels, dtype=bool)
    is_target_voxel[target_flat] = True
    target_key = class_key(episode.target.label)
    object_is_target_class = np.array([class_key(label) == target_key for label in world.labels], dtype=bool)
    id_is_target_class = np.array([class_key(name) == target_key for name in names], dtype=bool)
    t0 = time.perf_counter()
    seen_frames = [camera.observe(world, pose) for pose in poses]
    t1 = time.perf_counter()
    segmenter = None
    if config.perception == "realistic":
        # Drawn first from the noise stream: the objects' propensities, fixed for the episode; then the
        # target's given that the mapping pass along this route never labelled it (1').
        segmenter = Segmenter(
            config.segmenter,
            world,
            episode.target.label,
            np.asarray(episode.target.size),
            config.camera,
            noise_rng,
        )
        segmenter.miss_while_mapping(world.index_of(episode.target.id), seen_frames, noise_rng)
        # The segmenter's label codes -> the label map's ids.
        id_of_code = np.array([id_of[str(n)] for n in segmenter.names], dtype=np.uint32)
    rates = RateCounts()
    frames = []
    for seen in seen_frames:
        if segmenter is None:
            noisy = config.noise.corrupt(
                world.labels_of(seen.owner), episode.target.label, noise_rng, vocabulary=world.labels
            )
            uniq, inverse = np.unique(noisy, return_inverse=True)
            label_ids = np.array([id_of[str(u)] for u in uniq], dtype=np.uint32)[inverse]
        else:
            label_ids = id_of_code[segmenter.label_codes(seen, noise_rng)]
        occupied = seen.owner != FREE
        rates.count(
            object_is_target_class[seen.owner[occupied]],
            id_is_target_class[label_ids[occupied]],
            is_target_voxel[seen.flat_idx[occupied]],
        )
        voxels = np.stack(np.unravel_index(seen.flat_idx, grid.shape), axis=1).astype(np.int32)
        frames.append(Frame(voxels, label_ids, bool(is_target_voxel[seen.flat_idx].any())))
    seconds = {"world": t0 - started, "camera": t1 - t0, "noise": time.perf_counter() - t1}
    return PreparedEpisode(
        episode=episode,
        grid=grid,
        target_flat=target_flat,
        label_map=dict(enumerate(names)),
        frames=tuple(frames),
        free_floor_m2=free_floor,
        seconds=seconds,
        rates=rates,
    )


def prepared_episodes(
    episodes: Iterable[Episode], config: SimConfig, skips: Counter[str], require_utterance: bool = False
) -> Iterator[PreparedEpisode]:
    """The episodes fit to run, prepared in order; the others counted in `skips` by reason."""
    camera = Camera(config.camera)
    for episode in episodes:
        try:
            yield prepare_episode(episode, config, camera, require_utterance)
        except EpisodeSkipped as exc:
            skips[exc.reason] += 1
            log.debug("skipped %s", exc)


@dataclass(frozen=True)
class MethodRun:
    """One method's session over one episode."""

    outcome: EpisodeOutcome
    grounded: bool | None  # the grounding's own flag; None without an utterance
    # whether the session fused it (not when its target names another class); None without an utterance
    fused: bool | None
    seconds: dict[str, float]  # observations (POSTs), grid reads, setup (create, utterance, delete)


class _Stopwatch:
    """Seconds spent per kind of request."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {"observations": 0.0, "grid_reads": 0.0, "setup": 0.0}

    def call(self, kind: str, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        try:
            return func(*args, **kwargs)
        finally:
            self.seconds[kind] += time.perf_counter() - started


def check_session_grid(session: dict[str, Any], grid: VoxelGrid) -> None:
    """SimError unless the session's grid is the one the episode's world was built on."""
    got = session.get("grid") or {}
    same = (
        list(got.get("shape", [])) == list(grid.shape)
        and np.allclose(got.get("min_corner", [np.nan] * 3), grid.origin, atol=1e-6)
        and abs(float(got.get("voxel_size", np.nan)) - grid.voxel_size) < 1e-9
    )
    if not same:
        msg = (
            f"the service's grid {got} differs from the simulator's (origin {list(grid.origin)}, shape "
            f"{list(grid.shape)}, voxel size {grid.voxel_size}): observed voxel indices would be wrong"
        )
        raise SimError(msg)


def run_method(
    client: VLMapClient, prepared: PreparedEpisode, method: str, config: SimConfig, robot_id: str = "sim"
) -> MethodRun:
    """One session of `method` over the prepared episode (module docstring, steps 1-5)."""
    options = METHOD_OPTIONS[method]
    episode, grid, target = prepared.episode, prepared.grid, prepared.episode.target
    watch = _Stopwatch()
    session = watch.call(
        "setup",
        client.create_session,
        f"{robot_id}-{method}",
        episode.service_graph.model_dump(mode="json"),
        grid={"voxel_size": config.voxel_size, "margin": config.margin},
        target_label=target.label,
        sensor_model=dict(zip(("tp", "fp"), config.sensor_model, strict=True)),
        label_map={str(k): name for k, name in prepared.label_map.items()},
    )
    session_id = session["id"]
    checkpoints = set(config.checkpoints)
    n_steps = len(prepared.frames)
    progress: list[float] = []
    masses: list[float] = []
    distances: list[float] = []

    def record(step: int, summary: dict[str, Any]) -> None:
        posterior = watch.call("grid_reads", client.get_belief_grid, session_id).posterior
        progress.append(step / n_steps)
        masses.append(target_mass(posterior, prepared.target_flat))
        distances.append(box_distance(summary["map_voxel"]["center"], target.min_corner, target.max_corner))

    try:
        check_session_grid(session, grid)
        grounded = fused = None
        if options is None:
            belief, _ = watch.call("setup", client.get_belief, session_id)
            summary = belief["summary"]
        else:
            try:
                answer = watch.call(
                    "setup", client.send_utterance, session_id, episode.utterance, options=options
                )
            except VLMapHTTPError as exc:
                if exc.status not in (413, 422):
                    raise
                reason = "utterance_refused"
                raise EpisodeSkipped(reason, f"{episode.episode_id}: {exc}") from None
            grounded, fused = bool(answer["grounding"]["grounded"]), bool(answer["fused"])
            summary = answer["belief"]["summary"]
        record(0, summary)
        for step, frame in enumerate(prepared.frames, start=1):
            answer = watch.call(
                "observations",
                client.send_observations,
                session_id,
                voxels=frame.voxels,
                labels=frame.label_ids,
            )
            if step in checkpoints:
                record(step, answer["belief"]["summary"])
    finally:
        watch.call("setup", client.delete_session, session_id)
    outcome = EpisodeOutcome(
        episode_id=episode.episode_id,
        method=method,
        target_seen=prepared.target_seen,
        n_target=len(prepared.target_flat),
        n_voxels=grid.n_voxels,
        progress=tuple(progress),
        mass=tuple(masses),
        argmax_distance=tuple(distances),
    )
    return MethodRun(outcome=outcome, grounded=grounded, fused=fused, seconds=watch.seconds)


def available_models(client: VLMapClient, role: str = "grounder") -> list[str]:
    """Names of the grounders (or proposers) the service has loaded (GET /v1/models)."""
    response = client.http.get("/v1/models")
    if response.status_code != 200:
        msg = f"GET /v1/models answered {response.status_code}: {response.text[:200]}"
        raise SimError(msg)
    return [m["name"] for m in response.json()["models"] if m.get("role") == role]


def check_service(client: VLMapClient, methods: Sequence[str]) -> None:
    """SimError unless the service has loaded every grounder and proposer the methods need."""
    grounders, proposers = needed_parts(methods)
    for role, needed in (("grounder", grounders), ("proposer", proposers)):
        loaded = available_models(client, role)
        missing = sorted(needed - set(loaded))
        if missing:
            hints = []
            if "lsm" in missing:
                hints.append(
                    "lsm needs trained weights in the service's model_dir (models/lsm) and "
                    "VLMAP_GROUNDERS naming it"
                )
            if set(missing) & {*LLM_METHODS, "llm"}:
                hints.append("the LLM baselines need a service started with an endpoint (VLMAP_LLM_URL)")
            hint = f" ({'; '.join(hints)})" if hints else ""
            msg = f"the service lacks the {role}s {missing} that {list(methods)} need; it has {loaded}{hint}"
            raise SimError(msg)


@dataclass
class EpisodeRecord:
    """What the run keeps of one episode: its description and each method's run."""

    episode_id: str
    scene_id: str
    source: str
    utterance: str | None
    language: str | None  # "human", "templated", None without an utterance
    target_label: str
    n_target_voxels: int
    n_voxels: int
    free_floor_m2: float
    target_seen: bool
    first_seen_step: int | None
    runs: dict[str, MethodRun] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "episode_id": self.episode_id,
            "scene_id": self.scene_id,
            "source": self.source,
            "utterance": self.utterance,
            "language": self.language,
            "target_label": self.target_label,
            "n_target_voxels": self.n_target_voxels,
            "n_voxels": self.n_voxels,
            "free_floor_m2": round(self.free_floor_m2, 3),
            "target_seen": self.target_seen,
            "first_seen_step": self.first_seen_step,
            "methods": {
                method: {
                    "grounded": run.grounded,
                    "fused": run.fused,
                    "progress": list(run.outcome.progress),
                    "target_mass": list(run.outcome.mass),
                    "information_gain": run.outcome.information_gain.tolist(),
                    "argmax_distance_m": list(run.outcome.argmax_distance),
                }
                for method, run in self.runs.items()
            },
        }


@dataclass
class SimResult:
    """A whole run: per-episode records, skip counts, the rates its frames' labels realised, and where the
    time went (seconds): world, camera and noise (frames, computed in the background thread), frames_wait
    (the main thread waiting for them), http_observations, http_grid_reads, http_setup (create, utterance,
    delete) and wall."""

    methods: tuple[str, ...]
    config: SimConfig
    records: list[EpisodeRecord] = field(default_factory=list)
    skips: Counter[str] = field(default_factory=Counter)
    seconds: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    rates: RateCounts = field(default_factory=RateCounts)

    @property
    def outcomes(self) -> list[EpisodeOutcome]:
        return [run.outcome for r in self.records for run in r.runs.values()]


def run_simulation(
    client: VLMapClient,
    episodes: Iterable[Episode],
    n_episodes: int,
    methods: Sequence[str],
    config: SimConfig,
    progress: bool = True,
) -> SimResult:
    """Run up to `n_episodes` fit episodes (in the order given) with every method on each.

    The next episode's frames are computed in a background thread while the service works on the current
    one (numpy and the HTTP wait release the GIL), which keeps both cores busy on a 2-core machine.
    """
    methods = check_methods(methods)
    check_service(client, methods)
    result = SimResult(methods=methods, config=config)
    stream = prepared_episodes(episodes, config, result.skips, needs_utterance(methods))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_episodes * len(methods), desc="episodes x methods", unit="run", dynamic_ncols=True)
    started = time.perf_counter()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-frames") as pool:
        upcoming: Future[PreparedEpisode | None] | None = pool.submit(next, stream, None)
        try:
            while upcoming is not None and len(result.records) < n_episodes:
                waited = time.perf_counter()
                prepared = upcoming.result()
                result.seconds["frames_wait"] += time.perf_counter() - waited
                if prepared is None:
                    break
                wanted_more = len(result.records) + 1 < n_episodes
                upcoming = pool.submit(next, stream, None) if wanted_more else None
                for kind, seconds in prepared.seconds.items():
                    result.seconds[kind] += seconds
                try:
                    record = _run_episode(client, prepared, methods, config, result, bar)
                except EpisodeSkipped as exc:
                    result.skips[exc.reason] += 1
                    log.debug("skipped %s", exc)
                    if upcoming is None:
                        upcoming = pool.submit(next, stream, None)
                    continue
                result.rates.add(prepared.rates)
                result.records.append(record)
        finally:
            if upcoming is not None:
                upcoming.cancel()
            if bar is not None:
                bar.close()
    result.seconds["wall"] = time.perf_counter() - started
    return result


def _run_episode(
    client: VLMapClient,
    prepared: PreparedEpisode,
    methods: Sequence[str],
    config: SimConfig,
    result: SimResult,
    bar: Any,
) -> EpisodeRecord:
    episode = prepared.episode
    record = EpisodeRecord(
        episode_id=episode.episode_id,
        scene_id=episode.scene_id,
        source=episode.source,
        utterance=episode.utterance,
        language=episode.language,
        target_label=episode.target.label,
        n_target_voxels=len(prepared.target_flat),
        n_voxels=prepared.grid.n_voxels,
        free_floor_m2=prepared.free_floor_m2,
        target_seen=prepared.target_seen,
        first_seen_step=prepared.first_seen_step,
    )
    for method in methods:
        run = run_method(client, prepared, method, config)
        record.runs[method] = run
        for kind, seconds in run.seconds.items():
            result.seconds[f"http_{kind}"] += seconds
        if bar is not None:
            bar.update(1)
    return record
