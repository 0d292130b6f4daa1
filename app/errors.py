"""Domain exceptions. The API maps each to one HTTP status in `app.api.errors`; nothing else raises HTTP."""

from __future__ import annotations

from typing import Any


class VLMapError(Exception):
    """Base class of every error this package raises on purpose."""


class InvalidInput(VLMapError):
    """A request or file is malformed; `field` names the offending location (dotted path), `details` lists
    the individual errors when a validator found several."""

    def __init__(
        self, message: str, field: str | None = None, details: list[dict[str, Any]] | None = None
    ) -> None:
        super().__init__(message)
        self.field = field
        self.details = details or []

    def __str__(self) -> str:
        base = super().__str__()
        return f"{self.field}: {base}" if self.field else base


class InvalidSceneGraph(InvalidInput):
    """A scene graph (in any accepted format) cannot be read or normalised."""


class LimitExceeded(VLMapError):
    """A configured limit (objects per scene graph, voxels per batch, ...) was exceeded; `retry_after_s`,
    when set, says when trying again may succeed (a rate or a busy resource)."""

    def __init__(self, message: str, limit_name: str, retry_after_s: float | None = None) -> None:
        super().__init__(message)
        self.limit_name = limit_name
        self.retry_after_s = retry_after_s


class NotFound(VLMapError):
    """A named resource (session, model, object id) does not exist."""


class ModelUnavailable(VLMapError):
    """The grounding model or an upstream dependency (LLM endpoint, store) cannot serve right now."""


class UnsupportedMediaType(InvalidInput):
    """A body arrived in a content type the endpoint does not read."""


class StoreUnavailable(ModelUnavailable):
    """The session store (Redis, the data directory) cannot be reached or written; retrying may succeed."""


class LLMResponseError(ModelUnavailable):
    """An LLM endpoint answered, but not with what was asked for (no JSON object, wrong shape, NaN).

    A `ModelUnavailable` because, to a caller, the model could not serve this request (the API answers 503).
    """


class Unauthenticated(VLMapError):
    """No API key, or one the service does not know."""


class Forbidden(VLMapError):
    """The API key is valid but its role or robot ids do not cover this operation."""


class IdempotencyKeyReused(InvalidInput):
    """An Idempotency-Key came back with another request than the one it was first used with."""


class AlreadyApplied(VLMapError):
    """The update carried an Idempotency-Key that its session has seen: nothing was changed, and `record`
    (an `app.stores.base.IdempotencyRecord`) says what the first request with that key did. The API answers
    it by repeating that answer (or a 422 when the request differs); it never reaches a client as such."""

    def __init__(self, record: object) -> None:
        super().__init__("this Idempotency-Key was seen before")
        self.record = record


class Conflict(VLMapError):
    """The request conflicts with the resource's state (e.g. observations before the target is known)."""
