"""Sessions in Redis, shared by every replica of the service.

Keys of session S (the hash tag {S} keeps them in one cluster slot):

    <prefix>:s:{S}:meta   hash: static (msgpack: robot, grid, target, label map, sensor model, limits,
                          creation time; only the target ever changes), sg (scene graph JSON), version,
                          updated_at, look_alikes (int64 flat indices of the mapped objects of the
                          target's class, `mapped_look_alikes`, rewritten with sg or the target),
                          block_voxels (the layers' block size); `info` and `list` read this hash alone
    <prefix>:s:{S}:lang   hash: block number -> float32 bytes of the session's `block_voxels` voxels (the meta
                          hash's field, fixed at creation; absent blocks are zeros)
    <prefix>:s:{S}:vis    hash: the same for the vision layer
    <prefix>:s:{S}:lock   the update lock
    <prefix>:s:{S}:summary  hash: summary options -> msgpack {version, summary}, the last summary computed
                          by any replica: dashboards polling through several replicas summarise each
                          version once, fleet-wide (a reader uses it only if its version is current)
    <prefix>:s:{S}:idem   hash: idempotency key -> `IdempotencyRecord` of the commit made under it: a
                          client's Idempotency-Key ("k:<key>"), or the commit's own id ("c:<id>")
    <prefix>:s:{S}:idem_at  sorted set: the same keys scored by when they were written (ms)
    <prefix>:sessions, <prefix>:robot:<R>   sorted sets of session ids scored by expiry time (ms), as last
                          recorded (a hint: `list` checks every id against its meta hash)

Redis Cluster: the store speaks to a cluster when the URL's server is one (`INFO cluster`), through
redis-py's cluster clients, unchanged otherwise. Every script touches only keys of one session (one hash
tag, so one slot) or one index; an index is written apart from the session, after it.

No lost updates across replicas: an update reads what it needs (the meta hash and the blocks it will
change) in one transaction, computes, and commits with one script call (`_COMMIT_SCRIPT`) that writes only
if the session is still at the version it read and no other writer holds the session's lock; else it
reads again. Every update is then one read and one write round trip, and one fsync on an `appendfsync
always` Redis (a lock taken and released around each update had cost two more writes, each fsynced). A
writer that keeps losing (a slow utterance among fast observation streams) takes the session's lock (SET
NX PX with a random token), which makes every other writer's commit fail until it is done. An observation
batch reads and writes only the vision blocks its voxels fall in.

The mirror: each store keeps in memory the last state of each session it read in full or committed
(`_Mirror`), named by its (version, updated_at). A replica that a robot's connection stays with then
updates without the read (it computes from the mirror and commits on the condition that the stored state
still has that name; when another replica wrote meanwhile, the commit fails and the update reads), and
summarises a version it wrote without reading the whole belief back. The mirror is never needed to be
right: the commit's condition is checked in Redis, and a state is taken from it only under its name.
An observation batch's update from the mirror also runs on the caller's event loop
(`apply_observations_async`), committed through that loop's `redis.asyncio` client: it needs no read, so
no worker thread; an update that must read runs on one.

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
`idempotency_window_s`); a keyed delete leaves its record (and no other) for the window.

Locks: a lock holder renews its lock every third of `lock_ttl_s` while it works, so the ttl can be short
(3 s): a holder that died (kill -9 mid-update) leaves a lock that other writers wait out within that ttl.

Any Redis failure (connection refused or lost, timeout, out of memory) raises `StoreUnavailable`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import json
import logging
import math
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from typing import Any, ParamSpec, TypeVar

import msgpack
import numpy as np

from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.session import (
    DEFAULT_MAX_BATCH_VOXELS,
    BeliefState,
    IncrementBatch,
    Labels,
    ObservationModel,
    SensorModel,
    Session,
    SessionInfo,
    UpdateResult,
    check_target_label,
    language_log_likelihood,
    mapped_look_alikes,
)
from app.belief.summary import PosteriorSummary, json_fingerprint, summarize
from app.errors import AlreadyApplied, InvalidInput, NotFound, StoreUnavailable
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph
from app.stores.base import (
    DEFAULT_IDEMPOTENCY_KEYS,
    DEFAULT_IDEMPOTENCY_WINDOW_S,
    DEFAULT_TTL_S,
    Authorize,
    Idempotency,
    IdempotencyRecord,
    check_session_id,
    float64_mixture,
    session_limit_error,
)

#: Voxels per stored block of a new session: 4 kB of float32. A camera's 10k-voxel batch in a 163k-voxel room
#: touches 160 kB of 1024-voxel blocks, against 550 kB of the 65,536-voxel blocks first used: each update
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

# HSET of n (field, value) pairs from ARGV[at], in chunks: Lua's unpack() refuses more than ~8000 values
# (a 16M-voxel layer is 15,625 blocks).
_HSET_CHUNKS = """
local function hset_pairs(key, at, n)
    local done = 0
    while done < n do
        local m = math.min(n - done, 1000)
        local first = at + 2 * done
        redis.call('HSET', key, unpack(ARGV, first, first + 2 * m - 1))
        done = done + m
    end
end
"""

# Remember an idempotency key (KEYS[i], KEYS[i + 1]: the idem hash and its sorted set) and forget those
# past the window or beyond the count.
_REMEMBER = """
local function remember(i, key, record, now_ms, window_ms, max_keys)
    redis.call('HSET', KEYS[i], key, record)
    redis.call('ZADD', KEYS[i + 1], now_ms, key)
    local oldest = '(' .. (now_ms - window_ms)
    local stale = redis.call('ZRANGEBYSCORE', KEYS[i + 1], '-inf', oldest, 'LIMIT', 0, 64)
    local excess = redis.call('ZCARD', KEYS[i + 1]) - max_keys
    if excess > 0 then
        for _, k in ipairs(redis.call('ZRANGE', KEYS[i + 1], 0, excess - 1)) do table.insert(stale, k) end
    end
    for _, k in ipairs(stale) do
        redis.call('HDEL', KEYS[i], k)
        redis.call('ZREM', KEYS[i + 1], k)
    end
