"""Durable homes for VL-Map sessions: one `SessionStore` interface, an in-memory store with an optional
write-ahead log (`MemorySessionStore`) and a Redis store shared by replicas (`RedisSessionStore`).

`__all__` is what the other rooms use: `open_store` and the store interface with the changes it applies
(`Change`, `Delta` and its parts, `SessionView`) and its idempotency records, all defined in
`app.stores.base`. `RedisSessionStore` is imported from `app.stores.redis_store` where wanted: `open_store`
loads that module only for a redis:// URL, so that the memory store's users never do."""

from __future__ import annotations

from pathlib import Path

from app.errors import InvalidInput
from app.stores.base import (
    DEFAULT_IDEMPOTENCY_KEYS,
    DEFAULT_IDEMPOTENCY_WINDOW_S,
    DEFAULT_TTL_S,
    Change,
    Delta,
    Idempotency,
    IdempotencyRecord,
    LanguageDelta,
    MetaDelta,
    SessionStore,
    SessionView,
)
from app.stores.memory import MemorySessionStore

__all__ = [
    "DEFAULT_TTL_S",
    "Change",
    "Delta",
    "Idempotency",
    "IdempotencyRecord",
    "LanguageDelta",
    "MemorySessionStore",
    "MetaDelta",
    "SessionStore",
    "SessionView",
    "open_store",
]


def open_store(
    url: str | None = None,
    *,
    data_dir: Path | str | None = None,
    ttl_s: float | None = DEFAULT_TTL_S,
    mirror_mib: int | None = None,
    idempotency_window_s: float = DEFAULT_IDEMPOTENCY_WINDOW_S,
    idempotency_keys: int = DEFAULT_IDEMPOTENCY_KEYS,
) -> SessionStore:
    """The store a setting names: None or "memory" -> `MemorySessionStore(data_dir)`, redis:// -> Redis, a
    single server or a cluster (`mirror_mib`: its mirror's size, `RedisSessionStore`'s default when None)."""
    window, keys = idempotency_window_s, idempotency_keys
    if url is None or url == "memory":
        return MemorySessionStore(data_dir, ttl_s=ttl_s, idempotency_window_s=window, idempotency_keys=keys)
    if url.startswith(("redis://", "rediss://", "unix://")):
        from app.stores.redis_store import DEFAULT_MIRROR_BYTES, RedisSessionStore

        mirror = DEFAULT_MIRROR_BYTES if mirror_mib is None else mirror_mib << 20
        return RedisSessionStore(
            url, ttl_s=ttl_s, mirror_bytes=mirror, idempotency_window_s=window, idempotency_keys=keys
        )
    msg = f"unknown session store {url!r}: use 'memory' or a redis:// URL"
    raise InvalidInput(msg, "session_store")
