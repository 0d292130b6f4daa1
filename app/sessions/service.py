"""The session use-cases, each written once: create, list, read, delete, replace the scene graph, utter,
observe (labels or detections), summarise and download the grid.

`SessionService` checks the caller's access against the session it acts on, turns requests into the pure
changes of `app.sessions.changes` for the store, answers a retried request (an Idempotency-Key the store
remembers) as the first time once the caller may see it, and owns the summary cache. What it computes on
whole layers or grids runs on the worker threads (`run`); the store decides what else needs one.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import hashlib
import json
import logging
import math
import time
import uuid
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Coroutine, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar

import numpy as np

from app.belief.grid import VoxelGrid
from app.belief.session import (
    SensorModel,
    Session,
    SessionInfo,
    UpdateResult,
    check_target_label,
    language_log_likelihood,
    new_session,
)
from app.belief.summary import DEFAULT_TOP_K, SUMMARY_FORMAT, PosteriorSummary, column_mass, place_voxels
from app.errors import AlreadyApplied, IdempotencyKeyReused, InvalidInput, LimitExceeded, NotFound, VLMapError
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.limits import check_coordinates
from app.scene_graph.model import SceneGraph
from app.sessions import changes
from app.sessions.batch import ObservationBatch
from app.sessions.changes import Caller
from app.sessions.events import EventHub, EventStream, SessionFollow, Sync
from app.sessions.recording import RECORD_TOP_K, Frame, merged, scene_graph_part, utterance_part
from app.sessions.summaries import Belief, SummaryCache, TopDown, UtteranceLog
from app.settings import Settings
from app.stores.base import Idempotency, IdempotencyRecord, SessionStore
from app.stores.events import StoredEvent
from app.vocabulary import head_noun, lemmas, lexical_match, object_nouns

log = logging.getLogger("vlmap.sessions")
T = TypeVar("T")
#: Runs a function on a worker thread: `run(func, *args)`.
Runner = Callable[..., Awaitable[Any]]
#: Sessions whose latest top-down view a process keeps (`SessionService.top_down`).
TOP_DOWN_SESSIONS = 64
#: Grounds an utterance in a scene graph with the parts the request named.
Ground = Callable[[SceneGraph], Awaitable[tuple[Grounding, LanguageSensor]]]


@dataclass(frozen=True)
class Applied(Generic[T]):
    """A change's outcome: `replayed` when it answers a retry of a keyed request (then `answer` is what the
    first answer embedded beside the state, as its caller gave it)."""

    value: T
    replayed: bool = False
    answer: bytes = b""


@dataclass(frozen=True)
class GridRequest:
    """The voxel grid a new session asks for: around its scene graph, or between two corners."""

    voxel_size: float
    margin: float
    min_corner: Sequence[float] | None = None
    max_corner: Sequence[float] | None = None


@dataclass(frozen=True)
class NewSession:
    """A request for a session: whose, on what map, looking for what (may be "": named later)."""

    robot_id: str
    scene_graph: SceneGraph
    grid: GridRequest
    target_label: str = ""
    label_map: Mapping[str, str] | None = None  # label id (digits) -> class name
    sensor_model: SensorModel | None = None


@dataclass(frozen=True)
class PreparedUtterance:
    """An utterance grounded in a session's scene graph, and whether the session will fuse it."""

    info: SessionInfo
    grounding: Grounding
    sensor: LanguageSensor
    fused: bool
    reason: str | None
    utterance: str = ""  # its text, for the session's event


def utterance_verdict(target_label: str, result: Grounding) -> tuple[bool, str | None]:
    """Whether a session looking for `target_label` fuses this grounding, and what to tell the caller.

    Not fused: the session has a target class and the utterance's target phrase names an object class (its
    lemmatised head noun, or the whole phrase, is one of `object_nouns()`) that no naming of the session's
    matches (`lexical_match` 0; "bag" names a backpack loosely, "keys" a keychain). A phrase that names no
    object ("it", "something", empty) fuses. An utterance that was not grounded fuses its broad prior, and
    the reason says that the belief got only that.
    """
    spoken = result.proposal.parse.target
    phrase = lemmas(spoken)
    names_an_object = phrase in object_nouns() or head_noun(phrase) in object_nouns()
    if target_label and names_an_object and lexical_match(phrase, lemmas(target_label)) == 0:
        return (
            False,
            f"the utterance's target {spoken!r} is not the session's target {target_label!r}: not fused",
        )
    if not result.grounded:
        why = f" ({result.proposal.reason})" if result.proposal.reason else ""
        return True, f"not grounded{why}: the belief got only the broad prior"
    return True, None


