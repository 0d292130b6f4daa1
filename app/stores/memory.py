"""Sessions in process memory, optionally made durable by a write-ahead log and per-session snapshots.

Durability (when `data_dir` is given). Every update is first appended to an append-only log as its
*delta* (`app.stores.base.Delta`: the utterance's mixture parameters, from which replay recomputes its
term; the batch's voxel indices and increments; the new scene graph; the new target label), each record
framed as [u32 length][u32 crc32][msgpack
payload] and stamped with a log sequence number (LSN); the file is fsync'd before the update is applied in
memory and acknowledged. So a `kill -9` at any moment loses nothing that was acknowledged: a crash
mid-append leaves a torn last record, which the next start recognises (short header, short payload or bad
crc), ignores and cuts off.

Compaction. After `snapshot_every` records or `snapshot_bytes` of log, the log rolls over to a new
segment; every session changed since its last snapshot is written to `sessions/<id>.snap` (meta + layers +
the LSN it includes) through a temporary file, fsync and rename; then the old segments are deleted. On
start, snapshots are loaded and the segments replayed in order, skipping records a session's snapshot
already includes (LSN <= its snapshot's), which makes a crash anywhere inside compaction harmless.

Layout of `data_dir`: `LOCK` (flock: one process per directory), `wal-<seq>.log`, `sessions/<id>.snap`.

Idempotency-Keys (`app.stores.base`) travel in the record of the update they came with (`idem`), and in the
snapshot of their session; a deleted session's keys stay (a tombstone) for the window: its delete record
holds them, and each compaction logs the tombstones still in their window again.

Locking: a lock per session serialises its updates (log append + apply happen under it, so the log order
is the apply order); a registry lock guards the id -> session map; the log has its own lock. Lock order:
session, then registry, then log. What may wait on a lock or the disk runs on a worker thread; an inline
change of a store without a log runs on the caller's event loop when its session's lock is free.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator, Mapping
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import anyio.to_thread
import msgpack
import numpy as np

from app.belief.grid import VoxelGrid
from app.belief.session import (
    IncrementBatch,
    ObservationModel,
    Session,
    SessionInfo,
    UpdateResult,
    language_log_likelihood,
)
from app.errors import InvalidInput, NotFound, StoreUnavailable
from app.scene_graph.model import SceneGraph
from app.stores.base import (
    DEFAULT_IDEMPOTENCY_KEYS,
    DEFAULT_IDEMPOTENCY_WINDOW_S,
    DEFAULT_TTL_S,
    Change,
    Delta,
    Idempotency,
    IdempotencyLog,
    IdempotencyRecord,
    LanguageDelta,
    MetaDelta,
    apply_delta,
    check_session_id,
    compact_indices,
    next_language_layer,
    pack_array,
    pack_mixture,
    session_limit_error,
    unpack_array,
    unpack_mixture,
)
from app.stores.events import MemoryEventLog, describe
from app.stores.recording import thin

T = TypeVar("T")

log = logging.getLogger(__name__)

#: Records between compactions.
DEFAULT_SNAPSHOT_EVERY = 1000
#: Log bytes between compactions (observation batches are large: 100k voxels make an 800 kB record).
DEFAULT_SNAPSHOT_BYTES = 256 * 2**20

_HEADER = struct.Struct("<II")  # payload length, crc32 of the payload
_SNAPSHOT_DIR = "sessions"


class _Entry:
    """A live session with its lock, the Idempotency-Keys it remembers and the LSNs of its last logged update
    and of its last snapshot."""

    __slots__ = ("deleted", "keys", "lock", "lsn", "session", "snap_lsn")

    def __init__(self, session: Session, keys: IdempotencyLog, lsn: int = 0, snap_lsn: int = 0) -> None:
        self.session = session
        self.keys = keys
        self.lock = threading.Lock()
        self.lsn = lsn
        self.snap_lsn = snap_lsn
        self.deleted = False


def _packed_keys(items: list[tuple[str, IdempotencyRecord]]) -> list[list[Any]]:
    return [[key, record.pack()] for key, record in items]


def _idem_field(idempotency: Idempotency | None, record: IdempotencyRecord | None) -> dict[str, Any]:
    """The `idem` field of a log record: the key and what it remembers (nothing without a key)."""
    if idempotency is None or record is None:
        return {}
    return {"idem": [idempotency.key, record.pack()]}


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _segment_seq(path: Path) -> int:
    return int(path.stem.removeprefix("wal-"))


class _WriteAheadLog:
    """Numbered append-only segments of framed msgpack records; `append` returns once it is on disk."""

    def __init__(self, directory: Path, next_seq: int, next_lsn: int) -> None:
        self.directory = directory
        self.lock = threading.Lock()
        self.next_lsn = next_lsn
        self.records = 0  # since the last rotation
        self.bytes = 0
        self._broken: str | None = None
        self._seq = next_seq
        self._file = self._open_segment()

    def _open_segment(self) -> BinaryIO:
        handle = (self.directory / f"wal-{self._seq:08d}.log").open("ab")
        _fsync_dir(self.directory)
        return handle

    def append(self, record: dict[str, Any]) -> int:
        with self.lock:
            if self._broken:
                msg = f"the session log cannot be written: {self._broken}"
                raise StoreUnavailable(msg)
            lsn = self.next_lsn
            payload = msgpack.packb({**record, "lsn": lsn}, use_bin_type=True)
            frame = _HEADER.pack(len(payload), zlib.crc32(payload)) + payload
            start = self._file.tell()
            try:
                self._file.write(frame)
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as exc:
                self._undo(start, exc)
                msg = f"the session log cannot be written: {exc}"
                raise StoreUnavailable(msg) from exc
            self.next_lsn += 1
            self.records += 1
            self.bytes += len(frame)
            return lsn

    def _undo(self, start: int, exc: OSError) -> None:
        """Cut a half-written record off, or refuse all further appends if that fails too."""
        try:
            self._file.truncate(start)
            self._file.seek(start)
            os.fsync(self._file.fileno())
        except OSError:
            self._broken = str(exc)

    def rotate(self) -> list[Path]:
        """Start a new segment; returns the older segments (whose records all have smaller LSNs)."""
        with self.lock:
            self._seq += 1
            try:
                new_file = self._open_segment()
            except OSError:
                self._seq -= 1  # keep appending to the current segment
                raise
            self._file.close()
            self._file = new_file
            self.records = self.bytes = 0
            return sorted(
                (p for p in self.directory.glob("wal-*.log") if _segment_seq(p) < self._seq), key=_segment_seq
            )

    def close(self) -> None:
        with self.lock:
            self._file.close()


def _read_segment(path: Path, tolerate_torn_tail: bool) -> Iterator[dict[str, Any]]:
    """Records of one segment; a torn last record is cut off (if tolerated) or raises."""
    data = path.read_bytes()
    offset = 0
    while offset < len(data):
        torn = offset + _HEADER.size > len(data)
        if not torn:
            length, crc = _HEADER.unpack_from(data, offset)
            payload = data[offset + _HEADER.size : offset + _HEADER.size + length]
            torn = len(payload) < length or zlib.crc32(payload) != crc
        if torn:
            if not tolerate_torn_tail:
                msg = f"session log {path} is corrupt at byte {offset} (not its last segment)"
                raise StoreUnavailable(msg)
            log.warning("session log %s: ignoring a torn record at byte %d (crash mid-write)", path, offset)
            with path.open("r+b") as fh:
                fh.truncate(offset)
                os.fsync(fh.fileno())
            return
        yield msgpack.unpackb(payload, raw=False)
        offset += _HEADER.size + length


class MemorySessionStore:
    """Thread-safe in-memory sessions, durable across crashes when `data_dir` is given (module docstring)."""

    def __init__(
        self,
        data_dir: Path | str | None = None,
        *,
        ttl_s: float | None = DEFAULT_TTL_S,
        snapshot_every: int = DEFAULT_SNAPSHOT_EVERY,
        snapshot_bytes: int = DEFAULT_SNAPSHOT_BYTES,
        idempotency_window_s: float = DEFAULT_IDEMPOTENCY_WINDOW_S,
        idempotency_keys: int = DEFAULT_IDEMPOTENCY_KEYS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.ttl_s = ttl_s
        self.snapshot_every = snapshot_every
        self.snapshot_bytes = snapshot_bytes
        self.idempotency_window_s = idempotency_window_s
        self.idempotency_keys = idempotency_keys
        self._clock = clock
        self.events = MemoryEventLog()
        self._entries: dict[str, _Entry] = {}
        # session id -> its recording's packed frames (process memory only: app.sessions.recording)
        self._recordings: dict[str, list[bytes]] = {}
        # deleted sessions' ids -> (robot id, the keys they remembered, their delete's among them)
        self._tombstones: dict[str, tuple[str, IdempotencyLog]] = {}
        self._registry_lock = threading.Lock()
        self._compact_lock = threading.Lock()
        self._closed = False
        self._dir = Path(data_dir) if data_dir is not None else None
        self._wal: _WriteAheadLog | None = None
        self._lock_file: BinaryIO | None = None
        if self._dir is not None:
            try:
                self._open_durable(self._dir)
            except OSError as exc:
                msg = f"cannot open the session data directory {self._dir}: {exc}"
                raise StoreUnavailable(msg) from exc
        self._purge_expired()

    # -- durability -----------------------------------------------------------------------------------------

    def _open_durable(self, directory: Path) -> None:
        (directory / _SNAPSHOT_DIR).mkdir(parents=True, exist_ok=True)
        self._lock_file = (directory / "LOCK").open("ab")
        try:
            fcntl.flock(self._lock_file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            self._lock_file.close()
            msg = f"the session data directory {directory} is in use by another store"
            raise StoreUnavailable(msg) from exc
        for tmp in (directory / _SNAPSHOT_DIR).glob("*.tmp"):
            tmp.unlink()
        last_lsn = 0
        for path in (directory / _SNAPSHOT_DIR).glob("*.snap"):
            snap = msgpack.unpackb(path.read_bytes(), raw=False)
            session = Session.from_meta(snap["meta"], unpack_array(snap["lang"]), unpack_array(snap["vis"]))
            keys = self._keys(snap.get("idem", []))
            self._entries[session.id] = _Entry(session, keys, snap["lsn"], snap["lsn"])
            last_lsn = max(last_lsn, snap["lsn"])
        segments = sorted(directory.glob("wal-*.log"), key=_segment_seq)
        replayed = 0
        for number, path in enumerate(segments):
            for record in _read_segment(path, tolerate_torn_tail=number == len(segments) - 1):
                self._replay(record)
                last_lsn = max(last_lsn, record["lsn"])
                replayed += 1
        next_seq = _segment_seq(segments[-1]) + 1 if segments else 1
        self._wal = _WriteAheadLog(directory, next_seq, last_lsn + 1)
        if not replayed:
            for segment in segments:  # empty segments of earlier starts
                segment.unlink()
        else:
            log.info(
                "session store %s: %d sessions, %d log records replayed",
                directory,
                len(self._entries),
                replayed,
            )
            self._compact()

    def _keys(self, packed: list[list[Any]] | None = None) -> IdempotencyLog:
        keys = IdempotencyLog(self.idempotency_window_s, self.idempotency_keys)
        for key, record in packed or []:
            keys.add(key, IdempotencyRecord.unpack(record))
        return keys

    def _replay(self, record: dict[str, Any]) -> None:
        sid, lsn, op = record["sid"], record["lsn"], record["op"]
        entry = self._entries.get(sid)
        if op == "tombstone" or (op == "delete" and "keys" in record):
            self._tombstones[sid] = (record["robot"], self._keys(record.get("keys", [])))
            if "idem" in record:
                self._tombstones[sid][1].add(record["idem"][0], IdempotencyRecord.unpack(record["idem"][1]))
        if op == "tombstone":
            return
        if op == "create":
            if entry is not None and entry.lsn >= lsn:
                return  # the snapshot already holds this incarnation
            lang = unpack_array(record["lang"]) if "lang" in record else None
            vis = unpack_array(record["vis"]) if "vis" in record else None
            keys = self._keys()
            self._entries[sid] = _Entry(Session.from_meta(record["meta"], lang, vis), keys, lsn)
            self._tombstones.pop(sid, None)
            if "idem" in record:
                keys.add(record["idem"][0], IdempotencyRecord.unpack(record["idem"][1]))
            return
        if entry is None or entry.lsn >= lsn:
            return  # deleted later, or already in the snapshot
        if op == "delete":
            del self._entries[sid]
            return
        if "idem" in record:
            entry.keys.add(record["idem"][0], IdempotencyRecord.unpack(record["idem"][1]))
        session = entry.session
        delta = _delta_of(record, session)
        lang = next_language_layer(session, delta.language) if delta.language is not None else None
        apply_delta(session, delta, lang, record["t"])
        entry.lsn = lsn

    def _append(self, record: dict[str, Any]) -> int:
        """Log a record (durably) and return its LSN; 0 without a data directory."""
        return self._wal.append(record) if self._wal is not None else 0

    def _maybe_compact(self) -> None:
        wal = self._wal
        if wal is not None and (wal.records >= self.snapshot_every or wal.bytes >= self.snapshot_bytes):
            self._compact()

    def _compact(self) -> None:
        """Snapshot every session changed since its last snapshot, then drop the log segments before now."""
        if self._wal is None or self._dir is None or not self._compact_lock.acquire(blocking=False):
            return
        try:
            old_segments = self._wal.rotate()
            self._log_tombstones()
            with self._registry_lock:
                entries = list(self._entries.values())
            snap_dir = self._dir / _SNAPSHOT_DIR
            written = []
            for entry in entries:
                with entry.lock:
                    if entry.deleted or entry.lsn <= entry.snap_lsn:
                        continue
                    lsn, payload = entry.lsn, self._snapshot_bytes(entry)
                path = snap_dir / f"{entry.session.id}.snap"
                tmp = path.with_suffix(".tmp")
                with tmp.open("wb") as fh:
                    fh.write(payload)
                    fh.flush()
                    os.fsync(fh.fileno())
                tmp.replace(path)
                written.append((entry, lsn, path))
            _fsync_dir(snap_dir)
            for entry, lsn, path in written:
                with entry.lock:
                    if entry.deleted:  # deleted while we wrote: its delete removed nothing or an older file
                        path.unlink(missing_ok=True)
                    else:
                        entry.snap_lsn = max(entry.snap_lsn, lsn)
            _fsync_dir(snap_dir)
            for segment in old_segments:
                segment.unlink()
            _fsync_dir(self._dir)
        except OSError:
            log.exception("session store compaction failed; the log keeps growing until the next attempt")
        finally:
            self._compact_lock.release()

    def _log_tombstones(self) -> None:
        """Log again, into the segment just started, the deleted sessions' keys still in their window (the
        segments that held their delete records are about to go)."""
        now = self._clock()
        with self._registry_lock:
            tombstones = list(self._tombstones.items())
        for sid, (robot_id, keys) in tombstones:
            live = keys.live(now)
            if not live:
                with self._registry_lock:
                    self._tombstones.pop(sid, None)
                continue
            self._append(
                {"op": "tombstone", "sid": sid, "t": now, "robot": robot_id, "keys": _packed_keys(live)}
            )

    @staticmethod
    def _snapshot_bytes(entry: _Entry) -> bytes:
        session = entry.session
        snap = {
            "lsn": entry.lsn,
            "meta": session.meta(),
            "lang": pack_array(session.belief.lang),
            "vis": pack_array(session.belief.vis),
            "idem": _packed_keys(entry.keys.items()),
        }
        packed: bytes = msgpack.packb(snap, use_bin_type=True)
        return packed

    # -- sessions -------------------------------------------------------------------------------------------

    def _expired(self, session: Session, now: float) -> bool:
        return self.ttl_s is not None and now - session.updated_at > self.ttl_s

    def _check_open(self) -> None:
        if self._closed:
            msg = "the session store is closed"
            raise StoreUnavailable(msg)

    def _entry(self, session_id: str) -> _Entry:
        self._check_open()
        with self._registry_lock:
            entry = self._entries.get(session_id)
        if entry is None:
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        if self._expired(entry.session, self._clock()):
            self._remove(entry)
            msg = f"no session {session_id!r} (expired)"
            raise NotFound(msg)
        return entry

    @contextlib.contextmanager
    def _locked(self, session_id: str) -> Iterator[_Entry]:
        entry = self._entry(session_id)
        with entry.lock:
            if entry.deleted:
                msg = f"no session {session_id!r}"
                raise NotFound(msg)
            yield entry

    async def _off_loop(self, func: Callable[[], T]) -> T:
        """Run on a worker thread: what waits for a session's lock or appends to the log."""
        return await anyio.to_thread.run_sync(func)

    def _remove(
        self, entry: _Entry, idempotency: Idempotency | None = None, *, announce: bool = False
    ) -> bool:
        """Log the deletion and forget the session; False if someone else removed it first. A delete
        (`announce`) leaves the session's keys and its own, if any, as a tombstone: a retry of the session's
        creation or of the delete is then applied once. `announce`: publish its "deleted" event (an expiry
        has none, as on Redis, where keys expire by themselves)."""
        with entry.lock:
            if entry.deleted:
                return False
            now = self._clock()
            entry.keys.check(idempotency, now)
            record: dict[str, Any] = {"op": "delete", "sid": entry.session.id, "t": now}
            tombstone = idempotency is not None or (announce and bool(entry.keys.items()))
            if tombstone:
                record |= {"robot": entry.session.robot_id, "keys": _packed_keys(entry.keys.items())}
            remembered = None
            if idempotency is not None:
                result = UpdateResult(entry.session.id, entry.session.version, 0)
                remembered = IdempotencyRecord.of(idempotency, result, now, robot_id=entry.session.robot_id)
                record |= _idem_field(idempotency, remembered)
            self._append(record)
            if idempotency is not None and remembered is not None:
                entry.keys.add(idempotency.key, remembered)
            if tombstone:
                with self._registry_lock:
                    # Tombstones whose keys have all left the window go here too: without a data directory
                    # no compaction would ever drop them.
                    for gone in [t for t, (_, keys) in self._tombstones.items() if not keys.live(now)]:
                        del self._tombstones[gone]
                    self._tombstones[entry.session.id] = (entry.session.robot_id, entry.keys)
            entry.deleted = True
            if announce:
                self._publish(entry.session, {"kind": "deleted"}, now, last=True)
            else:  # an expiry has no event, but its history goes as a deletion's does
                self.events.forget(entry.session.id)
            if self._dir is not None:
                (self._dir / _SNAPSHOT_DIR / f"{entry.session.id}.snap").unlink(missing_ok=True)
            with self._registry_lock:
                if self._entries.get(entry.session.id) is entry:
                    del self._entries[entry.session.id]
                    self._recordings.pop(entry.session.id, None)
        return True

    def _create(
        self, session: Session, max_per_robot: int | None, idempotency: Idempotency | None
    ) -> SessionInfo:
        self._check_open()
        check_session_id(session.id)
        stored = session.copy()
        now = self._clock()
        stored.updated_at = now
        while True:
            with self._registry_lock:
                existing = self._entries.get(stored.id)
                if existing is None:
                    tombstone = self._tombstones.get(stored.id)
                    if tombstone is not None:  # a retry of a deleted session's creation is not applied again
                        tombstone[1].check(idempotency, now)
                    # Counted and created under the registry lock: parallel creations cannot pass the limit.
                    if max_per_robot is not None:
                        live = sum(
                            e.session.robot_id == stored.robot_id and not self._expired(e.session, now)
                            for e in self._entries.values()
                        )
                        if live >= max_per_robot:
                            raise session_limit_error(stored.robot_id, max_per_robot)
                    record: dict[str, Any] = {
                        "op": "create",
                        "sid": stored.id,
                        "t": now,
                        "meta": stored.meta(),
                    }
                    for name, layer in (("lang", stored.belief.lang), ("vis", stored.belief.vis)):
                        if np.any(layer):
                            record[name] = pack_array(layer)
                    keys = self._keys()
                    remembered = None
                    if idempotency is not None:
                        result = UpdateResult(stored.id, stored.version, 0)
                        remembered = IdempotencyRecord.of(idempotency, result, now, robot_id=stored.robot_id)
                        record |= _idem_field(idempotency, remembered)
                    # Logged under the registry lock: a compaction listing sessions after its log cut sees
                    # every session whose creation precedes the cut.
                    self._entries[stored.id] = _Entry(stored, keys, self._append(record))
                    self._publish(stored, {"kind": "created"}, now)
                    self._tombstones.pop(stored.id, None)
                    if idempotency is not None and remembered is not None:
                        keys.add(idempotency.key, remembered)
                    break
            if not self._expired(existing.session, now):
                with existing.lock:
                    existing.keys.check(idempotency, now)
                msg = f"a session with id {stored.id!r} exists"
                raise InvalidInput(msg, "id")
            self._remove(existing)
        self._maybe_compact()
        return stored.info()

    async def create(
        self, session: Session, *, max_per_robot: int | None = None, idempotency: Idempotency | None = None
    ) -> SessionInfo:
        return await self._off_loop(partial(self._create, session, max_per_robot, idempotency))

    def _head(self, session_id: str) -> _Entry:
        """The live entry, without its lock (an update may hold that for milliseconds, and this runs on the
        event loop): what it holds is read as before or after a concurrent update. Expired sessions are left
        for the next locked read or the purge to remove (that writes the log)."""
        self._check_open()
        with self._registry_lock:
            entry = self._entries.get(session_id)
        if entry is None or entry.deleted or self._expired(entry.session, self._clock()):
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        return entry

    async def head(self, session_id: str) -> SessionInfo:
        return self._head(session_id).session.info()

    async def head_and_scene_graph(self, session_id: str) -> tuple[SessionInfo, SceneGraph]:
        session = self._head(session_id).session
        return session.info(), session.scene_graph  # replaced whole, never changed in place

    def _load(self, session_id: str) -> Session:
        with self._locked(session_id) as entry:
            return entry.session.copy()

    async def load(self, session_id: str) -> Session:
        return await self._off_loop(partial(self._load, session_id))

    async def summary_get(self, session_id: str, version: int, options: str) -> dict[str, Any] | None:
        return None  # one process: its own summary cache is the only one

    async def summary_put(self, session_id: str, version: int, options: str, summary: dict[str, Any]) -> None:
        return None

    def _list(self, robot_id: str | None) -> list[SessionInfo]:
        self._check_open()
        self._purge_expired()
        with self._registry_lock:
            sessions = [e.session for e in self._entries.values()]
        infos = [s.info() for s in sessions if robot_id is None or s.robot_id == robot_id]
        return sorted(infos, key=lambda info: (info.created_at, info.id))

    async def list(self, robot_id: str | None = None) -> list[SessionInfo]:
        return await self._off_loop(partial(self._list, robot_id))

    def _delete(self, session_id: str, idempotency: Idempotency | None) -> None:
        try:
            entry = self._entry(session_id)
        except NotFound:
            self._check_tombstone(session_id, idempotency)
            raise
        if not self._remove(entry, idempotency, announce=True):
            self._check_tombstone(session_id, idempotency)
            msg = f"no session {session_id!r}"
            raise NotFound(msg)
        self._maybe_compact()

    async def delete(self, session_id: str, *, idempotency: Idempotency | None = None) -> None:
        await self._off_loop(partial(self._delete, session_id, idempotency))

    def _check_tombstone(self, session_id: str, idempotency: Idempotency | None) -> None:
        """AlreadyApplied if a deleted session remembers the key."""
        with self._registry_lock:
            tombstone = self._tombstones.get(session_id)
            if tombstone is not None and idempotency is not None:
                tombstone[1].check(idempotency, self._clock())

    def _update_locked(self, entry: _Entry, change: Change, idempotency: Idempotency | None) -> UpdateResult:
        """Check the key, compute the delta, log it, then apply it (the session's lock is held)."""
        session = entry.session
        now = self._clock()
        entry.keys.check(idempotency, now)
        delta = change.compute(_View(session))
        # Everything that can refuse the change runs before it is logged: a logged change always applies.
        lang = next_language_layer(session, delta.language) if delta.language is not None else None
        result = delta.result(session.id, session.version + 1, session.grid.n_voxels)
        remembered = None
        if idempotency is not None:
            remembered = IdempotencyRecord.of(idempotency, result, now, robot_id=session.robot_id)
        if self._wal is not None:
            record = _record_of(delta, session) | {"op": "delta", "sid": session.id, "t": now}
            entry.lsn = self._append(record | _idem_field(idempotency, remembered))
        if idempotency is not None and remembered is not None:
            entry.keys.add(idempotency.key, remembered)
        apply_delta(session, delta, lang, now)
        self._publish(session, describe(change.event, result), now)
        return result

    def _update(self, session_id: str, change: Change, idempotency: Idempotency | None) -> UpdateResult:
        with self._locked(session_id) as entry:
            result = self._update_locked(entry, change, idempotency)
        self._maybe_compact()
        return result

    async def update(
        self, session_id: str, change: Change, *, idempotency: Idempotency | None = None
    ) -> UpdateResult:
        if change.inline and self._wal is None:
            # Nothing to wait for but the session's lock: computed here when it is free (no thread switch).
            entry = self._head(session_id)
            if entry.lock.acquire(blocking=False):
                try:
                    if not entry.deleted:
                        return self._update_locked(entry, change, idempotency)
                finally:
                    entry.lock.release()
        return await self._off_loop(partial(self._update, session_id, change, idempotency))

    def _publish(self, session: Session, cause: Mapping[str, Any], at: float, *, last: bool = False) -> None:
        """The session's event for its current version (its lock held: events are numbered in order)."""
        self.events.publish(
            session.id,
            session.robot_id,
            session.created_at,
            session.version,
            at,
            session.target_label,
            cause,
            last=last,
        )

    def _announce_locked(
        self, entry: _Entry, cause: Mapping[str, Any], idempotency: Idempotency | None
    ) -> None:
        now = self._clock()
        entry.keys.check(idempotency, now)
        self._publish(entry.session, cause, now)

    def _announce(self, session_id: str, cause: Mapping[str, Any], idempotency: Idempotency | None) -> None:
        with self._locked(session_id) as entry:
            self._announce_locked(entry, cause, idempotency)

    async def announce(
        self, session_id: str, cause: Mapping[str, Any], *, idempotency: Idempotency | None = None
    ) -> None:
        entry = self._head(session_id)
        if entry.lock.acquire(blocking=False):  # free: published here, without a thread switch
            try:
                if not entry.deleted:
                    self._announce_locked(entry, cause, idempotency)
                    return
            finally:
                entry.lock.release()
        await self._off_loop(partial(self._announce, session_id, cause, idempotency))

    async def record(self, session_id: str, frame: bytes, limit: int) -> None:
        with self._registry_lock:  # under it a removed session's log is dropped: none is made again
            if session_id in self._entries:
                frames = self._recordings.setdefault(session_id, [])
                frames.append(frame)
                if len(frames) > limit:
                    self._recordings[session_id] = thin(frames, limit)

    async def recording(self, session_id: str) -> tuple[bytes, ...]:
        with self._registry_lock:
            return tuple(self._recordings.get(session_id, ()))

    def _purge_expired(self) -> int:
        if self.ttl_s is None:
            return 0
        now = self._clock()
        with self._registry_lock:
            expired = [e for e in self._entries.values() if self._expired(e.session, now)]
        return sum(self._remove(entry) for entry in expired)

    async def purge_expired(self) -> int:
        return await self._off_loop(self._purge_expired)

    def close(self) -> None:
        """Release the data directory; the log is already durable, so nothing needs flushing."""
        if self._closed:
            return
        self._closed = True
        if self._wal is not None:
            self._wal.close()
        if self._lock_file is not None:
            self._lock_file.close()

    def __enter__(self) -> MemorySessionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _View:
    """`SessionView` of a session held in memory (read under its lock)."""

    __slots__ = ("_session",)

    def __init__(self, session: Session) -> None:
        self._session = session

    @property
    def id(self) -> str:
        return self._session.id

    @property
    def robot_id(self) -> str:
        return self._session.robot_id

    @property
    def version(self) -> int:
        return self._session.version

    @property
    def target_label(self) -> str:
        return self._session.target_label

    @property
    def grid(self) -> VoxelGrid:
        return self._session.grid

    @property
    def label_map(self) -> Mapping[int, str]:
        return self._session.label_map

    def scene_graph(self) -> SceneGraph:
        return self._session.scene_graph

    def observer(self) -> ObservationModel:
        return self._session.observer


