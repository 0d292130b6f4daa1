"""Sessions in Redis, shared by every replica of the service.

Keys of session S (the hash tag {S} keeps them in one cluster slot):

    <prefix>:s:{S}:meta   hash: static (msgpack: robot, grid, target, label map, sensor model, limits,
                          creation time; only the target ever changes), sg (scene graph JSON), version,
                          updated_at, look_alikes (int64 flat indices of the mapped objects of the
                          target's class, `mapped_look_alikes`, rewritten with sg or the target),
                          block_voxels (the layers' block size); `head` and `list` read this hash alone
    <prefix>:s:{S}:lang   hash: block number -> float32 bytes of the session's `block_voxels` voxels (the meta
                          hash's field, fixed at creation; absent blocks are zeros)
    <prefix>:s:{S}:vis    hash: the same for the vision layer
    <prefix>:s:{S}:lock   the update lock
    <prefix>:s:{S}:summary  hash: summary options -> msgpack {version, summary}, the last summary computed
                          by any replica: dashboards polling through several replicas summarise each
                          version once, fleet-wide (a reader uses it only if its version is current)
    <prefix>:s:{S}:idem   hash: idempotency key -> `IdempotencyRecord` of the commit made under it: a
                          client's Idempotency-Key ("k:<key>"), or the commit's own id ("c:<id>")
    <prefix>:s:{S}:idem_at  sorted set: the idem hash's client keys scored by when they were written (ms)
    <prefix>:s:{S}:commits  sorted set: the same for its commit ids, bounded apart: keyless commits never push
                          a client's key out
    <prefix>:s:{S}:events  stream: the session's events, one per version, written by the script that
                          commits it (`app.stores.redis_events`), each also published on <prefix>:events
    <prefix>:sessions, <prefix>:robot:<R>   sorted sets of session ids scored by expiry time (ms), as last
                          recorded (a hint: `list` checks every id against its meta hash)

Redis Cluster: the store speaks to a cluster when the URL's server is one (`INFO cluster`), through
redis-py's cluster clients, unchanged otherwise. Every script touches only keys of one session (one hash
tag, so one slot) or one index; an index is written apart from the session, after it.

No lost updates across replicas: an update reads the meta hash, computes the change's delta from it,
reads the blocks the delta changes, and commits with one script call (`COMMIT_SCRIPT`) that writes only
if the session is still at the version it read and no other writer holds the session's lock; else it
reads again. Every update is then two reads and one write round trip (none but the write from the
mirror), and one fsync on an `appendfsync always` Redis (a lock taken and released around each update
would cost two more writes, each fsynced). A writer that keeps losing (a slow utterance among fast
observation streams) takes the session's lock (SET NX PX with a random token), which makes every other
writer's commit fail until it is done. An observation batch reads and writes only the vision blocks its
voxels fall in.

The mirror: each store keeps in memory the last state of each session it read in full or committed
(`app.stores.redis_mirror`), named by its (version, updated_at). A replica that a robot's connection stays
with then updates without the read (it computes from the mirror and commits on the condition that the
stored state still has that name; when another replica wrote meanwhile, the commit fails and the update
reads), and summarises a version it wrote without reading the whole belief back. The mirror is never
needed to be right: the commit's condition is checked in Redis, and a state is taken from it only under
its name; a change that refuses the mirrored state is refused only once a read shows that Redis holds
that state.
An inline change (`Change.inline`: a camera view's batch) from the mirror is computed on the caller's
event loop and committed through that loop's `redis.asyncio` client: it needs no read, so no worker
thread; an update that must read runs on one.

Expiry: every write sets the same absolute expiry (PEXPIREAT now + ttl) on all of the session's keys;
Redis drops the keys. The index scores follow when they lag by more than a tenth of the ttl (each
process refreshes a session's after its commits), so a live session's score is at most `_INDEX_LAG` of
the ttl behind its expiry; listings, the per-robot count and purges allow for that, and prune ids whose
session is gone.

Exactly once: a commit carries an idempotency key (the client's Idempotency-Key, else a fresh commit id)
and writes its record in the same script call. A commit sent again (redis-py resends a command whose reply
timed out or whose connection dropped, and a lost reply is resent here too) finds its record and is told
it landed; another request with a client's key finds the key's record and changes nothing
(`AlreadyApplied`). The records of a session are bounded in number and age (`idempotency_keys`,
`idempotency_window_s`), the client's keys and the commit ids each on their own; a delete leaves the
session's client keys and its own (a tombstone) for the window, so that a retry of the session's creation
is not applied again.

Locks: a lock holder renews its lock every third of `lock_ttl_s` while it works, so the ttl can be short
(3 s): a holder that died (kill -9 mid-update) leaves a lock that other writers wait out within that ttl.

Any Redis failure (connection refused or lost, timeout, out of memory) raises `StoreUnavailable`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
import math
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from typing import Any, ParamSpec, TypeVar

import anyio.to_thread
import msgpack
import numpy as np

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import (
    ObservationModel,
    SensorModel,
    Session,
    SessionInfo,
    UpdateResult,
    mapped_look_alikes,
)
from app.errors import AlreadyApplied, InvalidInput, NotFound, StoreUnavailable
from app.scene_graph.model import SceneGraph
from app.stores.base import (
    DEFAULT_IDEMPOTENCY_KEYS,
    DEFAULT_IDEMPOTENCY_WINDOW_S,
    DEFAULT_TTL_S,
    Change,
    Delta,
    Idempotency,
    IdempotencyRecord,
    check_session_id,
    session_limit_error,
)
from app.stores.events import describe, event_parts
from app.stores.redis_events import DELETED_STREAM_MS, RedisEventLog
from app.stores.redis_mirror import (
    Mirror,
    Mirrored,
    PartWrites,
    Stamp,
    assemble_layer,
    layer_blocks,
    n_blocks,
)
from app.stores.redis_scripts import (
    ANNOUNCE_SCRIPT,
    COMMIT_SCRIPT,
    CREATE_SCRIPT,
    DELETE_SCRIPT,
    RECORD_SCRIPT,
    RELEASE_SCRIPT,
    RENEW_SCRIPT,
    RESERVE_SCRIPT,
)

#: Voxels per stored block of a new session: 4 kB of float32. A camera's 10k-voxel batch in a 163k-voxel room
#: touches 160 kB of 1024-voxel blocks, against 550 kB of 65,536-voxel blocks: each update
#: reads, rewrites and (on an `appendfsync always` Redis) fsyncs that much.
DEFAULT_BLOCK_VOXELS = 1 << 10
#: The block size of sessions stored before the meta hash recorded one.
LEGACY_BLOCK_VOXELS = 1 << 16
#: How long a session's lock outlives its holder's last renewal (seconds): what a writer waits at most when
#: the holder died (a live holder renews it every third of this).
DEFAULT_LOCK_TTL_S = 3.0
#: How long an update waits for a session's lock before giving up with StoreUnavailable (seconds).
DEFAULT_LOCK_WAIT_S = 10.0
#: Commits retried under the lock (only if the lock expired under a slow holder and another writer won).
_MAX_LOCKED_ATTEMPTS = 20

#: Optimistic attempts before an update takes the session's lock.
_OPTIMISTIC_ATTEMPTS = 3
#: Bytes of layers the mirror holds (the least recently used sessions go first): 2 x 4 bytes per voxel,
#: 1.3 MB for a 163k-voxel room.
DEFAULT_MIRROR_BYTES = 256 << 20

#: How far (a share of the ttl) a live session's index score may lag behind its expiry.
_INDEX_LAG = 0.1
#: How long a creation's reservation in its robot's index lasts before the creation makes it its expiry
#: (seconds): a process that dies between the two leaves an entry that stops counting after this.
_RESERVATION_S = 60.0
#: Sessions whose index scores this process remembers (to refresh them only when they lag).
_INDEXED_SESSIONS = 1 << 16

log = logging.getLogger(__name__)

P = ParamSpec("P")
R = TypeVar("R")
#: Hashes an update writes: key -> {field: value}.
Writes = dict[str, dict[str, Any]]


def _unavailable(exc: Exception) -> StoreUnavailable:
    # The client's error names the server (its address, even its password in a URL): logged, never answered.
    log.warning("session store (Redis) error: %s: %s", type(exc).__name__, exc)
    msg = "the session store is unavailable; try again"
    return StoreUnavailable(msg)


def _redis_errors(method: Callable[P, R]) -> Callable[P, R]:
    """Turn every Redis client error into StoreUnavailable (the API answers 503)."""

    @functools.wraps(method)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        from redis.exceptions import RedisError

        try:
            return method(*args, **kwargs)
        except RedisError as exc:
            raise _unavailable(exc) from exc

    return wrapper


async def _off_loop(func: Callable[[], R]) -> R:
    """Run a blocking Redis call on a worker thread, its client errors as StoreUnavailable."""
    return await anyio.to_thread.run_sync(_redis_errors(func))


@functools.lru_cache(maxsize=64)
def parse_scene_graph_json(raw: bytes) -> SceneGraph:
    """A stored scene graph, parsed once per distinct JSON: every summary and utterance reads the session's
    scene graph, and parsing a 60-object one costs about as much as reading the session. Callers share the
    object and never change it (a replacement is a new scene graph)."""
    return SceneGraph.model_validate_json(raw)


@functools.lru_cache(maxsize=1024)
def _decode_static(raw: bytes) -> dict[str, Any]:
    """The meta hash's static fields, decoded once per distinct bytes (they change only with the target);
    callers never change the dict."""
    decoded: dict[str, Any] = msgpack.unpackb(raw, raw=False)
    return decoded


def _block_voxels(stored: bytes | None) -> int:
    """A session's block size from its meta hash field."""
    return LEGACY_BLOCK_VOXELS if stored is None else int(stored)


