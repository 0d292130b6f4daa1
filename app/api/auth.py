"""API keys with roles: who may call what.

Roles: `robot` (creates and updates its own sessions, limited to its robot ids), `viewer` (reads
everything, changes nothing: dashboards) and `admin` (everything). Keys travel as `Authorization: Bearer
<key>` and are stored only as SHA-256 digests: keys are long random tokens (`vlmap keys new`), so a fast
unsalted digest is safe, and lookups compare digests with `hmac.compare_digest` against every record so
that timing reveals nothing. With no key configured the service runs open (every caller is an anonymous
admin); `vlmap serve` refuses to do that on a non-loopback address unless told to.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import threading
import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from app.errors import Forbidden, InvalidInput, LimitExceeded


class Role(StrEnum):
    ROBOT = "robot"
    VIEWER = "viewer"
    ADMIN = "admin"


def digest(key: str) -> str:
    """Hex SHA-256 of a key: what the key file stores."""
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def new_key() -> str:
    """A fresh key: 32 random bytes, URL-safe, with a prefix that makes leaked keys easy to grep for."""
    return "vlm_" + secrets.token_urlsafe(32)


@dataclass(frozen=True)
class Principal:
    """The caller of one request."""

    name: str
    role: Role
    robot_ids: frozenset[str] = frozenset()

    def can_read(self, robot_id: str) -> bool:
        return self.role in (Role.ADMIN, Role.VIEWER) or robot_id in self.robot_ids

    def can_write(self, robot_id: str) -> bool:
        return self.role is Role.ADMIN or (self.role is Role.ROBOT and robot_id in self.robot_ids)

    def require_read(self, robot_id: str) -> None:
        if not self.can_read(robot_id):
            msg = f"key {self.name!r} may not read robot {robot_id!r}'s sessions"
            raise Forbidden(msg)

    def require_write(self, robot_id: str) -> None:
        if not self.can_write(robot_id):
            msg = f"key {self.name!r} ({self.role.value}) may not change robot {robot_id!r}'s sessions"
            raise Forbidden(msg)


OPEN_ACCESS = Principal(name="anonymous", role=Role.ADMIN)


@dataclass(frozen=True)
class KeyRecord:
    name: str
    role: Role
    sha256: str
    robot_ids: frozenset[str] = frozenset()


class KeyRing:
    """The configured keys; empty means open access."""

    def __init__(self, records: list[KeyRecord]) -> None:
        self.records = records

    @property
    def is_open(self) -> bool:
        return not self.records

    @classmethod
    def from_json(cls, text: str, source: str) -> KeyRing:
        """`[{"name", "role", "sha256", "robot_ids": [...]}]`; bad entries raise naming the entry."""
        try:
            entries: Any = json.loads(text)
        except json.JSONDecodeError as exc:
            msg = f"{source}: not JSON: {exc}"
            raise InvalidInput(msg, field=source) from exc
        if not isinstance(entries, list):
            msg = f"{source}: expected a list of key records"
            raise InvalidInput(msg, field=source)
        records = []
        for index, entry in enumerate(entries):
            try:
                sha = str(entry["sha256"]).lower()
                if len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha):
                    msg = "sha256 must be 64 hex digits"
                    raise ValueError(msg)
                records.append(
                    KeyRecord(
                        name=str(entry["name"]),
                        role=Role(entry["role"]),
                        sha256=sha,
                        robot_ids=frozenset(str(r) for r in entry.get("robot_ids", [])),
                    )
                )
            except (KeyError, TypeError, ValueError) as exc:
                msg = f"{source}[{index}]: bad key record: {exc}"
                raise InvalidInput(msg, field=f"{source}[{index}]") from exc
        return cls(records)

    @classmethod
    def load(cls, keys_file: Path | None, keys_json: str | None) -> KeyRing:
        if keys_file is not None:
            return cls.from_json(keys_file.read_text(encoding="utf-8"), str(keys_file))
        if keys_json:
            return cls.from_json(keys_json, "VLMAP_API_KEYS")
        return cls([])

    def authenticate(self, key: str) -> Principal | None:
        """The principal whose digest matches; every record is compared, in constant time each."""
        presented = digest(key)
        found: KeyRecord | None = None
        for record in self.records:
            if hmac.compare_digest(presented, record.sha256):
                found = record
        return Principal(found.name, found.role, found.robot_ids) if found else None


@dataclass
class RateLimiter:
    """A token bucket per key: `rate` requests a second on average, bursts up to `burst` (per process).
    A refusal is a LimitExceeded named `limit_name` that says when the next token comes (Retry-After)."""

    rate: float
    burst: float
    limit_name: str = "rate_limit"
    what: str = "requests"
    _buckets: dict[str, tuple[float, float]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def check(self, name: str) -> None:
        if self.rate <= 0:
            return
        now = time.monotonic()
        with self._lock:
            tokens, last = self._buckets.get(name, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            if tokens < 1.0:
                self._buckets[name] = (tokens, now)
                msg = (
                    f"key {name!r} exceeded {self.rate:g} {self.what}/s (burst {self.burst:g}); retry shortly"
                )
                raise LimitExceeded(msg, limit_name=self.limit_name, retry_after_s=(1.0 - tokens) / self.rate)
            self._buckets[name] = (tokens - 1.0, now)
