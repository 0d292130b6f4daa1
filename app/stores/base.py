"""The session-store interface and what both stores share (id rules, binary codecs).

Every store method is safe to call from many threads at once (the API calls stores from a threadpool),
and updates to one session are serialised, so concurrent updates add up exactly as if applied one after
the other. Versions start at 0 on creation and grow by one with every acknowledged update (utterance,
observation batch, detection batch, scene-graph replacement, target-label change).

A session created with target label "" has no target class yet: `apply_observations` raises `Conflict`
until `set_target_label` names one; `apply_detections` needs no class.

Expiry: a session expires `ttl_s` seconds after its last write (creation or update); reads do not extend
it. An expired session behaves as deleted (`NotFound`).

Idempotency: every change takes an optional `Idempotency` (a client's Idempotency-Key and the fingerprint
of its request). The session remembers the key with the change, atomically (`IdempotencyRecord`: in the
same log record or commit), for `idempotency_window_s` and at most `idempotency_keys` keys; a change that
brings a remembered key changes nothing and raises `AlreadyApplied` with the record, so that a retry of an
update whose answer was lost (a timeout, a replica killed, a Redis failover) is applied once. A deleted
session's delete record stays for the window.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import msgpack
import numpy as np

from app.belief.session import BeliefState, Labels, Session, SessionInfo, UpdateResult
from app.belief.summary import PosteriorSummary
from app.errors import AlreadyApplied, InvalidInput, LimitExceeded
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph

#: Default idle lifetime of a session (seconds): a day without updates.
DEFAULT_TTL_S = 24 * 3600.0

# Ids become file names (memory store) and key parts (Redis): letters, digits, ".", "_", "-"; no leading dot.
_SESSION_ID = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9._\-]{0,127}")

#: Called with a session's robot id before an update changes it; raises to refuse (e.g. `Forbidden`).
Authorize = Callable[[str], None]

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
        return msgpack.packb([*fields, self.at, self.commit, self.robot_id], use_bin_type=True)

    @classmethod
    def unpack(cls, data: bytes) -> IdempotencyRecord:
        return cls(*msgpack.unpackb(data, raw=False))

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
        if record is not None and now - record.at <= self.window_s:
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


@runtime_checkable
class SessionStore(Protocol):
    """Where sessions live between requests; `MemorySessionStore` and `RedisSessionStore` implement it."""

    def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        """Store a new session (its current layers and version included); InvalidInput if the id exists,
        LimitExceeded("max_sessions_per_robot") if its robot has `max_per_robot` live sessions already
        (checked atomically with the creation)."""
        ...

    def get(self, session_id: str) -> Session:
        """A copy of the whole session, layers included; NotFound if absent or expired."""
        ...

    def info(self, session_id: str) -> SessionInfo:
        """The session's metadata (grid, label map, sensor model, version) without reading its layers."""
        ...

    async def owner_and_version(self, session_id: str) -> tuple[str, int]:
        """The session's robot id and current version, on the event loop (no worker thread): what a poll
        needs to check access and its ETag. NotFound if absent or expired."""
        ...

    def scene_graph(self, session_id: str) -> SceneGraph:
        """The session's current scene graph, without reading its layers."""
        ...

    def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        """Live sessions (of one robot, if given), oldest first."""
        ...

    def delete(
        self, session_id: str, *, authorize: Authorize | None = None, idempotency: Idempotency | None = None
    ) -> None:
        """Remove a session; NotFound if absent. `authorize(robot_id)` as in `apply_observations`."""
        ...

    def replace_scene_graph(
        self, session_id: str, scene_graph: SceneGraph, *, idempotency: Idempotency | None = None
    ) -> int:
        """Swap the scene graph (the grid and the layers stay); returns the new version."""
        ...

    def set_target_label(self, session_id: str, label: str) -> int:
        """Name the target class (`app.belief.session.check_target_label`); returns the new version."""
        ...

    def apply_utterance(
        self,
        session_id: str,
        mixture: GaussianMixture,
        *,
        target_label: str | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse one utterance's language mixture (fusion equation (3)); `target_label`, when given, names the
        target class in the same update if the session has none yet."""
        ...

    def apply_observations(
        self,
        session_id: str,
        labels: Labels,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        authorize: Authorize | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse labelled voxels (fusion equation (4)); tp/fp override the session's sensor model.

        The voxels are given as exactly one of points (n, 3), flat indices (n,) or integer voxel coordinates
        (n, 3); points and coordinates outside the grid are counted in `voxels_outside`, not fused.
        `authorize(robot_id)`, if given, is called with the owner of the state the update is computed from,
        before anything changes; what it raises refuses the update. Conflict while the session's target
        label is "" (unknown).
        """
        ...

    def apply_detections(
        self,
        session_id: str,
        p_target: np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        prior: float = 0.5,
        authorize: Authorize | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """Fuse detector probabilities (fusion equation (5)); the voxels and `authorize` as in
        `apply_observations`."""
        ...

    async def apply_observations_async(
        self,
        session_id: str,
        labels: Labels,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        authorize: Authorize | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """`apply_observations` for a caller on an event loop, which it never blocks on I/O or a lock."""
        ...

    async def apply_detections_async(
        self,
        session_id: str,
        p_target: np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        prior: float = 0.5,
        authorize: Authorize | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        """`apply_detections` for a caller on an event loop, which it never blocks on I/O or a lock."""
        ...

    def read_layers(self, session_id: str) -> BeliefState:
        """A consistent copy of the belief layers and their version."""
        ...

    def summary(self, session_id: str, **kwargs: Any) -> PosteriorSummary:
        """`app.belief.summary.summarize` of one consistent state of the session, with its `version`."""
        ...

    def purge_expired(self) -> int:
        """Drop expired sessions now; returns how many."""
        ...

    def close(self) -> None: ...


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