@dataclasses.dataclass(frozen=True)
class _Commit:
    """One call of `COMMIT_SCRIPT`: its KEYS and ARGV, and what to know of it once it returns."""

    keys: list[str]
    args: list[Any]
    commit_id: str
    stamp: Stamp  # the state it was computed from
    writes: PartWrites
    now: float  # its updated_at


class _View:
    """`SessionView` of what an update read of the meta hash, or took from the mirror (`mirror`); the scene
    graph is read only when asked for."""

    def __init__(
        self,
        session_id: str,
        stamp: Stamp,
        static: dict[str, Any],
        look_alikes: np.ndarray,
        block_voxels: int,
        read_scene_graph: Callable[[], bytes],
        mirror: Mirrored | None = None,
    ) -> None:
        self.id = session_id
        self.stamp = stamp
        self.static = static
        self.look_alikes = look_alikes
        self.block_voxels = block_voxels
        self.mirror = mirror
        self._read_scene_graph = read_scene_graph
        self._grid: VoxelGrid | None = None

    @classmethod
    def of(cls, session_id: str, mirrored: Mirrored) -> _View:
        return cls(
            session_id,
            mirrored.stamp,
            mirrored.static,
            mirrored.look_alikes,
            mirrored.block_voxels,
            lambda: mirrored.scene_graph_json,
            mirrored,
        )

    @property
    def robot_id(self) -> str:
        return str(self.static["robot_id"])

    @property
    def version(self) -> int:
        return self.stamp[0]

    @property
    def target_label(self) -> str:
        return str(self.static["target_label"])

    @property
    def grid(self) -> VoxelGrid:
        if self._grid is None:
            self._grid = VoxelGrid.from_dict(self.static["grid"])
        return self._grid

    @property
    def label_map(self) -> Mapping[int, str]:
        return {int(k): str(v) for k, v in self.static["label_map"]}

    @property
    def limits(self) -> fusion.LayerLimits:
        return fusion.LayerLimits(**self.static["limits"])

    def scene_graph_json(self) -> bytes:
        return self._read_scene_graph()

    def scene_graph(self) -> SceneGraph:
        return parse_scene_graph_json(self.scene_graph_json())

    def observer(self) -> ObservationModel:
        return ObservationModel(
            self.grid,
            self.target_label,
            dict(self.label_map),
            SensorModel(**self.static["sensor_model"]),
            self.look_alikes,
        )