end
"""

# KEYS: meta, lock, lang, vis, summary, idem, idem_at, then the hashes written.
# ARGV: [1] version read, [2] updated_at read (with the version, the name of the state read: a session
# deleted and created again under its id restarts its versions), [3] lock token ("" without the lock),
# [4] new updated_at, [5] expiry ms ("" for none), [6] idempotency key, [7] its record, [8] now ms,
# [9] window ms, [10] keys kept, [11] number of hashes written, then per hash: its number of fields, then
# field, value, ...
# Returns {version} when written, {-1} without the session, {-2} when another writer came first, and
# {-3, record} when the key was seen (this very commit, resent, or another request with the key).
_COMMIT_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + """
local seen = redis.call('HGET', KEYS[6], ARGV[6])
if seen then return {-3, seen} end
local state = redis.call('HMGET', KEYS[1], 'version', 'updated_at')
if not state[1] then return {-1} end
if state[1] ~= ARGV[1] or state[2] ~= ARGV[2] then return {-2} end
local holder = redis.call('GET', KEYS[2])
if holder and holder ~= ARGV[3] then return {-2} end
local at = 12
for k = 8, 7 + tonumber(ARGV[11]) do
    local n = tonumber(ARGV[at])
    hset_pairs(KEYS[k], at + 1, n)
    at = at + 1 + 2 * n
end
local new = tonumber(state[1]) + 1
redis.call('HSET', KEYS[1], 'version', new, 'updated_at', ARGV[4])
remember(6, ARGV[6], ARGV[7], tonumber(ARGV[8]), tonumber(ARGV[9]), tonumber(ARGV[10]))
if ARGV[5] ~= '' then
    for _, k in ipairs({1, 3, 4, 5, 6, 7}) do redis.call('PEXPIREAT', KEYS[k], ARGV[5]) end
end
return {new}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms, [5] keys kept,
# [6] expiry ms ("" for none), then for meta, lang and vis: the number of fields, then field, value, ...
# Returns {0} when created, {-1} when the session exists, {-3, record} when it exists made under the key.
_CREATE_SCRIPT = (
    _HSET_CHUNKS
    + _REMEMBER
    + """
if redis.call('EXISTS', KEYS[1]) == 1 then
    local seen = ARGV[1] ~= '' and redis.call('HGET', KEYS[5], ARGV[1])
    if seen then return {-3, seen} end
    return {-1}
end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6])  -- what a deleted incarnation left
local at = 7
for k = 1, 3 do
    local n = tonumber(ARGV[at])
    if n > 0 then hset_pairs(KEYS[k], at + 1, n) end
    at = at + 1 + 2 * n
end
if ARGV[1] ~= '' then
    remember(5, ARGV[1], ARGV[2], tonumber(ARGV[3]), tonumber(ARGV[4]), tonumber(ARGV[5]))
end
if ARGV[6] ~= '' then
    for k = 1, 6 do redis.call('PEXPIREAT', KEYS[k], ARGV[6]) end
end
return {0}
"""
)

# KEYS: meta, lang, vis, summary, idem, idem_at.
# ARGV: [1] idempotency key ("" for none), [2] its record, [3] now ms, [4] window ms.
# Returns {0} when deleted, {-1} without the session, {-3, record} when the key was seen.
_DELETE_SCRIPT = """
if ARGV[1] ~= '' then
    local seen = redis.call('HGET', KEYS[5], ARGV[1])
    if seen then return {-3, seen} end
end
if redis.call('EXISTS', KEYS[1]) == 0 then return {-1} end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3], KEYS[4], KEYS[5], KEYS[6])
if ARGV[1] ~= '' then  -- the tombstone: this delete's record, for the window
    redis.call('HSET', KEYS[5], ARGV[1], ARGV[2])
    redis.call('ZADD', KEYS[6], ARGV[3], ARGV[1])
    redis.call('PEXPIRE', KEYS[5], ARGV[4])
    redis.call('PEXPIRE', KEYS[6], ARGV[4])
end
return {0}
"""

# KEYS: a robot's index. ARGV: [1] session id, [2] the score from which an entry counts as live, [3] the
# reservation's score, [4] the robot's limit. Returns 1 when reserved (or already there), 0 at the limit.
_RESERVE_SCRIPT = """
if redis.call('ZSCORE', KEYS[1], ARGV[1]) then return 1 end
if redis.call('ZCOUNT', KEYS[1], ARGV[2], '+inf') >= tonumber(ARGV[4]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[3], ARGV[1])
return 1
"""

_RELEASE_SCRIPT = """
if redis.call('get', KEYS[1]) == ARGV[1] then
    return redis.call('del', KEYS[1])
end
return 0
"""

_RENEW_SCRIPT = """
if redis.call('get', KEYS[1]) == ARGV[1] then
    return redis.call('pexpire', KEYS[1], ARGV[2])
end
return 0
"""

log = logging.getLogger(__name__)

