"""The session-store interface and what both stores share (id rules, binary codecs, the named deltas).

A store keeps sessions and applies *changes* to them; it does no belief arithmetic of its own beyond
applying a `Delta` with `app.belief.fusion`'s functions. The use-cases (`app.sessions`) compute each delta
as a pure function of a `SessionView` (`Change`), so the fusion of an utterance or a batch is written once,
whatever the store. Versions start at 0 on creation and grow by one with every acknowledged update.

Expiry: a session expires `ttl_s` seconds after its last write (creation or update); reads do not extend
it. An expired session behaves as deleted (`NotFound`).

Idempotency: every change takes an optional `Idempotency` (a client's Idempotency-Key and the fingerprint
of its request). The session remembers the key with the change, atomically (`IdempotencyRecord`: in the
same log record or commit), for `idempotency_window_s` and at most `idempotency_keys` keys; a change that
brings a remembered key changes nothing and raises `AlreadyApplied` with the record (which names the
session's owner, so that the caller's access is checked before the first answer is given again), so that
a retry of an update whose answer was lost (a timeout, a replica killed, a Redis failover) is applied
once. A deleted session's delete record stays for the window.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import msgpack
import numpy as np

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import IncrementBatch, ObservationModel, Session, SessionInfo, UpdateResult
from app.errors import AlreadyApplied, InvalidInput, LimitExceeded
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph
from app.stores.events import EventLog

#: Default idle lifetime of a session (seconds): a day without updates.
DEFAULT_TTL_S = 24 * 3600.0

# Ids become file names (memory store) and key parts (Redis): letters, digits, ".", "_", "-"; no leading dot.
_SESSION_ID = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9._\-]{0,127}")

#: Default window and count of the Idempotency-Keys a session remembers.
DEFAULT_IDEMPOTENCY_WINDOW_S = 3600.0
DEFAULT_IDEMPOTENCY_KEYS = 1000


@dataclass(frozen=True)
class Idempotency:
    """An update's Idempotency-Key, the fingerprint of the request that carried it, and what the caller needs,
    beyond the update's result, to give its first answer again (`answer`, opaque to the store)."""

    key: str
    fingerprint: str
    answer: bytes = b""


@dataclass(frozen=True)
class IdempotencyRecord:
    """What a session remembers of an update made under an Idempotency-Key (`AlreadyApplied.record`)."""

    fingerprint: str
    version: int
    voxels_updated: int = 0
    voxels_outside: int = 0
    answer: bytes = b""
    at: float = 0.0  # when it was applied (store clock)
    commit: str = ""  # the commit that wrote it (a Redis update recognises its own resent commit by it)
    robot_id: str = ""  # the session's owner (a deleted session's record is checked against it)

    def pack(self) -> bytes:
        fields = [self.fingerprint, self.version, self.voxels_updated, self.voxels_outside, self.answer]
        packed: bytes = msgpack.packb([*fields, self.at, self.commit, self.robot_id], use_bin_type=True)
        return packed

    @classmethod
    def unpack(cls, data: bytes) -> IdempotencyRecord:
        return cls(*msgpack.unpackb(data, raw=False))

    def remembered(self, now: float, window_s: float) -> bool:
        """Whether the key is still remembered at `now`: applied at most `window_s` before."""
        return now - self.at <= window_s

    @classmethod
    def of(
        cls, idempotency: Idempotency, result: UpdateResult, at: float, commit: str = "", robot_id: str = ""
    ) -> IdempotencyRecord:
        return cls(
            idempotency.fingerprint,
            result.version,
            result.voxels_updated,
            result.voxels_outside,
            idempotency.answer,
            at,
            commit,
            robot_id,
        )


class IdempotencyLog:
    """The Idempotency-Keys one session remembers (memory store): the last `max_keys`, none older than
    `window_s`. Not thread-safe: the session's lock guards it."""

    def __init__(self, window_s: float, max_keys: int) -> None:
        self.window_s = window_s
        self.max_keys = max_keys
        self._records: OrderedDict[str, IdempotencyRecord] = OrderedDict()

    def check(self, idempotency: Idempotency | None, now: float) -> None:
        """AlreadyApplied if the key is remembered."""
        if idempotency is None:
            return
        record = self._records.get(idempotency.key)
        if record is not None and record.remembered(now, self.window_s):
            raise AlreadyApplied(record)

    def add(self, key: str, record: IdempotencyRecord) -> None:
        self._records.pop(key, None)
        self._records[key] = record
        while self._records and (
            len(self._records) > self.max_keys
            or record.at - next(iter(self._records.values())).at > self.window_s
        ):
            self._records.popitem(last=False)

    def items(self) -> list[tuple[str, IdempotencyRecord]]:
        return list(self._records.items())

    def live(self, now: float) -> list[tuple[str, IdempotencyRecord]]:
        """The keys still remembered at `now` (a deleted session's tombstone keeps those)."""
        return [(k, r) for k, r in self._records.items() if r.remembered(now, self.window_s)]