def _static_meta(session: Session) -> dict[str, Any]:
    meta = session.meta()
    for key in ("scene_graph", "version", "updated_at"):
        del meta[key]
    return meta


def _info(session_id: str, static: dict[str, Any], version: bytes, updated_at: bytes) -> SessionInfo:
    """A `SessionInfo` from the meta hash's fields alone."""
    grid = VoxelGrid.from_dict(static["grid"])
    return SessionInfo(
        id=session_id,
        robot_id=static["robot_id"],
        target_label=static["target_label"],
        n_voxels=grid.n_voxels,
        created_at=static["created_at"],
        updated_at=float(updated_at),
        version=int(version),
        grid=grid,
        sensor_model=SensorModel(**static["sensor_model"]),
        label_map={int(k): str(v) for k, v in static["label_map"]},
    )


def _not_found(session_id: str) -> NotFound:
    msg = f"no session {session_id!r}"
    return NotFound(msg)


class RedisSessionStore:
    """`SessionStore` on a Redis server (`url` as redis-py reads it, e.g. redis://127.0.0.1:6379/0)."""

    def __init__(
        self,
        url: str = "redis://127.0.0.1:6379/0",
        *,
        ttl_s: float | None = DEFAULT_TTL_S,
        prefix: str = "vlmap",
        block_voxels: int = DEFAULT_BLOCK_VOXELS,
        lock_ttl_s: float = DEFAULT_LOCK_TTL_S,
        lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
        socket_timeout_s: float = 5.0,
        mirror_bytes: int = DEFAULT_MIRROR_BYTES,
        idempotency_window_s: float = DEFAULT_IDEMPOTENCY_WINDOW_S,
        idempotency_keys: int = DEFAULT_IDEMPOTENCY_KEYS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if block_voxels < 1:
            msg = f"block_voxels must be positive, got {block_voxels}"
            raise InvalidInput(msg, "block_voxels")
        self.ttl_s = ttl_s
        self.prefix = prefix
        self.block_voxels = block_voxels
        self.lock_ttl_ms = int(lock_ttl_s * 1000)
        self.lock_wait_s = lock_wait_s
        self.idempotency_window_ms = int(idempotency_window_s * 1000)
        self.idempotency_keys = idempotency_keys
        self._clock = clock
        self._mirror = Mirror(mirror_bytes)
        self._url, self._socket_timeout_s = url, socket_timeout_s
        # Connected on first use (a replica may start before Redis does): (client, scripts, is a cluster)
        self._connection: tuple[Any, dict[str, Any], bool] | None = None
        self._connect_lock = threading.Lock()
        # (its loop, a redis.asyncio client, the commit script on it)
        self._async: tuple[asyncio.AbstractEventLoop, Any, Any] | None = None
        # session id -> the index score this process last wrote for it
        self._indexed: OrderedDict[str, float] = OrderedDict()
        self._indexed_lock = threading.Lock()
        self.events = RedisEventLog(
            url, f"{prefix}:events", lambda sid: self._key(sid, "events"), self._events_client
        )

    # -- the connection -------------------------------------------------------------------------------------

    def _connect(self) -> tuple[Any, dict[str, Any], bool]:
        with self._connect_lock:
            if self._connection is None:
                import redis
                from redis.cluster import RedisCluster

                wait = self._socket_timeout_s
                # Typed Any: redis-py's annotations merge its sync and async return types.
                client: Any = redis.Redis.from_url(
                    self._url, socket_timeout=wait, socket_connect_timeout=wait
                )
                clustered = bool(client.info("cluster").get("cluster_enabled"))
                if clustered:
                    client.close()
                    client = RedisCluster.from_url(
                        self._url, socket_timeout=wait, socket_connect_timeout=wait
                    )
                sources = {
                    "announce": ANNOUNCE_SCRIPT,
                    "commit": COMMIT_SCRIPT,
                    "create": CREATE_SCRIPT,
                    "delete": DELETE_SCRIPT,
                    "record": RECORD_SCRIPT,
                    "reserve": RESERVE_SCRIPT,
                    "release": RELEASE_SCRIPT,
                    "renew": RENEW_SCRIPT,
                }
                scripts = {name: client.register_script(text) for name, text in sources.items()}
                self._connection = (client, scripts, clustered)
            return self._connection

    @property
    def _client(self) -> Any:
        """The redis-py client (a `RedisCluster` on a cluster)."""
        return self._connect()[0]

    def _script(self, name: str) -> Any:
        return self._connect()[1][name]

    @property
    def clustered(self) -> bool:
        """Whether the store speaks to a Redis Cluster."""
        return self._connect()[2]

    async def _async_client(self) -> tuple[Any, Any]:
        """A redis.asyncio client of the running event loop (one per loop: its connections belong to it) and
        the commit script registered on it; of the cluster's kind when the server is one."""
        import redis.asyncio
        from redis.asyncio.cluster import RedisCluster

        loop = asyncio.get_running_loop()
        current = self._async
        if current is None or current[0] is not loop:
            # Whether the server is a cluster is asked once, by the threaded client, off the loop.
            connection = self._connection
            if connection is None:
                connection = await _off_loop(self._connect)
            kind: Any = RedisCluster if connection[2] else redis.asyncio.Redis
            wait = self._socket_timeout_s
            client = kind.from_url(self._url, socket_timeout=wait, socket_connect_timeout=wait)
            current = self._async = (loop, client, client.register_script(COMMIT_SCRIPT))
        return current[1], current[2]

    async def _events_client(self) -> Any:
        return (await self._async_client())[0]

    def _event_args(
        self, session_id: str, static: Mapping[str, Any], target: str, at: float, cause: Mapping[str, Any]
    ) -> list[Any]:
        """The `_EVENT` arguments of the scripts: the event's JSON around its version, the stream's length
        and the channel."""
        head, tail = event_parts(session_id, static["robot_id"], static["created_at"], at, target, cause)
        return [head, tail, max(1, self.events.history), self.events.channel]

    async def _on_loop(self, command: str, *args: Any) -> Any:
        """One read with the event loop's client (sent again once if its pooled connection was to a Redis
        that has restarted since)."""
        from redis.exceptions import ConnectionError as RedisConnectionError
        from redis.exceptions import RedisError

        try:
            client = (await self._async_client())[0]
            try:
                return await getattr(client, command)(*args)
            except RedisConnectionError:
                return await getattr(client, command)(*args)
        except RedisError as exc:
            raise _unavailable(exc) from exc

    # -- keys and small helpers -----------------------------------------------------------------------------

    def _key(self, session_id: str, part: str) -> str:
        return f"{self.prefix}:s:{{{session_id}}}:{part}"

    def _index_key(self, robot_id: str | None = None) -> str:
        return f"{self.prefix}:sessions" if robot_id is None else f"{self.prefix}:robot:{robot_id}"

    def _expiry_ms(self, now: float) -> float:
        return math.inf if self.ttl_s is None else math.floor((now + self.ttl_s) * 1000)

    def _live_from_ms(self, now: float) -> float:
        """The index score from which an entry may be a live session (scores lag by up to `_INDEX_LAG`)."""
        return -math.inf if self.ttl_s is None else (now - _INDEX_LAG * self.ttl_s) * 1000

    def _index_update(self, session_id: str, now: float) -> tuple[float, Callable[[], None]]:
        """(the score to record, a function noting it was recorded) if the session's index entries lag by
        more than `_INDEX_LAG` of the ttl behind an expiry from `now`; (nan, no-op) when they do not."""
        expiry = self._expiry_ms(now)
        with self._indexed_lock:
            recorded = self._indexed.get(session_id)
        if self.ttl_s is None or (
            recorded is not None and expiry - recorded <= _INDEX_LAG * self.ttl_s * 1000
        ):
            return math.nan, lambda: None

        def noted() -> None:
            with self._indexed_lock:
                self._indexed[session_id] = expiry
                self._indexed.move_to_end(session_id)
                while len(self._indexed) > _INDEXED_SESSIONS:
                    self._indexed.popitem(last=False)

        return expiry, noted

    def _refresh_index(self, session_id: str, robot_id: str, now: float) -> None:
        """Move the session's index scores to its expiry when they lag (after a commit; the indexes live in
        other slots than the session). A failure only leaves them lagging: the next commit tries again."""
        from redis.exceptions import RedisError

        score, noted = self._index_update(session_id, now)
        if math.isnan(score):
            return
        try:
            self._client.zadd(self._index_key(), {session_id: score})
            self._client.zadd(self._index_key(robot_id), {session_id: score})
        except RedisError as exc:
            log.warning("session index not refreshed", extra={"session": session_id, "error": str(exc)})
            return
        noted()

    async def _refresh_index_async(self, session_id: str, robot_id: str, now: float) -> None:
        """`_refresh_index` on the event loop's client."""
        from redis.exceptions import RedisError

        score, noted = self._index_update(session_id, now)
        if math.isnan(score):
            return
        client = (await self._async_client())[0]
        try:
            await client.zadd(self._index_key(), {session_id: score})
            await client.zadd(self._index_key(robot_id), {session_id: score})
        except RedisError as exc:
            log.warning("session index not refreshed", extra={"session": session_id, "error": str(exc)})
            return
        noted()

    @contextlib.contextmanager
    def _session_lock(self, session_id: str) -> Iterator[str]:
        """Hold the session's lock, renewed every third of its ttl until released; yields its token."""
        key, token = self._key(session_id, "lock"), uuid.uuid4().hex
        deadline = time.monotonic() + self.lock_wait_s
        pause = 0.001
        while not self._client.set(key, token, nx=True, px=self.lock_ttl_ms):
            if time.monotonic() > deadline:
                msg = f"session {session_id!r} stayed locked for {self.lock_wait_s} s; try again"
                raise StoreUnavailable(msg)
            time.sleep(pause)
            pause = min(2 * pause, 0.05)
        released = threading.Event()

        def renew() -> None:
            from redis.exceptions import RedisError

            while not released.wait(self.lock_ttl_ms / 3000):
                try:
                    if not self._script("renew")(keys=[key], args=[token, self.lock_ttl_ms]):
                        return  # lost it (expired under a stalled process): the commit's checks still hold
                except RedisError:
                    return

        renewer = threading.Thread(target=renew, name="vlmap-lock-renewal", daemon=True)
        renewer.start()
        try:
            yield token
        finally:
            released.set()
            renewer.join()
            self._script("release")(keys=[key], args=[token])

    # -- updates --------------------------------------------------------------------------------------------

    def _update(self, session_id: str, change: Change, idempotency: Idempotency | None) -> UpdateResult:
        """One read-compute-commit of a session (see the module docstring), from the mirror first."""
        mirrored = self._mirror.get(session_id)
        for _ in range(_OPTIMISTIC_ATTEMPTS):
            committed = self._attempt(session_id, change, "", idempotency, mirrored)
            if committed is not None:
                return committed
            if mirrored is not None:  # another writer came first: read from now on
                self._mirror.drop(session_id, mirrored.stamp)
                mirrored = None
        with self._session_lock(session_id) as token:
            for _ in range(_MAX_LOCKED_ATTEMPTS):
                committed = self._attempt(session_id, change, token, idempotency)
                if committed is not None:
                    return committed
        msg = f"session {session_id!r} kept changing during an update; try again"
        raise StoreUnavailable(msg)

    def _read_view(self, session_id: str) -> _View:
        """What an update needs of the meta hash (the scene graph is read if the change asks for it)."""
        meta_key = self._key(session_id, "meta")
        static_raw, version, updated_at, look_alikes, block_voxels = self._client.hmget(
            meta_key, ["static", "version", "updated_at", "look_alikes", "block_voxels"]
        )
        if static_raw is None:
            raise _not_found(session_id)

        def scene_graph_json() -> bytes:
            raw = self._client.hget(meta_key, "sg")
            if raw is None:
                raise _not_found(session_id)
            return bytes(raw)

        return _View(
            session_id,
            (int(version), updated_at),
            _decode_static(static_raw),
            np.frombuffer(look_alikes or b"", dtype="<i8"),
            _block_voxels(block_voxels),
            functools.cache(scene_graph_json),
        )

    def _attempt(
        self,
        session_id: str,
        change: Change,
        token: str,
        idempotency: Idempotency | None,
        mirrored: Mirrored | None = None,
    ) -> UpdateResult | None:
        """Read (or take the mirrored state), compute, commit once; None when another writer came first."""
        view = _View.of(session_id, mirrored) if mirrored is not None else self._read_view(session_id)
        try:
            delta = change.compute(view)
        except Exception:
            if mirrored is None:
                raise
            # A refusal stands only against the stored state: the mirror may be a state that another
            # replica's writes left behind (a target named there, the session made again for another robot),
            # and no commit would fail to tell.
            stored = self._read_view(session_id)
            if stored.stamp == mirrored.stamp:
                raise
            self._mirror.drop(session_id, mirrored.stamp)
            view, mirrored = stored, None
            delta = change.compute(view)
        writes = self._writes(view, delta)
        result = delta.result(session_id, view.version + 1, view.grid.n_voxels)
        commit = self._commit_of(session_id, view, token, writes, result, idempotency, change, delta)
        outcome = self._script("commit")(keys=commit.keys, args=commit.args)
        if not self._committed(session_id, outcome, commit, mirrored):
            return None
        self._refresh_index(session_id, view.robot_id, commit.now)
        return result

    async def _attempt_on_loop(
        self, session_id: str, change: Change, mirrored: Mirrored, idempotency: Idempotency | None
    ) -> UpdateResult | None:
        """`_attempt` from the mirrored state, committed through the running event loop's client; None when
        another writer came first (or the change refused a mirrored state that is no longer stored)."""
        from redis.exceptions import ConnectionError as RedisConnectionError

        view = _View.of(session_id, mirrored)
        try:
            delta = change.compute(view)
        except Exception:
            # A refusal stands only against the stored state (`_attempt`); else the update reads.
            version, updated_at = await self._on_loop(
                "hmget", self._key(session_id, "meta"), ["version", "updated_at"]
            )
            if version is not None and (int(version), updated_at) == mirrored.stamp:
                raise
            return None
        writes = self._writes(view, delta)
        result = delta.result(session_id, view.version + 1, view.grid.n_voxels)
        commit = self._commit_of(session_id, view, "", writes, result, idempotency, change, delta)
        script = (await self._async_client())[1]
        try:
            outcome = await script(keys=commit.keys, args=commit.args)
        except RedisConnectionError:
            # The connection closed, so the reply is lost but not necessarily the commit: a pooled connection
            # to a Redis that has restarted since fails so on its first use. Sent again, the commit finds its
            # own record if it landed.
            outcome = await script(keys=commit.keys, args=commit.args)
        if not self._committed(session_id, outcome, commit, mirrored):
            return None
        await self._refresh_index_async(session_id, view.robot_id, commit.now)
        return result

    def _writes(self, view: _View, delta: Delta) -> PartWrites:
        """The hashes (by part) that store the delta applied to the view's state: the language layer whole,
        the vision blocks the increments fall in (block by block), the meta hash's changed fields. Layers
        not in the mirror are read here; a concurrent change since the view fails the commit."""
        writes: PartWrites = {}
        n, b = view.grid.n_voxels, view.block_voxels
        limits = view.limits
        if delta.language is not None:
            if view.mirror is not None:
                lang = view.mirror.lang.copy()
            else:
                lang = assemble_layer(self._client.hgetall(self._key(view.id, "lang")), n, b)
            fusion.apply_language(lang, delta.language.log_likelihood, limits.lang_span)
            writes["lang"] = layer_blocks(lang, b)
        if delta.meta is not None:
            meta: dict[str, Any] = {}
            if delta.meta.target_label is not None:
                static = {**view.static, "target_label": delta.meta.target_label}
                meta["static"] = msgpack.packb(static, use_bin_type=True)
            if delta.meta.scene_graph is not None:
                meta["sg"] = delta.meta.scene_graph.model_dump_json().encode()
            if delta.meta.look_alikes is not None:
                meta["look_alikes"] = np.asarray(delta.meta.look_alikes, dtype="<i8").tobytes()
            writes["meta"] = meta
        if delta.vision is not None and len(delta.vision.flat_idx):
            writes["vis"] = self._vision_blocks(view, delta.vision.flat_idx, delta.vision.increments, limits)
        return writes

    def _vision_blocks(
        self, view: _View, flat_idx: np.ndarray, increments: np.ndarray, limits: fusion.LayerLimits
    ) -> dict[str, bytes]:
        """The vision blocks the increments fall in, after `fusion.apply_increments` (equation (4)'s
        clamped sum) on those blocks laid side by side: a batch reads and writes only what it touches."""
        n, b = view.grid.n_voxels, view.block_voxels
        touched = np.flatnonzero(np.bincount(flat_idx // b, minlength=n_blocks(n, b)))  # (T,)
        names = [str(i) for i in touched]
        local = np.zeros(len(touched) * b, dtype=fusion.LAYER_DTYPE)  # (T * b,) touched blocks side by side
        if view.mirror is not None:
            for slot, i in enumerate(touched):
                block = view.mirror.vis[int(i) * b : (int(i) + 1) * b]
                local[slot * b : slot * b + len(block)] = block
        else:
            stored = self._client.hmget(self._key(view.id, "vis"), names)
            for slot, data in enumerate(stored):
                if data is not None:
                    local[slot * b : slot * b + len(data) // 4] = np.frombuffer(data, dtype="<f4")
        slot_of = np.zeros(n_blocks(n, b), dtype=np.int64)
        slot_of[touched] = np.arange(len(touched))
        local_idx = slot_of[flat_idx // b] * b + flat_idx % b
        fusion.apply_increments(local, local_idx, increments, limits.vis_min, limits.vis_max)
        return {
            name: local[slot * b : slot * b + min(b, n - int(i) * b)].tobytes()
            for slot, (name, i) in enumerate(zip(names, touched, strict=True))
        }

    def _commit_of(
        self,
        session_id: str,
        view: _View,
        token: str,
        writes: PartWrites,
        result: UpdateResult,
        idempotency: Idempotency | None,
        change: Change | None = None,
        delta: Delta | None = None,
    ) -> _Commit:
        """The `COMMIT_SCRIPT` call for writes computed from the view's state, with the record of its
        idempotency key (the client's, else its own id) and the version's event (its cause from `change`)."""
        now = self._clock()
        commit_id = uuid.uuid4().hex
        key = f"k:{idempotency.key}" if idempotency is not None else f"c:{commit_id}"
        given = idempotency or Idempotency(key, "")
        record = IdempotencyRecord.of(given, result, now, commit_id, view.robot_id)
        expiry = self._expiry_ms(now)
        parts = ("meta", "lock", "lang", "vis", "summary", "idem", "idem_at", "events", "commits")
        keys = [self._key(session_id, part) for part in parts]
        stamp = view.stamp
        args: list[Any] = [stamp[0], stamp[1], token, repr(now), int(expiry) if math.isfinite(expiry) else ""]
        args += [key, record.pack(), int(now * 1000), self.idempotency_window_ms, self.idempotency_keys]
        args.append(len(writes))
        named = delta.meta.target_label if delta is not None and delta.meta is not None else None
        cause = describe(change.event if change is not None else None, result)
        args += self._event_args(session_id, view.static, named or view.target_label, now, cause)
        for part, fields in writes.items():
            keys.append(self._key(session_id, part))
            args.append(len(fields))
            for field_name, value in fields.items():
                args += [field_name, value]
        return _Commit(keys, args, commit_id, stamp, writes, now)

    def _committed(
        self, session_id: str, outcome: list[Any], commit: _Commit, mirrored: Mirrored | None
    ) -> bool:
        """The commit script's outcome: True if it wrote, now or when sent before (the mirror then follows),
        False if another writer came first; NotFound if the session is gone, AlreadyApplied if the client's
        key was seen."""
        code = int(outcome[0])
        if code == -1:
            raise _not_found(session_id)
        if code == -2:
            return False
        if code == -3:
            record = IdempotencyRecord.unpack(outcome[1])
            if record.commit != commit.commit_id:
                raise AlreadyApplied(record)
        stamp = commit.stamp
        base = mirrored or self._mirror.get(session_id, stamp)
        if base is not None:  # the mirror follows the commit (with the bytes Redis now holds)
            self._mirror.put(session_id, base.after(commit.writes, (stamp[0] + 1, repr(commit.now).encode())))
        return True

    async def update(
        self, session_id: str, change: Change, *, idempotency: Idempotency | None = None
    ) -> UpdateResult:
        # An inline change from the mirror is computed here and committed with the loop's client: no worker
        # thread. Otherwise, or when another writer came first, the reading update runs on a worker thread.
        if change.inline:
            mirrored = self._mirror.get(session_id)
            if mirrored is not None:
                from redis.exceptions import RedisError

                try:
                    committed = await self._attempt_on_loop(session_id, change, mirrored, idempotency)
                except RedisError as exc:
                    raise _unavailable(exc) from exc
                if committed is not None:
                    return committed
                self._mirror.drop(session_id, mirrored.stamp)
        return await _off_loop(functools.partial(self._update, session_id, change, idempotency))

    # -- SessionStore ---------------------------------------------------------------------------------------

    def _create(
        self, session: Session, max_per_robot: int | None, idempotency: Idempotency | None
    ) -> SessionInfo:
        check_session_id(session.id)
        now = self._clock()
        static = msgpack.packb(_static_meta(session), use_bin_type=True)
        sg = session.scene_graph.model_dump_json().encode()
        look_alikes = mapped_look_alikes(session.grid, session.scene_graph, session.target_label)
        look_alike_bytes = look_alikes.astype("<i8").tobytes()
        expiry = self._expiry_ms(now)
        robot_index = self._index_key(session.robot_id)
        if idempotency is not None:
            # A retry of a creation (the session live, or deleted: its tombstone) is answered before a slot
            # is reserved, which would otherwise hold one of the robot's slots for nothing, or refuse with
            # a 429 the final 404. The script checks again, atomically.
            seen = self._fresh(self._client.hget(self._key(session.id, "idem"), f"k:{idempotency.key}"), now)
            if seen is not None:
                raise AlreadyApplied(seen)
        if max_per_robot is not None:
            self._reserve(session.id, robot_index, now, max_per_robot)
        meta = {
            "static": static,
            "sg": sg,
            "look_alikes": look_alike_bytes,
            "block_voxels": self.block_voxels,
            "version": session.version,
            "updated_at": repr(now),
        }
        parts = [meta]
        for layer in (session.belief.lang, session.belief.vis):
            parts.append(layer_blocks(layer, self.block_voxels) if np.any(layer) else {})
        record = b""
        if idempotency is not None:
            result = UpdateResult(session.id, session.version, 0)
            record = IdempotencyRecord.of(idempotency, result, now, robot_id=session.robot_id).pack()
        args: list[Any] = [f"k:{idempotency.key}" if idempotency is not None else "", record, int(now * 1000)]
        args += [
            self.idempotency_window_ms,
            self.idempotency_keys,
            int(expiry) if math.isfinite(expiry) else "",
            session.version,
        ]
        created = {"kind": "created"}
        args += self._event_args(session.id, _static_meta(session), session.target_label, now, created)
        for fields in parts:
            args.append(len(fields))
            for name, value in fields.items():
                args += [name, value]
        key_parts = ("meta", "lang", "vis", "summary", "idem", "idem_at", "events", "commits")
        keys = [self._key(session.id, part) for part in key_parts]
        outcome = self._script("create")(keys=keys, args=args)
        if int(outcome[0]) < 0:
            if int(outcome[0]) == -3:
                raise AlreadyApplied(IdempotencyRecord.unpack(outcome[1]))
            msg = f"a session with id {session.id!r} exists"
            raise InvalidInput(msg, "id")
        self._client.zadd(self._index_key(), {session.id: expiry})
        self._client.zadd(robot_index, {session.id: expiry})  # the reservation becomes the expiry
        stamp = (session.version, repr(now).encode())
        self._mirror.put(
            session.id,
            Mirrored(
                stamp,
                msgpack.unpackb(static, raw=False),
                look_alikes.astype("<i8"),
                self.block_voxels,
                sg,
                session.belief.lang.astype(fusion.LAYER_DTYPE, copy=True),  # the caller keeps its session
                session.belief.vis.astype(fusion.LAYER_DTYPE, copy=True),
            ),
        )
        return dataclasses.replace(session.info(), updated_at=now)

    async def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        return await _off_loop(functools.partial(self._create, session, max_per_robot, idempotency))

    def _fresh(self, packed: bytes | None, now: float) -> IdempotencyRecord | None:
        """A key's record read outside a script, unless it is older than the window (the scripts' `fresh`)."""
        if packed is None:
            return None
        record = IdempotencyRecord.unpack(packed)
        return record if record.remembered(now, self.idempotency_window_ms / 1000) else None

    def _reserve(self, session_id: str, robot_index: str, now: float, limit: int) -> None:
        """Count the session in its robot's index, atomically with the check that the robot has fewer than
        `limit` live sessions (LimitExceeded otherwise). Entries of sessions that are gone are pruned first;
        the reservation lasts `_RESERVATION_S` until the creation makes it the session's expiry."""
        self._live_ids(robot_index, now)
        reservation = (now + _RESERVATION_S) * 1000
        if self.ttl_s is None:
            reservation = math.inf
        live_from = self._live_from_ms(now)
        args = [session_id, live_from, reservation, limit]
        if not self._script("reserve")(keys=[robot_index], args=args):
            raise session_limit_error(robot_index.rsplit(":", 1)[1], limit)

    def _live_ids(self, index: str, now: float) -> list[tuple[str, dict[str, Any], bytes, bytes]]:
        """(id, static, version, updated_at) of the index's sessions that still exist, oldest score first;
        entries whose session is gone (and whose score says it should be) are removed."""
        now_ms = now * 1000
        self._client.zremrangebyscore(index, "-inf", f"({self._live_from_ms(now)}")
        entries = self._client.zrangebyscore(index, self._live_from_ms(now), "+inf", withscores=True)
        ids = [sid.decode() for sid, _ in entries]
        with self._client.pipeline(transaction=False) as pipe:
            for sid in ids:
                pipe.hmget(self._key(sid, "meta"), ["static", "version", "updated_at"])
            rows = pipe.execute()
        live, gone = [], []
        for (sid, score), (static_raw, version, updated_at) in zip(
            zip(ids, (score for _, score in entries), strict=True), rows, strict=True
        ):
            if static_raw is not None:
                live.append((sid, _decode_static(static_raw), version, updated_at))
            elif score < now_ms:  # expired or deleted; a newer score is a creation in flight
                gone.append(sid)
        if gone:
            self._client.zrem(index, *gone)
        return live

    def _read_state(self, session_id: str) -> Mirrored:
        """The whole session in one transaction; it becomes the mirrored state."""
        with self._client.pipeline(transaction=True) as pipe:
            for part in ("meta", "lang", "vis"):
                pipe.hgetall(self._key(session_id, part))
            meta, lang, vis = pipe.execute()
        if not meta:
            raise _not_found(session_id)
        static = _decode_static(meta[b"static"])
        n, b = int(np.prod(static["grid"]["shape"])), _block_voxels(meta.get(b"block_voxels"))
        state = Mirrored(
            (int(meta[b"version"]), meta[b"updated_at"]),
            static,
            np.frombuffer(meta.get(b"look_alikes", b""), dtype="<i8"),
            b,
            meta[b"sg"],
            assemble_layer(lang, n, b),
            assemble_layer(vis, n, b),
        )
        self._mirror.put(session_id, state)
        return state

    def _load(self, session_id: str) -> Session:
        """The current state: the mirror's when it is current (no layers read back), else read whole."""
        version, updated_at = self._client.hmget(self._key(session_id, "meta"), ["version", "updated_at"])
        if version is None:
            raise _not_found(session_id)
        state = self._mirror.get(session_id, (int(version), updated_at)) or self._read_state(session_id)
        full = {**state.static, "version": state.stamp[0], "updated_at": float(state.stamp[1])}
        scene_graph = parse_scene_graph_json(state.scene_graph_json)
        return Session.from_meta(full, state.lang.copy(), state.vis.copy(), scene_graph=scene_graph)

    async def load(self, session_id: str) -> Session:
        return await _off_loop(functools.partial(self._load, session_id))

    async def head(self, session_id: str) -> SessionInfo:
        fields = ["static", "version", "updated_at"]
        static_raw, version, updated_at = await self._on_loop("hmget", self._key(session_id, "meta"), fields)
        if static_raw is None:
            raise _not_found(session_id)
        return _info(session_id, _decode_static(static_raw), version, updated_at)

    async def head_and_scene_graph(self, session_id: str) -> tuple[SessionInfo, SceneGraph]:
        fields = ["static", "version", "updated_at", "sg"]
        static_raw, version, updated_at, raw = await self._on_loop(
            "hmget", self._key(session_id, "meta"), fields
        )
        if static_raw is None or raw is None:
            raise _not_found(session_id)
        info = _info(session_id, _decode_static(static_raw), version, updated_at)
        return info, parse_scene_graph_json(bytes(raw))

    async def summary_get(self, session_id: str, version: int, options: str) -> dict[str, Any] | None:
        stored = await self._on_loop("hget", self._key(session_id, "summary"), options)
        if stored is None:
            return None
        entry = msgpack.unpackb(stored, raw=False)
        summary: dict[str, Any] = entry["summary"]
        return summary if entry["version"] == version else None

    async def summary_put(self, session_id: str, version: int, options: str, summary: dict[str, Any]) -> None:
        # A slower replica may overwrite a newer entry with an older one; readers then recompute (harmless).
        # The entry expires with the session (the commit that made the version renewed the others).
        meta_key, summary_key = self._key(session_id, "meta"), self._key(session_id, "summary")
        ttl_ms = await self._on_loop("pttl", meta_key)
        entry = msgpack.packb({"version": version, "summary": summary}, use_bin_type=True)
        await self._on_loop("hset", summary_key, options, entry)
        if ttl_ms > 0:
            await self._on_loop("pexpire", summary_key, ttl_ms)

    def _list(self, robot_id: str | None) -> list[SessionInfo]:
        rows = self._live_ids(self._index_key(robot_id), self._clock())
        infos = [_info(sid, static, version, updated_at) for sid, static, version, updated_at in rows]
        return sorted(infos, key=lambda info: (info.created_at, info.id))

    async def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        return await _off_loop(functools.partial(self._list, robot_id))

    def _delete(self, session_id: str, idempotency: Idempotency | None) -> None:
        meta_key, idem_key = self._key(session_id, "meta"), self._key(session_id, "idem")
        key = f"k:{idempotency.key}" if idempotency is not None else ""
        with self._client.pipeline(transaction=True) as pipe:
            pipe.hget(meta_key, "static")
            pipe.hget(idem_key, key or "-")
            static_raw, seen_raw = pipe.execute()
        seen = self._fresh(seen_raw, self._clock()) if key else None
        if seen is not None:
            raise AlreadyApplied(seen)
        if static_raw is None:
            raise _not_found(session_id)
        static = _decode_static(static_raw)
        robot_id = static["robot_id"]
        now = self._clock()
        packed = b""
        if idempotency is not None:
            result = UpdateResult(session_id, 0, 0)
            packed = IdempotencyRecord.of(idempotency, result, now, robot_id=robot_id).pack()
        parts = ("meta", "lang", "vis", "summary", "idem", "idem_at", "events", "commits")
        keys = [self._key(session_id, part) for part in parts]
        args: list[Any] = [key, packed, int(now * 1000), self.idempotency_window_ms]
        args += self._event_args(session_id, static, static["target_label"], now, {"kind": "deleted"})
        args.append(DELETED_STREAM_MS)
        outcome = self._script("delete")(keys=keys, args=args)
        if int(outcome[0]) == -3:
            raise AlreadyApplied(IdempotencyRecord.unpack(outcome[1]))
        if int(outcome[0]) == -1:
            raise _not_found(session_id)
        self._client.zrem(self._index_key(), session_id)
        self._client.zrem(self._index_key(robot_id), session_id)
        self._client.delete(self._key(session_id, "rec"))  # after the script: no frame is appended since
        self._mirror.drop(session_id)

    async def delete(self, session_id: str, *, idempotency: Idempotency | None = None) -> None:
        await _off_loop(functools.partial(self._delete, session_id, idempotency))

    def _announce(self, session_id: str, cause: Mapping[str, Any], idempotency: Idempotency | None) -> None:
        static_raw = self._client.hget(self._key(session_id, "meta"), "static")
        if static_raw is None:
            raise _not_found(session_id)
        static = _decode_static(static_raw)
        keys = [self._key(session_id, part) for part in ("meta", "events", "idem", "idem_at")]
        now = self._clock()
        args = self._event_args(session_id, static, static["target_label"], now, cause)
        args += [f"k:{idempotency.key}" if idempotency is not None else "", int(now * 1000)]
        args.append(self.idempotency_window_ms)
        outcome = self._script("announce")(keys=keys, args=args)
        if int(outcome[0]) == -3:
            raise AlreadyApplied(IdempotencyRecord.unpack(outcome[1]))
        if int(outcome[0]) == 0:
            raise _not_found(session_id)

    async def announce(
        self, session_id: str, cause: Mapping[str, Any], *, idempotency: Idempotency | None = None
    ) -> None:
        await _off_loop(functools.partial(self._announce, session_id, cause, idempotency))

    def _record(self, session_id: str, frame: bytes, limit: int) -> None:
        keys = [self._key(session_id, "rec"), self._key(session_id, "meta")]
        self._script("record")(keys=keys, args=[frame, limit])

    async def record(self, session_id: str, frame: bytes, limit: int) -> None:
        await _off_loop(functools.partial(self._record, session_id, frame, limit))

    async def recording(self, session_id: str) -> tuple[bytes, ...]:
        return tuple(await self._on_loop("lrange", self._key(session_id, "rec"), 0, -1))

    def _purge_expired(self) -> int:
        """Prune the index entries of sessions Redis has dropped (their keys expire by themselves)."""
        now = self._clock()
        index = self._index_key()
        stale = [sid.decode() for sid in self._client.zrangebyscore(index, "-inf", f"({now * 1000}")]
        with self._client.pipeline(transaction=False) as pipe:
            for sid in stale:
                pipe.exists(self._key(sid, "meta"))
            alive = pipe.execute()
        gone = [sid for sid, exists in zip(stale, alive, strict=True) if not exists]
        if gone:
            self._client.zrem(index, *gone)
        return len(gone)

    async def purge_expired(self) -> int:
        return await _off_loop(self._purge_expired)

    def close(self) -> None:
        if self._connection is not None:
            self._connection[0].close()

    def __enter__(self) -> RedisSessionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