P = ParamSpec("P")
R = TypeVar("R")
#: A read queued beside the meta hash: (redis-py command name, key, *arguments).
Read = tuple[Any, ...]
#: An update's reads, or a function that makes them (called only when the update reads).
Reads = Sequence[Read] | Callable[[], Sequence[Read]]
#: Hashes an update writes: key -> {field: value}.
Writes = dict[str, dict[str, Any]]
#: change(what the meta hash held, read results) -> (writes, result)
Change = Callable[["_Snapshot", list[Any]], tuple[Writes, R]]
#: An observation or detection batch's change, the reads it needs when it reads, and its idempotency key.
BatchUpdate = tuple[Change[UpdateResult], Callable[[], Sequence[Read]], Idempotency | None]


def _unavailable(exc: Exception) -> StoreUnavailable:
    msg = f"the session store (Redis) is unavailable: {type(exc).__name__}: {exc}"
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


@functools.lru_cache(maxsize=64)
def parse_scene_graph_json(raw: bytes) -> SceneGraph:
    """A stored scene graph, parsed once per distinct JSON: every summary and utterance reads the session's
    scene graph, and parsing a 60-object one took 1.7 ms, half of reading the session. Callers share the
    object and never change it (a replacement is a new scene graph)."""
    return SceneGraph.model_validate_json(raw)