@dataclass(frozen=True)
class LanguageDelta:
    """An utterance's term of the language layer: its mixture (float64, what a log keeps and replays) and
    equation (3)'s increment on the session's grid, `app.belief.session.language_log_likelihood` at the
    session's span (relative to its best voxel: the layer is defined up to a constant)."""

    mixture: GaussianMixture
    log_likelihood: np.ndarray  # (N,) float32, max 0


@dataclass(frozen=True)
class MetaDelta:
    """A change of what turns messages into increments: the target class, the scene graph, and the mapped
    look-alikes under them (`app.belief.session.mapped_look_alikes`; stores that keep them write them)."""

    target_label: str | None = None
    scene_graph: SceneGraph | None = None
    look_alikes: np.ndarray | None = None


@dataclass(frozen=True)
class Delta:
    """What one update changes, in named parts; a store applies them in one atomic step and one version."""

    language: LanguageDelta | None = None
    vision: IncrementBatch | None = None
    meta: MetaDelta | None = None

    def result(self, session_id: str, version: int, n_voxels: int) -> UpdateResult:
        """The update's answer: voxels the vision part touched (all of them for a language term)."""
        if self.language is not None:
            return UpdateResult(session_id, version, n_voxels)
        if self.vision is not None:
            return UpdateResult(session_id, version, len(self.vision.flat_idx), self.vision.n_outside)
        return UpdateResult(session_id, version, 0)


class SessionView(Protocol):
    """A session's current state as a store hands it to a `Change` (read-only; its parts load lazily)."""

    @property
    def id(self) -> str: ...

    @property
    def robot_id(self) -> str: ...

    @property
    def version(self) -> int: ...

    @property
    def target_label(self) -> str: ...

    @property
    def grid(self) -> VoxelGrid: ...

    @property
    def label_map(self) -> Mapping[int, str]: ...

    def scene_graph(self) -> SceneGraph: ...

    def observer(self) -> ObservationModel:
        """The session's observation model (its mapped look-alikes included)."""
        ...


@dataclass(frozen=True)
class Change:
    """An update: `compute(view) -> Delta`, a pure function of the session's current state (it may raise to
    refuse the update, which then changes nothing; it may run more than once when a concurrent writer
    came first). `inline`: cheap enough to compute on the event loop when the store holds the state in
    memory and needs no I/O to apply it. `event`: the `cause` of the version's event
    (`app.stores.events`) from the update's result; without it the event says {"kind": "update"}."""

    compute: Callable[[SessionView], Delta]
    inline: bool = False
    event: Callable[[UpdateResult], Mapping[str, Any]] | None = None


@runtime_checkable
class SessionStore(Protocol):
    """Where sessions live between requests; `MemorySessionStore` and `RedisSessionStore` implement it.

    Every method may be called from many tasks at once; the store decides what runs on the event loop and
    what on a worker thread (I/O waits, lock waits, work on whole layers)."""

    async def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        """Store a new session (its current layers and version included); InvalidInput if the id exists,
        LimitExceeded("max_sessions_per_robot") if its robot has `max_per_robot` live sessions already
        (checked atomically with the creation)."""
        ...

    async def delete(self, session_id: str, *, idempotency: Idempotency | None = None) -> None:
        """Remove a session; NotFound if absent (AlreadyApplied if a deleted session remembers the key)."""
        ...

    async def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        """Live sessions (of one robot, if given), oldest first."""
        ...

    async def head(self, session_id: str) -> SessionInfo:
        """The session's metadata (robot, version, last update, grid, target, label map), without its scene
        graph or layers: what access checks and ETags need. NotFound if absent or expired."""
        ...

    async def head_and_scene_graph(self, session_id: str) -> tuple[SessionInfo, SceneGraph]:
        """`head` and the session's current scene graph, read together (one version's), without its layers:
        what grounding an utterance needs."""
        ...

    async def load(self, session_id: str) -> Session:
        """A consistent copy of the whole session, layers and version included (the caller's to keep)."""
        ...

    async def summary_get(self, session_id: str, version: int, options: str) -> dict[str, Any] | None:
        """A summary (`PosteriorSummary.to_dict`) of this version with these options that some process put,
        if the store keeps them (shared by replicas); None otherwise."""
        ...

    async def summary_put(self, session_id: str, version: int, options: str, summary: dict[str, Any]) -> None:
        """Offer a version's summary to other processes (a store without sharing drops it)."""
        ...

    async def update(
        self, session_id: str, change: Change, *, idempotency: Idempotency | None = None
    ) -> UpdateResult:
        """Apply `change.compute(view)` to the session's current state, atomically, as the next version.

        Updates of one session are serialised: concurrent ones add up as if applied one after the other.
        A remembered Idempotency-Key changes nothing and raises `AlreadyApplied` (module docstring)."""
        ...

    async def purge_expired(self) -> int:
        """Drop expired sessions now; returns how many."""
        ...

    async def record(self, session_id: str, frame: bytes, limit: int) -> None:
        """Append a packed frame to the session's recording, thinned past `limit` frames
        (`app.sessions.recording.thin`); nothing when the session is gone. The log goes with the session."""
        ...

    async def recording(self, session_id: str) -> tuple[bytes, ...]:
        """The session's recorded frames, oldest first (empty when none or gone)."""
        ...

    @property
    def events(self) -> EventLog:
        """The sessions' events: one per version (written with it, atomically), per deletion and per
        `announce`."""
        ...

    async def announce(
        self, session_id: str, cause: Mapping[str, Any], *, idempotency: Idempotency | None = None
    ) -> None:
        """An event for the session's current version that changes nothing (an utterance not fused), in
        order with its updates; NotFound if absent, AlreadyApplied (and no event) if the session remembers
        the key: an announcement remembers none, but its key must not be one an update used."""
        ...

    def close(self) -> None: ...