def _record_of(delta: Delta, session: Session) -> dict[str, Any]:
    """A delta's fields in a log record (the language term as its mixture: replay recomputes it)."""
    record: dict[str, Any] = {}
    if delta.language is not None:
        record["mixture"] = pack_mixture(delta.language.mixture)
    if delta.meta is not None:
        if delta.meta.target_label is not None:
            record["target"] = delta.meta.target_label
        if delta.meta.scene_graph is not None:
            record["scene_graph"] = delta.meta.scene_graph.model_dump(mode="json")
    if delta.vision is not None:
        record["idx"] = pack_array(compact_indices(delta.vision.flat_idx, session.grid.n_voxels))
        record["inc"] = pack_array(delta.vision.increments)
    return record


def _delta_of(record: dict[str, Any], session: Session) -> Delta:
    """The delta a log record holds (also the operations logged before deltas had one record kind)."""
    op = record["op"]
    if op not in ("delta", "utterance", "increments", "scene_graph", "target"):
        msg = f"unknown session-log operation {op!r}"
        raise StoreUnavailable(msg)
    language = vision = meta = None
    if "mixture" in record:
        mixture = unpack_mixture(record["mixture"])
        language = LanguageDelta(mixture, language_log_likelihood(session.grid, mixture))
    if "idx" in record:
        vision = IncrementBatch(unpack_array(record["idx"]).astype(np.int64), unpack_array(record["inc"]))
    target = record.get("target", record.get("label"))
    if target is not None or "scene_graph" in record:
        sg = record.get("scene_graph")
        meta = MetaDelta(target, SceneGraph.model_validate(sg) if sg is not None else None)
    return Delta(language, vision, meta)
