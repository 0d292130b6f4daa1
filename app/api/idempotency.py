"""The Idempotency-Key request header (IETF httpapi draft "The Idempotency-Key HTTP Header Field").

Every state-changing session endpoint takes one. The key is remembered with the change it came with, in the
same store write (`app.stores.base`), so that a request repeated after its answer was lost (a timeout, a
replica killed mid-request, a Redis failover) is applied once:

- the same key with the same request (method, path, query, content type and body) is answered as the first
  time, with `Idempotent-Replayed: true`; what the answer embeds of the session's current state (its
  metadata, the belief summary) is read anew;
- the same key with another request is a 422 (`idempotency_key_reused`);
- a key is remembered by its session for `idempotency_window_s`, and for its last
  `idempotency_keys_per_session` keys.

A key is 1-255 printable ASCII characters; the draft's quoted form ("...", a structured-field string) and
a bare token are the same key.
"""

from __future__ import annotations

import hashlib
from typing import Annotated

from fastapi import Depends, Header, Request

from app.errors import InvalidInput
from app.stores.base import Idempotency

REPLAYED_HEADER = "Idempotent-Replayed"


def replayable(status: int = 200) -> dict[int | str, dict[str, object]]:
    """The OpenAPI success response of a keyed route, with its replay header."""
    header = {
        "description": "true when this answers a request repeated with its Idempotency-Key.",
        "schema": {"type": "string", "enum": ["true"]},
    }
    return {status: {"description": "Successful Response", "headers": {REPLAYED_HEADER: header}}}


IdempotencyKeyHeader = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        description="Makes the request safe to retry: a request repeated with the same key (and body) is "
        "applied once and answered as the first time; the same key with another body is a 422. 1-255 "
        "printable ASCII characters, e.g. a UUID.",
    ),
]


def idempotency_of(request: Request, key: str | None, body: bytes, answer: bytes = b"") -> Idempotency | None:
    """The request's `Idempotency` (None without a key): the key, and the fingerprint of the request."""
    if key is None:
        return None
    text = key.strip()
    if len(text) >= 2 and text[0] == text[-1] == '"':
        text = text[1:-1]
    if not (0 < len(text) <= 255 and text.isascii() and text.isprintable()):
        msg = "an Idempotency-Key is 1-255 printable ASCII characters"
        raise InvalidInput(msg, field="Idempotency-Key")
    digest = hashlib.sha256()
    for part in (request.method, request.url.path, request.headers.get("content-type", "")):
        digest.update(part.encode("latin-1", "replace") + b"\0")
    if request.url.query:  # a binary scene-graph body's other fields; absent, the fingerprint is as before
        digest.update(b"?" + request.url.query.encode("latin-1", "replace") + b"\0")
    digest.update(body)
    return Idempotency(text, digest.hexdigest()[:32], answer)


async def request_idempotency(request: Request, key: IdempotencyKeyHeader = None) -> Idempotency | None:
    """The request's `Idempotency` from its Idempotency-Key header and body (None without a key)."""
    return None if key is None else idempotency_of(request, key, await request.body())


#: A state-changing route's Idempotency-Key, as the dependency that reads it.
IdempotencyDep = Annotated[Idempotency | None, Depends(request_idempotency)]


def with_answer(idempotency: Idempotency | None, answer: bytes) -> Idempotency | None:
    return None if idempotency is None else Idempotency(idempotency.key, idempotency.fingerprint, answer)
