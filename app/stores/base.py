"""The session-store interface and what both stores share (id rules, binary codecs).

Every store method is safe to call from many threads at once (the API calls stores from a threadpool),
and updates to one session are serialised, so concurrent updates add up exactly as if applied one after
the other. Versions start at 0 on creation and grow by one with every acknowledged update (utterance,
observation batch, detection batch, scene-graph replacement, target-label change).

A session created with target label "" has no target class yet: `apply_observations` raises `Conflict`
until `set_target_label` names one; `apply_detections` needs no class.

Expiry: a session expires `ttl_s` seconds after its last write (creation or update); reads do not extend
it. An expired session behaves as deleted (`NotFound`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from app.belief.session import BeliefState, Session, SessionInfo, UpdateResult
from app.belief.summary import PosteriorSummary
from app.errors import InvalidInput
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph

#: Default idle lifetime of a session (seconds): a day without updates.
DEFAULT_TTL_S = 24 * 3600.0

# Ids become file names (memory store) and key parts (Redis): letters, digits, ".", "_", "-"; no leading dot.
_SESSION_ID = re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9._\-]{0,127}")

#: Called with a session's robot id before an update changes it; raises to refuse (e.g. `Forbidden`).
Authorize = Callable[[str], None]


@runtime_checkable
class SessionStore(Protocol):
    """Where sessions live between requests; `MemorySessionStore` and `RedisSessionStore` implement it."""

    def create(self, session: Session) -> SessionInfo:
        """Store a new session (its current layers and version included); InvalidInput if the id exists."""
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

    def delete(self, session_id: str) -> None:
        """Remove a session; NotFound if absent."""
        ...

    def replace_scene_graph(self, session_id: str, scene_graph: SceneGraph) -> int:
        """Swap the scene graph (the grid and the layers stay); returns the new version."""
        ...

    def set_target_label(self, session_id: str, label: str) -> int:
        """Name the target class (`app.belief.session.check_target_label`); returns the new version."""
        ...

    def apply_utterance(self, session_id: str, mixture: GaussianMixture) -> UpdateResult:
        """Fuse one utterance's language mixture (fusion equation (3))."""
        ...

    def apply_observations(
        self,
        session_id: str,
        labels: Sequence[int] | Sequence[str] | np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        authorize: Authorize | None = None,
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
    ) -> UpdateResult:
        """Fuse detector probabilities (fusion equation (5)); the voxels and `authorize` as in
        `apply_observations`."""
        ...

    async def apply_observations_async(
        self,
        session_id: str,
        labels: Sequence[int] | Sequence[str] | np.ndarray,
        *,
        points: np.ndarray | None = None,
        flat_idx: np.ndarray | None = None,
        voxels: np.ndarray | None = None,
        tp: float | None = None,
        fp: float | None = None,
        authorize: Authorize | None = None,
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