def next_language_layer(session: Session, language: LanguageDelta) -> np.ndarray:
    """The session's language layer after the term (equation (3), shifted and clamped), as a new array:
    computed before a change is logged, so that a logged change always applies."""
    lang = session.belief.lang.copy()
    fusion.apply_language(lang, language.log_likelihood, session.belief.limits.lang_span)
    return lang


def apply_delta(session: Session, delta: Delta, lang: np.ndarray | None, now: float) -> None:
    """Apply a delta to a session held in memory, as one version (`lang`: its `next_language_layer`)."""
    belief = session.belief
    if lang is not None:
        belief.lang = lang
    if delta.meta is not None:
        if delta.meta.scene_graph is not None:
            session.replace_scene_graph(delta.meta.scene_graph)
        if delta.meta.target_label is not None:
            session.set_target_label(delta.meta.target_label)
    if delta.vision is not None:
        limits = belief.limits
        fusion.apply_increments(
            belief.vis, delta.vision.flat_idx, delta.vision.increments, limits.vis_min, limits.vis_max
        )
    belief.version += 1
    session.updated_at = now


def session_limit_error(robot_id: str, limit: int) -> LimitExceeded:
    msg = f"robot {robot_id!r} already has {limit} sessions; delete one first"
    return LimitExceeded(msg, limit_name="max_sessions_per_robot")


def check_session_id(session_id: str) -> None:
    if not isinstance(session_id, str) or not _SESSION_ID.fullmatch(session_id):
        msg = "session ids are 1-128 letters, digits, '.', '_' or '-', not starting with '.'"
        raise InvalidInput(msg, "id")


def float64_mixture(mixture: GaussianMixture) -> GaussianMixture:
    """The mixture in float64: what the log stores, so that live and replayed updates are identical."""
    return GaussianMixture(
        weights=np.asarray(mixture.weights, dtype=np.float64),
        means=np.asarray(mixture.means, dtype=np.float64),
        covariances=np.asarray(mixture.covariances, dtype=np.float64),
        box_weights=np.asarray(mixture.box_weights, dtype=np.float64),
        box_lows=np.asarray(mixture.box_lows, dtype=np.float64),
        box_highs=np.asarray(mixture.box_highs, dtype=np.float64),
    )


def pack_array(array: np.ndarray) -> dict[str, Any]:
    """A numpy array as msgpack-ready {dtype, shape, data} (little-endian bytes)."""
    arr = np.ascontiguousarray(array)
    arr = arr.astype(arr.dtype.newbyteorder("<"), copy=False)
    return {"dtype": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}


def unpack_array(packed: dict[str, Any]) -> np.ndarray:
    """Inverse of `pack_array` (a writable copy in native byte order)."""
    arr = np.frombuffer(packed["data"], dtype=np.dtype(packed["dtype"])).reshape(packed["shape"])
    return arr.astype(arr.dtype.newbyteorder("="))


def pack_mixture(mixture: GaussianMixture) -> dict[str, Any]:
    m = float64_mixture(mixture)
    packed = {
        "weights": pack_array(m.weights),
        "means": pack_array(m.means),
        "covariances": pack_array(m.covariances),
    }
    if len(m.box_weights):
        packed |= {
            "box_weights": pack_array(m.box_weights),
            "box_lows": pack_array(m.box_lows),
            "box_highs": pack_array(m.box_highs),
        }
    return packed


def unpack_mixture(packed: dict[str, Any]) -> GaussianMixture:
    """The mixture exactly as packed (no re-normalisation), so replaying it gives the same bits; a record
    written before mixtures had uniform boxes has none."""
    boxes = {}
    if "box_weights" in packed:
        boxes = {key: unpack_array(packed[key]) for key in ("box_weights", "box_lows", "box_highs")}
    return GaussianMixture(
        weights=unpack_array(packed["weights"]),
        means=unpack_array(packed["means"]),
        covariances=unpack_array(packed["covariances"]),
        **boxes,
    )


def compact_indices(flat_idx: np.ndarray, n_voxels: int) -> np.ndarray:
    """Voxel indices in the smallest integer type that holds the grid (int32 below 2^31 voxels)."""
    return np.asarray(flat_idx, dtype=np.int32 if n_voxels < 2**31 else np.int64)