def names_a_class(target: str, label_map: Mapping[int, str]) -> bool:
    """Whether an utterance's target phrase can serve as the session's target class."""
    try:
        check_target_label(target, label_map)
    except InvalidInput:
        return False
    return True


def summary_options(top_k: int, created_at: float) -> str:
    """The name of a shared summary (`SessionStore.summary_get`): its options, and the incarnation of the
    session it summarises (a session made again under its id restarts its versions)."""
    return json.dumps({"format": SUMMARY_FORMAT, "top_k": top_k, "created_at": created_at}, sort_keys=True)


def keyed_session_id(robot_id: str, idempotency: Idempotency) -> str:
    """The id a keyed creation gives its session: the same for a retry, so that the store finds it."""
    digest = hashlib.sha256(f"{robot_id}\0{idempotency.key}".encode()).digest()
    return uuid.UUID(bytes=digest[:16]).hex


class SessionService:
    """The use-cases over one store (module docstring); `run` puts CPU work on the worker threads."""

    def __init__(self, store: SessionStore, settings: Settings, run: Runner) -> None:
        self.store = store
        self.settings = settings
        self.run = run
        self.summaries = SummaryCache(watch_s=settings.summary_watch_s)
        self._top_downs: OrderedDict[str, TopDown] = OrderedDict()
        self._ahead: set[asyncio.Task[None]] = set()
        self._recording_due: dict[str, Mapping[str, Any]] = {}  # session -> its unrecorded batch cause
        self._recorded_at: OrderedDict[str, float] = OrderedDict()  # session -> its last batch frame's time
        self._recording_timers: dict[str, asyncio.TimerHandle] = {}
        store.events.history = settings.events_history
        self.events = EventHub(
            store.events,
            capacity=settings.events_buffer,
            fleet_history=settings.events_fleet_history,
            max_streams=settings.max_event_streams,
        )

    # -- helpers --------------------------------------------------------------------------------------------

    @staticmethod
    def _replay(record: object, idempotency: Idempotency | None, caller: Caller) -> IdempotencyRecord:
        """The first request's record, once the caller may write its session and the request is the same
        (else a 422)."""
        assert isinstance(record, IdempotencyRecord) and idempotency is not None  # only keyed changes replay
        if record.robot_id:
            caller.require_write(record.robot_id)
        if record.fingerprint != idempotency.fingerprint:
            msg = "this Idempotency-Key was used with another request; use a new key for a new request"
            raise IdempotencyKeyReused(msg, field="Idempotency-Key")
        return record

    async def _readable(self, caller: Caller, session_id: str) -> SessionInfo:
        info = await self.store.head(session_id)
        caller.require_read(info.robot_id)
        return info

    async def _writable(self, caller: Caller, session_id: str) -> SessionInfo:
        info = await self.store.head(session_id)
        caller.require_write(info.robot_id)
        return info

    # -- the session record ---------------------------------------------------------------------------------

    def _grid(self, request: GridRequest, scene_graph: SceneGraph) -> VoxelGrid:
        limit = self.settings.max_grid_voxels
        low_corner, high_corner = request.min_corner, request.max_corner
        if low_corner is None and high_corner is None:
            return VoxelGrid.around(
                scene_graph, voxel_size=request.voxel_size, margin=request.margin, max_voxels=limit
            )
        if low_corner is None or high_corner is None:
            msg = "give both min_corner and max_corner, or neither"
            raise InvalidInput(msg, field="grid.min_corner")
        check_coordinates("grid.min_corner", [low_corner], self.settings.max_coordinate_m)
        check_coordinates("grid.max_corner", [high_corner], self.settings.max_coordinate_m)
        low, high = np.asarray(low_corner, dtype=np.float64), np.asarray(high_corner, dtype=np.float64)
        if not np.all(high > low):
            msg = "max_corner must be above min_corner on every axis"
            raise InvalidInput(msg, field="grid.max_corner")
        shape = [math.ceil(float(extent) / request.voxel_size) for extent in high - low]  # no overflow
        if math.prod(shape) > limit:
            msg = f"the grid needs {math.prod(shape):,} voxels, more than the limit {limit:,}"
            raise LimitExceeded(msg, limit_name="max_grid_voxels")
        nx, ny, nz = shape
        return VoxelGrid(origin=tuple(low), shape=(nx, ny, nz), voxel_size=request.voxel_size)

    def _label_map(self, raw: Mapping[str, str] | None) -> dict[int, str]:
        """The label map with integer ids (each key is 1-10 ASCII digits, as the API's schema checks)."""
        limit = self.settings.max_label_map_entries
        if raw is not None and len(raw) > limit:
            msg = f"label_map: {len(raw)} entries exceed the limit of {limit}"
            raise LimitExceeded(msg, limit_name="max_label_map_entries")
        out: dict[int, str] = {}
        for key, name in (raw or {}).items():
            if int(key) >= 2**32:
                msg = f"label ids are uint32 (below 4294967296), got {key}"
                raise InvalidInput(msg, field=f"label_map.{key}")
            if int(key) in out:  # "7" and "007": one id named twice, and a JSON object keeps both
                msg = f"label id {int(key)} is given twice (as {key!r} and another spelling)"
                raise InvalidInput(msg, field=f"label_map.{key}")
            out[int(key)] = name
        return out

    def _check_places(self, grid: VoxelGrid, scene_graph: SceneGraph) -> None:
        """LimitExceeded unless the voxels of the scene graph's places on `grid` are within the limit: every
        summary of the session sums the belief over them."""
        total, limit = place_voxels(grid, scene_graph), self.settings.max_place_voxels
        if total > limit:
            msg = (
                f"the scene graph's objects and regions cover {total:,} voxels of the grid (summed over "
                f"them), more than the limit {limit:,}; use larger voxels or fewer, smaller boxes"
            )
            raise LimitExceeded(msg, limit_name="max_place_voxels")

    def _new_session(self, request: NewSession, session_id: str | None) -> Session:
        grid = self._grid(request.grid, request.scene_graph)
        self._check_places(grid, request.scene_graph)
        return new_session(
            request.robot_id,
            request.scene_graph,
            request.target_label,
            label_map=self._label_map(request.label_map),
            sensor_model=request.sensor_model,
            grid=grid,
            max_voxels=self.settings.max_grid_voxels,
            session_id=session_id,
        )

    async def create(
        self, caller: Caller, request: NewSession, idempotency: Idempotency | None = None
    ) -> Applied[SessionInfo]:
        """A uniform belief over a grid around the robot's scene graph."""
        caller.require_write(request.robot_id)
        session_id = keyed_session_id(request.robot_id, idempotency) if idempotency is not None else None
        session = await self.run(self._new_session, request, session_id)
        try:
            max_per_robot = self.settings.max_sessions_per_robot
            info = await self.store.create(session, max_per_robot=max_per_robot, idempotency=idempotency)
        except AlreadyApplied as exc:
            self._replay(exc.record, idempotency, caller)
            try:
                return Applied(await self.store.head(session.id), replayed=True)
            except NotFound:
                # Its tombstone remembered the key: the creation was applied once, and deleted since.
                msg = f"the session {session.id!r} made under this Idempotency-Key was deleted since"
                raise NotFound(msg) from None
        await self._record(info.id, {"kind": "created"}, scene_graph=request.scene_graph)
        return Applied(info)

    async def sessions(self, caller: Caller, robot_id: str | None = None) -> list[SessionInfo]:
        """The sessions the caller may read (of one robot, if given), oldest first."""
        return [info for info in await self.store.list(robot_id) if caller.can_read(info.robot_id)]

    async def get(self, caller: Caller, session_id: str) -> SessionInfo:
        """A session's metadata."""
        return await self._readable(caller, session_id)

    async def delete(
        self, caller: Caller, session_id: str, idempotency: Idempotency | None = None
    ) -> Applied[None]:
        """Delete a session and its belief."""
        try:
            await self._writable(caller, session_id)
        except NotFound:
            if idempotency is None:
                raise
            # Gone already: the store answers a retry of its delete from the record it left (checked below).
        try:
            await self.store.delete(session_id, idempotency=idempotency)
        except AlreadyApplied as exc:
            self._replay(exc.record, idempotency, caller)
            return Applied(None, replayed=True)
        return Applied(None)

    async def replace_scene_graph(
        self, caller: Caller, session_id: str, scene_graph: SceneGraph, idempotency: Idempotency | None = None
    ) -> Applied[SessionInfo]:
        """Use a new scene graph for later utterances and look-alikes (the grid and the layers stay)."""
        info = await self._writable(caller, session_id)
        await self.run(self._check_places, info.grid, scene_graph)
        replayed = False
        sizes = {"objects": len(scene_graph.objects), "regions": len(scene_graph.regions)}
        cause = {"kind": "scene_graph", **sizes}
        change = dataclasses.replace(changes.scene_graph(scene_graph, caller=caller), event=lambda _: cause)
        try:
            await self.store.update(session_id, change, idempotency=idempotency)
        except AlreadyApplied as exc:
            self._replay(exc.record, idempotency, caller)
            replayed = True
        else:
            await self._record(session_id, cause, scene_graph=scene_graph)
        return Applied(await self.store.head(session_id), replayed=replayed)

    # -- language -------------------------------------------------------------------------------------------

    async def prepare_utterance(
        self, caller: Caller, session_id: str, ground: Ground, utterance: str = ""
    ) -> PreparedUtterance:
        """Ground an utterance (`utterance`: its text) in the session's scene graph, once the caller may write
        the session."""
        info, scene_graph = await self.store.head_and_scene_graph(session_id)
        caller.require_write(info.robot_id)
        grounding, sensor = await ground(scene_graph)
        fused, reason = utterance_verdict(info.target_label, grounding)
        return PreparedUtterance(info, grounding, sensor, fused, reason, utterance)

    async def fuse_utterance(
        self, caller: Caller, prepared: PreparedUtterance, idempotency: Idempotency | None = None
    ) -> Applied[Belief]:
        """Fuse a prepared utterance unless its verdict refused it; while the session has no target class, the
        utterance's target phrase names it in the same update. `idempotency.answer` is remembered with it.
        A refused utterance changes no version, but the session's event stream is told of it."""
        info, replayed, answer = prepared.info, False, b""
        cause = {"kind": "utterance", "utterance": prepared.utterance, "fused": prepared.fused}
        cause |= {"reason": prepared.reason, "named_target": None}
        readings = prepared.grounding.hypotheses  # what a dashboard shows of the last utterance
        cause["hypotheses"] = [
            {"text": h.text, "weight": h.weight, "anchor_ids": list(h.anchor_ids)} for h in readings
        ]
        if prepared.fused:
            target = prepared.grounding.proposal.parse.target
            names = None
            if not info.target_label and target and names_a_class(target, info.label_map):
                names = target
            mixture = prepared.grounding.mixture
            log_likelihood = await self.run(language_log_likelihood, info.grid, mixture)
            change = changes.utterance(
                mixture,
                log_likelihood,
                info.grid,
                names_target=names,
                target_read=info.target_label,
                caller=caller,
            )
            cause["named_target"] = names
            change = dataclasses.replace(change, event=lambda _: cause)
            try:
                await self.store.update(info.id, change, idempotency=idempotency)
            except AlreadyApplied as exc:
                answer, replayed = self._replay(exc.record, idempotency, caller).answer, True
        else:
            try:
                await self.store.announce(info.id, cause, idempotency=idempotency)
            except AlreadyApplied as exc:  # the key came with an utterance that was fused (or another change)
                answer, replayed = self._replay(exc.record, idempotency, caller).answer, True
        if not replayed:
            said = utterance_part(prepared.utterance, prepared.fused, prepared.reason, prepared.grounding)
            await self._record(info.id, cause, utterance=said, summarised=prepared.fused)
        return Applied(await self.belief(caller, info.id), replayed=replayed, answer=answer)

    # -- vision ---------------------------------------------------------------------------------------------

    async def observe(
        self,
        caller: Caller,
        session_id: str,
        batch: ObservationBatch,
        idempotency: Idempotency | None = None,
        *,
        with_summary: bool = True,
    ) -> Applied[tuple[UpdateResult, Belief | None]]:
        """Fuse one batch of labels or detections; with its summary, or with it made ahead in the background
        for those who watch the session."""
        change = changes.observations(batch, self.settings.max_batch_voxels, caller=caller)
        kind = "labels" if batch.p_target is None else "detections"

        def cause(result: UpdateResult) -> dict[str, Any]:
            counts = {"voxels_updated": result.voxels_updated, "voxels_outside": result.voxels_outside}
            return {"kind": "observations", "batch": kind, **counts}

        stamp = batch.stamp if batch.stamp is not None and math.isfinite(batch.stamp) else None
        change = dataclasses.replace(change, event=lambda r: cause(r) | {"stamp": stamp})
        replayed = False
        try:
            result = await self.store.update(session_id, change, idempotency=idempotency)
        except AlreadyApplied as exc:
            first = self._replay(exc.record, idempotency, caller)
            result = UpdateResult(session_id, first.version, first.voxels_updated, first.voxels_outside)
            replayed = True
        belief = None
        if with_summary:
            if not replayed:
                await self._record(session_id, cause(result) | {"stamp": stamp})
            belief = await self.belief(caller, session_id)
        else:
            if not replayed:
                self._record_soon(session_id, cause(result) | {"stamp": stamp})
            self._summarise_ahead(session_id)
        return Applied((result, belief), replayed=replayed)

    # -- reading the belief ---------------------------------------------------------------------------------

    async def poll(self, caller: Caller, session_id: str, top_k: int) -> SessionInfo:
        """The session's metadata (its version names the belief), noting that someone watches its summary."""
        info = await self._readable(caller, session_id)
        self.summaries.watch(session_id, top_k)
        return info

    async def belief(
        self, caller: Caller, session_id: str, top_k: int = DEFAULT_TOP_K, info: SessionInfo | None = None
    ) -> Belief:
        """The posterior summary of the current version (of `info`'s, when given), computed once per version
        in this process, and once per version fleet-wide where the store shares summaries."""
        if info is None:
            info = await self._readable(caller, session_id)
        return await self._belief(info, top_k)

    async def _belief(self, info: SessionInfo, top_k: int) -> Belief:
        cached = self.summaries.get(info.id, info.created_at, info.version, top_k)
        if cached is not None:
            return cached
        wider = None
        if top_k < RECORD_TOP_K:
            wider = self.summaries.get(info.id, info.created_at, info.version, RECORD_TOP_K)
        if wider is not None:  # the recording's summary of this version: its first top_k voxels are these
            top = wider.summary.top_voxels[:top_k]
            belief = dataclasses.replace(wider, summary=dataclasses.replace(wider.summary, top_voxels=top))
            self.summaries.put(top_k, belief)
            return belief
        stored = await self.store.summary_get(info.id, info.version, summary_options(top_k, info.created_at))
        if stored is not None:
            summary = PosteriorSummary.from_dict(stored)
            belief = Belief(info.id, info.version, info.target_label, summary, info.created_at)
        else:
            session = await self.store.load(info.id)  # may be newer than `info`
            summary = await self.run(session.summary, top_k=top_k)
            options = summary_options(top_k, session.created_at)
            await self.store.summary_put(info.id, session.version, options, summary.to_dict())
            belief = Belief(info.id, session.version, session.target_label, summary, session.created_at)
        self.summaries.put(top_k, belief)
        return belief

    def _summarise_ahead(self, session_id: str) -> None:
        """Summarise the session's new version in the background if someone watches it."""
        top_ks = self.summaries.start_job(session_id)
        if top_ks is not None:
            self._in_background(self._ahead_job(session_id, top_ks))

    def _in_background(self, job: Coroutine[Any, Any, None]) -> None:
        """Run a job after the answer, cancelled by `close`."""
        task = asyncio.get_running_loop().create_task(job)
        self._ahead.add(task)
        task.add_done_callback(self._ahead.discard)

    async def _ahead_job(self, session_id: str, top_ks: list[int]) -> None:
        while True:
            try:
                info = await self.store.head(session_id)
                for top_k in top_ks:
                    await self._belief(info, top_k)
            except VLMapError as exc:  # e.g. the session was deleted meanwhile; the next poll will say so
                log.info("background summary of %s skipped: %s", session_id, exc)
            if not self.summaries.end_job(session_id):
                return

    # -- the recording --------------------------------------------------------------------------------------

    async def _record(
        self,
        session_id: str,
        cause: Mapping[str, Any],
        *,
        utterance: dict[str, Any] | None = None,
        scene_graph: SceneGraph | None = None,
        summarised: bool = True,
    ) -> None:
        """Add the session's current version to its recording (`app.sessions.recording`): with its summary
        unless `summarised` is False (an utterance that changed nothing). A failure is logged, never raised:
        the update it follows is done."""
        limit = self.settings.recording_frames
        if limit <= 0:
            return
        try:
            info = await self.store.head(session_id)
            version, target, at, summary = info.version, info.target_label, time.time(), None
            if summarised:
                belief = await self._belief(info, RECORD_TOP_K)
                version, target, at = belief.version, belief.target_label, info.updated_at
                summary = belief.summary.to_dict()
            graph = scene_graph_part(scene_graph) if scene_graph is not None else None
            frame = Frame(version, at, dict(cause), target, summary, utterance, graph)
            await self.store.record(session_id, frame.pack(), limit)
        except VLMapError as exc:
            log.warning("recording of %s skipped a version: %s", session_id, exc)

    def _record_soon(self, session_id: str, cause: Mapping[str, Any]) -> None:
        """Record the session's latest version off the request path, at most once per `recording_interval_s`:
        batches that arrive meanwhile share the frame that follows them (its cause is the last one's)."""
        if self.settings.recording_frames <= 0:
            return
        pending = session_id in self._recording_due
        self._recording_due[session_id] = cause
        if pending:
            return
        last = self._recorded_at.get(session_id)
        wait = 0.0 if last is None else last + self.settings.recording_interval_s - time.monotonic()
        if wait <= 0:
            self._record_due(session_id)
        else:  # a timer, not a sleeping task, so that closing has nothing to wait for
            self._recording_timers[session_id] = asyncio.get_running_loop().call_later(
                wait, self._record_due, session_id
            )

    def _record_due(self, session_id: str) -> None:
        self._recording_timers.pop(session_id, None)
        cause = self._recording_due.pop(session_id)
        now = time.monotonic()
        self._recorded_at[session_id] = now
        self._recorded_at.move_to_end(session_id)
        # Only sessions recorded within the interval need remembering: the others may be recorded at once.
        while next(iter(self._recorded_at.values())) < now - self.settings.recording_interval_s:
            self._recorded_at.popitem(last=False)
        self._in_background(self._record(session_id, cause))

    async def recording(self, caller: Caller, session_id: str, after: int | None = None) -> list[Frame]:
        """The session's recorded frames, one per version, oldest first: those after version `after`, if
        given (and the unfused utterances at it, which came after its frame)."""
        await self._readable(caller, session_id)
        frames = merged([Frame.unpack(raw) for raw in await self.store.recording(session_id)])
        if after is None:
            return frames
        return [f for f in frames if f.version > after or (f.summary is None and f.version == after)]

    async def top_down(self, caller: Caller, session_id: str) -> TopDown:
        """The belief seen from above (`column_mass`), computed once per version in this process: several
        dashboards showing a session share it (the latest version of the last `TOP_DOWN_SESSIONS` sessions
        asked for is kept)."""
        info = await self._readable(caller, session_id)
        cached = self._top_downs.get(session_id)
        if cached is None or (cached.version, cached.created_at) != (info.version, info.created_at):
            session = await self.store.load(session_id)  # may be newer than `info`
            mass = await self.run(column_mass, session.grid, session.belief.lang, session.belief.vis)
            cached = TopDown(session_id, session.version, session.grid, mass, session.created_at)
            self._top_downs[session_id] = cached
        self._top_downs.move_to_end(session_id)
        while len(self._top_downs) > TOP_DOWN_SESSIONS:
            self._top_downs.popitem(last=False)
        return cached

    async def scene_graph(self, caller: Caller, session_id: str) -> SceneGraph:
        """The scene graph the session grounds utterances in (its latest replacement)."""
        info, scene_graph = await self.store.head_and_scene_graph(session_id)
        caller.require_read(info.robot_id)
        return scene_graph

    async def utterances(self, caller: Caller, session_id: str) -> UtteranceLog:
        """The utterance events among the session's retained events (its last `events_history`, of every
        kind), oldest first."""
        await self._readable(caller, session_id)
        events = await self.store.events.retained(session_id)
        said = tuple(event for event in events if event.kind == "utterance")
        return UtteranceLog(session_id, said, complete=bool(events) and events[0].kind == "created")

    async def grid(self, caller: Caller, session_id: str) -> Session:
        """A consistent copy of the whole belief (and its layers), for a download."""
        await self._readable(caller, session_id)
        return await self.store.load(session_id)

    # -- the push stream ------------------------------------------------------------------------------------

    async def session_events(
        self, caller: Caller, session_id: str, last_event_id: str | None = None
    ) -> EventStream:
        """A stream of the session's events (`app.sessions.events`): those after `last_event_id` when the
        history still holds them, else a `sync`, then the live ones; it ends after the session's deletion."""
        await self._readable(caller, session_id)
        events = self.store.events
        sub = await self.events.session(session_id)

        async def alive() -> bool:
            try:
                await self.store.head(session_id)
            except NotFound:
                return False
            except VLMapError:  # an outage: the session may well be there
                return True
            return True

        follow = SessionFollow(events, session_id, "", alive)

        async def resync(reason: Literal["start", "expired", "gap"]) -> Sync:
            tail = await events.tail(session_id)
            follow.at(tail)
            info = await self.store.head(session_id)
            fields = {"session_id": session_id, "robot_id": info.robot_id, "version": info.version}
            fields["summary_url"] = f"/v1/sessions/{session_id}/belief"
            return Sync(reason, f"{session_id}:{tail}", fields)

        try:
            replayed = None
            if last_event_id is not None:
                named, _, after = last_event_id.partition(":")
                if named == session_id and events.order(after) is not None:
                    replayed = await events.replay(session_id, after)
                    follow.at(after)
            first: list[Any] = list(replayed) if replayed is not None else []
            if replayed is None:
                first = [await resync("start" if last_event_id is None else "expired")]
        except BaseException:
            sub.end()
            raise
        return EventStream(sub, first, resync=functools.partial(resync, "gap"), session=follow)

    async def fleet_events(
        self, caller: Caller, robot_id: str | None = None, last_event_id: str | None = None
    ) -> EventStream:
        """A stream of the events of every session the caller may read (of `robot_id`'s only, if given):
        those after `last_event_id` that this process still holds, else a `sync`, then the live ones."""
        if robot_id is not None:
            caller.require_read(robot_id)

        def accepts(event: StoredEvent) -> bool:
            return caller.can_read(event.robot_id)

        sub, replayed, last = await self.events.fleet(accepts, robot_id, last_event_id)
        query = f"?robot_id={robot_id}" if robot_id is not None else ""
        fields: dict[str, Any] = {"robot_id": robot_id} if robot_id is not None else {}
        fields["sessions_url"] = f"/v1/sessions{query}"
        first: list[Any] = list(replayed) if replayed is not None else []
        if replayed is None:
            first = [Sync("start" if last_event_id is None else "expired", last, fields)]

        async def resync() -> Sync:
            return Sync("gap", None, fields)

        return EventStream(sub, first, resync=resync)

    async def close(self) -> None:
        """Stop summarising and recording ahead (a job running now is cancelled) and end the event streams."""
        for timer in self._recording_timers.values():
            timer.cancel()
        for task in list(self._ahead):
            task.cancel()
        await asyncio.gather(*self._ahead, return_exceptions=True)
        await self.events.close()