def _n_blocks(n_voxels: int, b: int) -> int:
    return -(-n_voxels // b)


def _block_voxels(stored: bytes | None) -> int:
    """A session's block size from its meta hash field."""
    return LEGACY_BLOCK_VOXELS if stored is None else int(stored)


#: A stored state's name: (version, the meta hash's updated_at bytes).
Stamp = tuple[int, bytes]


@dataclasses.dataclass(frozen=True)
class _Mirrored:
    """A session's state as this store last read in full or committed it, named by `stamp`.

    Never changed in place (a summary on another thread may be reading it): an update makes a new one.
    `static` is decoded from the stored bytes, so it equals what a read of the meta hash gives.
    """

    stamp: Stamp
    static: dict[str, Any]
    look_alikes: np.ndarray
    block_voxels: int
    scene_graph_json: bytes
    lang: np.ndarray  # (N,) float32
    vis: np.ndarray  # (N,) float32

    @property
    def nbytes(self) -> int:
        return int(self.lang.nbytes + self.vis.nbytes)

    def after(self, writes: dict[str, dict[str, Any]], stamp: Stamp) -> _Mirrored:
        """The state once a commit wrote `writes` (part -> {field: value}, as `_attempt` sends them)."""
        layers = {"lang": self.lang, "vis": self.vis}
        for part, fields in writes.items():
            if part in layers and fields:
                layer, b = layers[part].copy(), self.block_voxels
                for name, data in fields.items():
                    start = int(name) * b
                    layer[start : start + len(data) // 4] = np.frombuffer(data, dtype="<f4")
                layers[part] = layer
        meta = writes.get("meta", {})
        sg = meta.get("sg", self.scene_graph_json)
        return _Mirrored(
            stamp=stamp,
            static=msgpack.unpackb(meta["static"], raw=False) if "static" in meta else self.static,
            look_alikes=(
                np.frombuffer(meta["look_alikes"], dtype="<i8") if "look_alikes" in meta else self.look_alikes
            ),
            block_voxels=self.block_voxels,
            scene_graph_json=sg.encode() if isinstance(sg, str) else sg,
            lang=layers["lang"],
            vis=layers["vis"],
        )


class _Mirror:
    """Sessions' last known states (`_Mirrored`), the least recently used dropped beyond `max_bytes`."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, _Mirrored] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, session_id: str, stamp: Stamp | None = None) -> _Mirrored | None:
        """The session's entry (only if it is the state `stamp` names, when given)."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is None or (stamp is not None and entry.stamp != stamp):
                return None
            self._entries.move_to_end(session_id)
            return entry

    def put(self, session_id: str, entry: _Mirrored) -> None:
        with self._lock:
            self._pop(session_id)
            if entry.nbytes > self.max_bytes:
                return
            self._entries[session_id] = entry
            self._bytes += entry.nbytes
            while self._bytes > self.max_bytes:
                self._pop(next(iter(self._entries)))

    def drop(self, session_id: str, stamp: Stamp | None = None) -> None:
        """Forget the session (only its entry named `stamp`, when given: a newer one stays)."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is not None and (stamp is None or entry.stamp == stamp):
                self._pop(session_id)

    def _pop(self, session_id: str) -> None:
        entry = self._entries.pop(session_id, None)
        if entry is not None:
            self._bytes -= entry.nbytes


@dataclasses.dataclass(frozen=True)
class _Commit:
    """One call of `_COMMIT_SCRIPT`: its KEYS and ARGV, and what to know of it once it returns."""

    keys: list[str]
    args: list[Any]
    commit_id: str
    stamp: Stamp  # the state it was computed from
    writes: Writes
    now: float  # its updated_at


@dataclasses.dataclass(frozen=True)
class _Snapshot:
    """What an update read of the meta hash, or took from the mirror (then `mirror` is set and the update's
    reads are not made: the change takes the layers and the scene graph from it)."""

    static: dict[str, Any]
    new_version: int
    look_alikes: np.ndarray  # the stored `mapped_look_alikes`
    block_voxels: int
    mirror: _Mirrored | None = None

    @classmethod
    def of(cls, mirrored: _Mirrored) -> _Snapshot:
        """What an update computes from when it takes the mirrored state."""
        version = mirrored.stamp[0]
        return cls(mirrored.static, version + 1, mirrored.look_alikes, mirrored.block_voxels, mirrored)


def _static_meta(session: Session) -> dict[str, Any]:
    meta = session.meta()
    for key in ("scene_graph", "version", "updated_at"):
        del meta[key]
    return meta


def _look_alikes(grid: VoxelGrid, scene_graph: SceneGraph, target_label: str) -> bytes:
    return mapped_look_alikes(grid, scene_graph, target_label).astype("<i8").tobytes()


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
        max_batch_voxels: int = DEFAULT_MAX_BATCH_VOXELS,
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
        self.max_batch_voxels = max_batch_voxels
        self.idempotency_window_ms = int(idempotency_window_s * 1000)
        self.idempotency_keys = idempotency_keys
        self._clock = clock
        self._mirror = _Mirror(mirror_bytes)
        self._url, self._socket_timeout_s = url, socket_timeout_s
        # Connected on first use (a replica may start before Redis does): (client, scripts, is a cluster)
        self._connection: tuple[Any, dict[str, Any], bool] | None = None
        self._connect_lock = threading.Lock()
        # (its loop, a redis.asyncio client, the commit script on it)
        self._async: tuple[asyncio.AbstractEventLoop, Any, Any] | None = None
        # session id -> the index score this process last wrote for it
        self._indexed: OrderedDict[str, float] = OrderedDict()
        self._indexed_lock = threading.Lock()

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
                    "commit": _COMMIT_SCRIPT,
                    "create": _CREATE_SCRIPT,
                    "delete": _DELETE_SCRIPT,
                    "reserve": _RESERVE_SCRIPT,
                    "release": _RELEASE_SCRIPT,
                    "renew": _RENEW_SCRIPT,
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

    @staticmethod
    def _blocks_of(layer: np.ndarray, b: int) -> dict[str, bytes]:
        return {str(i): layer[i * b : (i + 1) * b].tobytes() for i in range(_n_blocks(len(layer), b))}

    @staticmethod
    def _assemble(blocks: dict[bytes, bytes], n_voxels: int, b: int) -> np.ndarray:
        layer = np.zeros(n_voxels, dtype=fusion.LAYER_DTYPE)
        for name, data in blocks.items():
            start = int(name) * b
            layer[start : start + len(data) // 4] = np.frombuffer(data, dtype="<f4")
        return layer

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

    def _update(
        self,
        session_id: str,
        change: Change[R],
        reads: Reads = (),
        idempotency: Idempotency | None = None,
    ) -> R:
        """One read-compute-commit of a session (see the module docstring).

        `reads` are (command, key, *args) read in the same transaction as the meta hash (or a function that
        makes them, called only if an attempt reads); `change(snapshot, results)` gets the meta hash's
        fields and their results and returns (hashes to write, result).
        """
        mirrored = self._mirror.get(session_id)
        for _ in range(_OPTIMISTIC_ATTEMPTS):
            committed = self._attempt(session_id, change, reads, "", idempotency, mirrored)
            if committed is not None:
                return committed[0]
            if mirrored is not None:  # another writer came first: read from now on
                self._mirror.drop(session_id, mirrored.stamp)
                mirrored = None
        with self._session_lock(session_id) as token:
            for _ in range(_MAX_LOCKED_ATTEMPTS):
                committed = self._attempt(session_id, change, reads, token, idempotency)
                if committed is not None:
                    return committed[0]
        msg = f"session {session_id!r} kept changing during an update; try again"
        raise StoreUnavailable(msg)

    def _attempt(
        self,
        session_id: str,
        change: Change[R],
        reads: Reads,
        token: str,
        idempotency: Idempotency | None,
        mirrored: _Mirrored | None = None,
    ) -> tuple[R] | None:
        """Read (or take the mirrored state), compute, commit once; None when another writer came first."""
        if mirrored is not None:
            stamp, snapshot, results = mirrored.stamp, _Snapshot.of(mirrored), []
        else:
            with self._client.pipeline(transaction=True) as pipe:
                pipe.hmget(
                    self._key(session_id, "meta"),
                    ["static", "version", "updated_at", "look_alikes", "block_voxels"],
                )
                for command, key, *arguments in reads() if callable(reads) else reads:
                    getattr(pipe, command)(key, *arguments)
                (static_raw, version_raw, updated_at, look_alikes, block_voxels), *results = pipe.execute()
            if static_raw is None:
                msg = f"no session {session_id!r}"
                raise NotFound(msg)
            stamp = (int(version_raw), updated_at)
            look_alike_idx = np.frombuffer(look_alikes or b"", dtype="<i8")
            static = msgpack.unpackb(static_raw, raw=False)
            snapshot = _Snapshot(static, stamp[0] + 1, look_alike_idx, _block_voxels(block_voxels))
        writes, result = change(snapshot, results)
        commit = self._commit_of(session_id, stamp, snapshot.static, token, writes, result, idempotency)
        outcome = self._script("commit")(keys=commit.keys, args=commit.args)
        if not self._committed(session_id, outcome, commit, mirrored):
            return None
        self._refresh_index(session_id, snapshot.static["robot_id"], commit.now)
        return (result,)

    async def _attempt_from_mirror(
        self, session_id: str, change: Change[R], mirrored: _Mirrored, idempotency: Idempotency | None
    ) -> tuple[R] | None:
        """`_attempt` from the mirrored state, committed through the running event loop's client."""
        from redis.exceptions import ConnectionError as RedisConnectionError

        writes, result = change(_Snapshot.of(mirrored), [])
        commit = self._commit_of(session_id, mirrored.stamp, mirrored.static, "", writes, result, idempotency)
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
        await self._refresh_index_async(session_id, mirrored.static["robot_id"], commit.now)
        return (result,)

    def _commit_of(
        self,
        session_id: str,
        stamp: Stamp,
        static: dict[str, Any],
        token: str,
        writes: Writes,
        result: Any,
        idempotency: Idempotency | None,
    ) -> _Commit:
        """The `_COMMIT_SCRIPT` call for writes computed from the state named `stamp`, with the record of its
        idempotency key (the client's, else its own id)."""
        now = self._clock()
        commit_id = uuid.uuid4().hex
        key = f"k:{idempotency.key}" if idempotency is not None else f"c:{commit_id}"
        update = result if isinstance(result, UpdateResult) else UpdateResult(session_id, stamp[0] + 1, 0)
        update = dataclasses.replace(update, version=stamp[0] + 1)
        record = IdempotencyRecord.of(
            idempotency or Idempotency(key, ""), update, now, commit_id, static["robot_id"]
        )
        expiry = self._expiry_ms(now)
        keys = [self._key(session_id, part) for part in ("meta", "lock", "lang", "vis", "summary")]
        keys += [self._key(session_id, "idem"), self._key(session_id, "idem_at")]
        args: list[Any] = [stamp[0], stamp[1], token, repr(now), int(expiry) if math.isfinite(expiry) else ""]
        args += [key, record.pack(), int(now * 1000), self.idempotency_window_ms, self.idempotency_keys]
        args.append(len(writes))
        for hash_key, fields in writes.items():
            keys.append(hash_key)
            args.append(len(fields))
            for field_name, value in fields.items():
                args += [field_name, value]
        return _Commit(keys, args, commit_id, stamp, writes, now)

    def _committed(
        self, session_id: str, outcome: list[Any], commit: _Commit, mirrored: _Mirrored | None
    ) -> bool:
        """The commit script's outcome: True if it wrote, now or when sent before (the mirror then follows),
        False if another writer came first; NotFound if the session is gone, AlreadyApplied if the client's
        key was seen."""
        code = int(outcome[0])
        if code == -1:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        if code == -2:
            return False
        if code == -3:
            record = IdempotencyRecord.unpack(outcome[1])
            if record.commit != commit.commit_id:
                raise AlreadyApplied(record)
        stamp = commit.stamp
        base = mirrored or self._mirror.get(session_id, stamp)
        if base is not None:  # the mirror follows the commit (with the bytes Redis now holds)
            parts = {key.rsplit(":", 1)[1]: fields for key, fields in commit.writes.items()}
            self._mirror.put(session_id, base.after(parts, (stamp[0] + 1, repr(commit.now).encode())))
        return True

    # -- SessionStore ---------------------------------------------------------------------------------------

    @_redis_errors
    def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        check_session_id(session.id)
        now = self._clock()
        static = msgpack.packb(_static_meta(session), use_bin_type=True)
        sg = session.scene_graph.model_dump_json().encode()
        look_alikes = _look_alikes(session.grid, session.scene_graph, session.target_label)
        expiry = self._expiry_ms(now)
        robot_index = self._index_key(session.robot_id)
        if max_per_robot is not None:
            self._reserve(session.id, robot_index, now, max_per_robot)
        meta = {
            "static": static,
            "sg": sg,
            "look_alikes": look_alikes,
            "block_voxels": self.block_voxels,
            "version": session.version,
            "updated_at": repr(now),
        }
        parts = [meta]
        for layer in (session.belief.lang, session.belief.vis):
            parts.append(self._blocks_of(layer, self.block_voxels) if np.any(layer) else {})
        record = b""
        if idempotency is not None:
            result = UpdateResult(session.id, session.version, 0)
            record = IdempotencyRecord.of(idempotency, result, now, robot_id=session.robot_id).pack()
        args: list[Any] = [f"k:{idempotency.key}" if idempotency is not None else "", record, int(now * 1000)]
        args += [
            self.idempotency_window_ms,
            self.idempotency_keys,
            int(expiry) if math.isfinite(expiry) else "",
        ]
        for fields in parts:
            args.append(len(fields))
            for name, value in fields.items():
                args += [name, value]
        keys = [self._key(session.id, part) for part in ("meta", "lang", "vis", "summary", "idem", "idem_at")]
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
            _Mirrored(
                stamp,
                msgpack.unpackb(static, raw=False),
                np.frombuffer(look_alikes, dtype="<i8"),
                self.block_voxels,
                sg,
                session.belief.lang.astype(fusion.LAYER_DTYPE, copy=True),  # the caller keeps its session
                session.belief.vis.astype(fusion.LAYER_DTYPE, copy=True),
            ),
        )
        return dataclasses.replace(session.info(), updated_at=now)

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
                live.append((sid, msgpack.unpackb(static_raw, raw=False), version, updated_at))
            elif score < now_ms:  # expired or deleted; a newer score is a creation in flight
                gone.append(sid)
        if gone:
            self._client.zrem(index, *gone)
        return live

    def _read(self, session_id: str, parts: tuple[str, ...]) -> tuple[dict[bytes, bytes], ...]:
        """HGETALL of the given hashes in one transaction (a consistent view); NotFound without meta."""
        with self._client.pipeline(transaction=True) as pipe:
            for part in parts:
                pipe.hgetall(self._key(session_id, part))
            results = pipe.execute()
        if not results[0]:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        return tuple(results)

    def _read_state(self, session_id: str) -> _Mirrored:
        """The whole session in one transaction; it becomes the mirrored state."""
        meta, lang, vis = self._read(session_id, ("meta", "lang", "vis"))
        static = msgpack.unpackb(meta[b"static"], raw=False)
        n, b = int(np.prod(static["grid"]["shape"])), _block_voxels(meta.get(b"block_voxels"))
        state = _Mirrored(
            (int(meta[b"version"]), meta[b"updated_at"]),
            static,
            np.frombuffer(meta.get(b"look_alikes", b""), dtype="<i8"),
            b,
            meta[b"sg"],
            self._assemble(lang, n, b),
            self._assemble(vis, n, b),
        )
        self._mirror.put(session_id, state)
        return state

    @staticmethod
    def _session_from(state: _Mirrored) -> Session:
        version, updated_at = state.stamp
        full = {**state.static, "version": version, "updated_at": float(updated_at)}
        scene_graph = parse_scene_graph_json(state.scene_graph_json)
        return Session.from_meta(full, state.lang.copy(), state.vis.copy(), scene_graph=scene_graph)

    @_redis_errors
    def get(self, session_id: str) -> Session:
        return self._session_from(self._read_state(session_id))

    @_redis_errors
    def info(self, session_id: str) -> SessionInfo:
        static_raw, version, updated_at = self._client.hmget(
            self._key(session_id, "meta"), ["static", "version", "updated_at"]
        )
        if static_raw is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        return _info(session_id, msgpack.unpackb(static_raw, raw=False), version, updated_at)

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
                connection = await asyncio.to_thread(self._connect)
            kind: Any = RedisCluster if connection[2] else redis.asyncio.Redis
            wait = self._socket_timeout_s
            client = kind.from_url(self._url, socket_timeout=wait, socket_connect_timeout=wait)
            current = self._async = (loop, client, client.register_script(_COMMIT_SCRIPT))
        return current[1], current[2]

    async def owner_and_version(self, session_id: str) -> tuple[str, int]:
        from redis.exceptions import ConnectionError as RedisConnectionError
        from redis.exceptions import RedisError

        fields = (self._key(session_id, "meta"), ["static", "version"])
        try:
            try:
                static_raw, version = await (await self._async_client())[0].hmget(*fields)
            except RedisConnectionError:  # a pooled connection to a Redis that has restarted since: once more
                static_raw, version = await (await self._async_client())[0].hmget(*fields)
        except RedisError as exc:
            raise _unavailable(exc) from exc
        if static_raw is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        return str(msgpack.unpackb(static_raw, raw=False)["robot_id"]), int(version)

    @_redis_errors
    def scene_graph(self, session_id: str) -> SceneGraph:
        raw = self._client.hget(self._key(session_id, "meta"), "sg")
        if raw is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        return parse_scene_graph_json(raw)

    @_redis_errors
    def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        rows = self._live_ids(self._index_key(robot_id), self._clock())
        infos = [_info(sid, static, version, updated_at) for sid, static, version, updated_at in rows]
        return sorted(infos, key=lambda info: (info.created_at, info.id))

    @_redis_errors
    def delete(
        self, session_id: str, *, authorize: Authorize | None = None, idempotency: Idempotency | None = None
    ) -> None:
        meta_key, idem_key = self._key(session_id, "meta"), self._key(session_id, "idem")
        key = f"k:{idempotency.key}" if idempotency is not None else ""
        with self._client.pipeline(transaction=True) as pipe:
            pipe.hget(meta_key, "static")
            pipe.hget(idem_key, key or "-")
            static_raw, seen = pipe.execute()
        if seen is not None and key:
            earlier = IdempotencyRecord.unpack(seen)
            if authorize is not None:
                authorize(earlier.robot_id)
            raise AlreadyApplied(earlier)
        if static_raw is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        robot_id = msgpack.unpackb(static_raw, raw=False)["robot_id"]
        if authorize is not None:
            authorize(robot_id)
        now = self._clock()
        packed = b""
        if idempotency is not None:
            result = UpdateResult(session_id, 0, 0)
            packed = IdempotencyRecord.of(idempotency, result, now, robot_id=robot_id).pack()
        keys = [self._key(session_id, part) for part in ("meta", "lang", "vis", "summary", "idem", "idem_at")]
        args = [key, packed, int(now * 1000), self.idempotency_window_ms]
        outcome = self._script("delete")(keys=keys, args=args)
        if int(outcome[0]) == -3:
            raise AlreadyApplied(IdempotencyRecord.unpack(outcome[1]))
        if int(outcome[0]) == -1:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        self._client.zrem(self._index_key(), session_id)
        self._client.zrem(self._index_key(robot_id), session_id)
        self._mirror.drop(session_id)

    @_redis_errors
    def replace_scene_graph(
        self, session_id: str, scene_graph: SceneGraph, *, idempotency: Idempotency | None = None
    ) -> int:
        sg_json = scene_graph.model_dump_json()
        meta_key = self._key(session_id, "meta")

        def change(meta: _Snapshot, _: list[Any]) -> tuple[Writes, int]:
            grid = VoxelGrid.from_dict(meta.static["grid"])
            look_alikes = _look_alikes(grid, scene_graph, meta.static["target_label"])
            return {meta_key: {"sg": sg_json, "look_alikes": look_alikes}}, meta.new_version

        return self._update(session_id, change, idempotency=idempotency)

    def _target_writes(self, meta: _Snapshot, label: str, scene_graph_json: bytes) -> dict[str, bytes]:
        """The meta hash's fields once the target class is `label` (checked against the label map)."""
        label_map = {int(k): str(v) for k, v in meta.static["label_map"]}
        check_target_label(label, label_map)
        packed = msgpack.packb({**meta.static, "target_label": label}, use_bin_type=True)
        scene_graph = parse_scene_graph_json(scene_graph_json)
        look_alikes = _look_alikes(VoxelGrid.from_dict(meta.static["grid"]), scene_graph, label)
        return {"static": packed, "look_alikes": look_alikes}

    @_redis_errors
    def set_target_label(self, session_id: str, label: str) -> int:
        meta_key = self._key(session_id, "meta")

        def change(meta: _Snapshot, read: list[Any]) -> tuple[Writes, int]:
            raw = read[0] if meta.mirror is None else meta.mirror.scene_graph_json
            return {meta_key: self._target_writes(meta, label, raw)}, meta.new_version

        return self._update(session_id, change, reads=[("hget", meta_key, "sg")])

    @_redis_errors
    def apply_utterance(
        self,
        session_id: str,
        mixture: GaussianMixture,
        *,
        target_label: str | None = None,
        idempotency: Idempotency | None = None,
    ) -> UpdateResult:
        mixture = float64_mixture(mixture)
        lang_key, meta_key = self._key(session_id, "lang"), self._key(session_id, "meta")

        def change(meta: _Snapshot, read: list[Any]) -> tuple[Writes, UpdateResult]:
            grid = VoxelGrid.from_dict(meta.static["grid"])
            if meta.mirror is not None:
                lang = meta.mirror.lang.copy()
            else:
                lang = self._assemble(read[0], grid.n_voxels, meta.block_voxels)
            span = fusion.LayerLimits(**meta.static["limits"]).lang_span
            fusion.apply_language(lang, language_log_likelihood(grid, mixture), span)
            writes: Writes = {lang_key: self._blocks_of(lang, meta.block_voxels)}
            if target_label and not meta.static["target_label"]:
                raw = read[1] if meta.mirror is None else meta.mirror.scene_graph_json
                writes[meta_key] = self._target_writes(meta, target_label, raw)
            return writes, UpdateResult(session_id, meta.new_version, grid.n_voxels)

        reads: list[Read] = [("hgetall", lang_key)]
        if target_label:
            reads.append(("hget", meta_key, "sg"))
        return self._update(session_id, change, reads=reads, idempotency=idempotency)

    def _observer(self, static: dict[str, Any], look_alikes: np.ndarray) -> ObservationModel:
        return ObservationModel(
            VoxelGrid.from_dict(static["grid"]),
            static["target_label"],
            {int(k): str(v) for k, v in static["label_map"]},
            SensorModel(**static["sensor_model"]),
            look_alikes,
        )

    def _batch_update(
        self,
        session_id: str,
        make_batch: Callable[[ObservationModel], IncrementBatch],
        flat_idx: np.ndarray | None,
        voxels: np.ndarray | None,
        authorize: Authorize | None,
    ) -> tuple[Change[UpdateResult], Callable[[], Sequence[Read]]]:
        """The change an observation or detection batch makes, and the reads it needs when it reads."""
        vis_key = self._key(session_id, "vis")
        guess = self.block_voxels
        # A session's grid never changes: the mirror's names it even after the entry goes stale (and is
        # dropped by the failed commit that sends the update to read).
        known = self._mirror.get(session_id) if voxels is not None else None
        shape = tuple(known.static["grid"]["shape"]) if known is not None else None

        @functools.cache
        def prefetch() -> tuple[str, ...]:
            """The blocks (as sized for new sessions) that a read attempt fetches with the meta hash: those
            of the flat indices, or of the voxel coordinates on the grid the mirror knew. Computed only if
            an attempt reads: an update from the mirror reads nothing."""
            idx = np.asarray(flat_idx if flat_idx is not None else [])
            ijk = np.asarray(voxels if voxels is not None else [])
            if shape is not None and ijk.ndim == 2 and ijk.shape[1:] == (3,) and ijk.dtype.kind in "iu":
                inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
                idx = np.ravel_multi_index(tuple(ijk[inside].T), shape)
            if not (idx.ndim == 1 and idx.dtype.kind in "iu" and len(idx) > 0 and idx.min() >= 0):
                return ()  # none to guess, or a batch the update will refuse
            return tuple(str(i) for i in np.flatnonzero(np.bincount(idx // guess)))

        def reads() -> list[Read]:
            return [("hmget", vis_key, list(prefetch()))] if prefetch() else []

        def change(meta: _Snapshot, read: list[Any]) -> tuple[Writes, UpdateResult]:
            if authorize is not None:
                authorize(meta.static["robot_id"])
            observer = self._observer(meta.static, meta.look_alikes)
            limits = fusion.LayerLimits(**meta.static["limits"])
            batch = make_batch(observer)
            n, b = observer.grid.n_voxels, meta.block_voxels
            touched = np.flatnonzero(np.bincount(batch.flat_idx // b, minlength=_n_blocks(n, b)))  # (T,)
            names = [str(i) for i in touched]
            local = np.zeros(len(touched) * b, dtype=fusion.LAYER_DTYPE)  # touched blocks side by side
            if meta.mirror is not None:
                for slot, i in enumerate(touched):
                    block = meta.mirror.vis[int(i) * b : (int(i) + 1) * b]
                    local[slot * b : slot * b + len(block)] = block
            else:
                fetched = prefetch()
                stored = dict(zip(fetched, read[0], strict=True)) if fetched and b == guess else {}
                missing = [name for name in names if name not in stored]
                if missing:  # unguessed, or an older block size; a concurrent change fails the commit
                    stored.update(zip(missing, self._client.hmget(vis_key, missing), strict=True))
                for slot, name in enumerate(names):
                    data = stored[name]
                    if data is not None:
                        local[slot * b : slot * b + len(data) // 4] = np.frombuffer(data, dtype="<f4")
            slot_of = np.zeros(_n_blocks(n, b), dtype=np.int64)
            slot_of[touched] = np.arange(len(touched))
            local_idx = slot_of[batch.flat_idx // b] * b + batch.flat_idx % b
            fusion.apply_increments(local, local_idx, batch.increments, limits.vis_min, limits.vis_max)
            blocks = {}
            for slot, i in enumerate(touched):
                length = min(b, n - int(i) * b)
                blocks[names[slot]] = local[slot * b : slot * b + length].tobytes()
            result = UpdateResult(session_id, meta.new_version, len(batch.flat_idx), batch.n_outside)
            return ({vis_key: blocks} if blocks else {}), result

        return change, reads

    def _apply_batch(self, session_id: str, update: BatchUpdate) -> UpdateResult:
        change, reads, idempotency = update
        return self._update(session_id, change, reads=reads, idempotency=idempotency)

    async def _apply_batch_async(self, session_id: str, update: BatchUpdate) -> UpdateResult:
        """`_apply_batch` for a caller on an event loop: from the mirror it computes there and commits with
        the loop's client (no worker thread); otherwise, or when another writer came first, it runs the
        reading update on a worker thread."""
        from redis.exceptions import RedisError

        change, reads, idempotency = update
        mirrored = self._mirror.get(session_id)
        if mirrored is not None:
            try:
                committed = await self._attempt_from_mirror(session_id, change, mirrored, idempotency)
            except RedisError as exc:
                raise _unavailable(exc) from exc
            if committed is not None:
                return committed[0]
            self._mirror.drop(session_id, mirrored.stamp)  # another writer came first: read from now on
        update_ = functools.partial(self._update, session_id, change, reads, idempotency)
        return await asyncio.to_thread(_redis_errors(update_))

    def _observations(
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
    ) -> BatchUpdate:
        """`apply_observations`'s update (its arguments are those of `SessionStore.apply_observations`)."""
        make = functools.partial(
            ObservationModel.observation_batch,
            labels=labels,
            points=points,
            flat_idx=flat_idx,
            voxels=voxels,
            tp=tp,
            fp=fp,
            max_voxels=self.max_batch_voxels,
        )
        return (*self._batch_update(session_id, make, flat_idx, voxels, authorize), idempotency)

    def _detections(
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
    ) -> BatchUpdate:
        """`apply_detections`'s update (its arguments are those of `SessionStore.apply_detections`)."""
        make = functools.partial(
            ObservationModel.detection_batch,
            p_target=p_target,
            points=points,
            flat_idx=flat_idx,
            voxels=voxels,
            prior=prior,
            max_voxels=self.max_batch_voxels,
        )
        return (*self._batch_update(session_id, make, flat_idx, voxels, authorize), idempotency)

    @_redis_errors
    def apply_observations(self, session_id: str, labels: Any, **kwargs: Any) -> UpdateResult:
        return self._apply_batch(session_id, self._observations(session_id, labels, **kwargs))

    @_redis_errors
    def apply_detections(self, session_id: str, p_target: np.ndarray, **kwargs: Any) -> UpdateResult:
        return self._apply_batch(session_id, self._detections(session_id, p_target, **kwargs))

    async def apply_observations_async(self, session_id: str, labels: Any, **kwargs: Any) -> UpdateResult:
        return await self._apply_batch_async(session_id, self._observations(session_id, labels, **kwargs))

    async def apply_detections_async(
        self, session_id: str, p_target: np.ndarray, **kwargs: Any
    ) -> UpdateResult:
        return await self._apply_batch_async(session_id, self._detections(session_id, p_target, **kwargs))

    @_redis_errors
    def read_layers(self, session_id: str) -> BeliefState:
        state = self._read_state(session_id)
        grid = VoxelGrid.from_dict(state.static["grid"])
        limits = fusion.LayerLimits(**state.static["limits"])
        return BeliefState(grid, limits, state.lang.copy(), state.vis.copy(), state.stamp[0])

    @_redis_errors
    def summary(self, session_id: str, **kwargs: Any) -> PosteriorSummary:
        """The current version's summary: the stored one if some replica already computed it, else computed
        from the layers and stored for the others."""
        meta_key, summary_key = self._key(session_id, "meta"), self._key(session_id, "summary")
        options = json.dumps(kwargs, sort_keys=True)
        with self._client.pipeline(transaction=False) as pipe:
            pipe.hmget(meta_key, ["version", "updated_at"])
            pipe.hget(summary_key, options)
            pipe.pttl(meta_key)
            (version, updated_at), stored, ttl_ms = pipe.execute()
        if version is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        if stored is not None:
            entry = msgpack.unpackb(stored, raw=False)
            if entry["version"] == int(version):
                return PosteriorSummary.from_dict(entry["summary"], version=entry["version"])
        # The version this replica wrote or read last is in the mirror: no need to read the belief back.
        state = self._mirror.get(session_id, (int(version), updated_at)) or self._read_state(session_id)
        summary = summarize(
            VoxelGrid.from_dict(state.static["grid"]),
            state.lang,
            state.vis,
            parse_scene_graph_json(state.scene_graph_json),
            scene_fingerprint=json_fingerprint(state.scene_graph_json),  # stored as model_dump_json gave it
            **kwargs,
        )
        # A slower replica may overwrite a newer entry with an older one; readers then recompute (harmless).
        entry = {"version": state.stamp[0], "summary": summary.to_dict()}
        with self._client.pipeline(transaction=False) as pipe:
            pipe.hset(summary_key, options, msgpack.packb(entry, use_bin_type=True))
            if ttl_ms > 0:
                pipe.pexpire(summary_key, ttl_ms)
            pipe.execute()
        return dataclasses.replace(summary, version=state.stamp[0])

    @_redis_errors
    def purge_expired(self) -> int:
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

    def close(self) -> None:
        if self._connection is not None:
            self._connection[0].close()

    def __enter__(self) -> RedisSessionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
