"""JSON request bodies, read by the service rather than by FastAPI: validated off the event loop, in bounds.

FastAPI validates a declared body on the event loop and lists every error, echoing its input: a 200 kB list
of 100k bad items held the loop for 5 s and answered 16 MB. Here a route declares `body: Annotated[Model,
JsonBody(Model)]` instead: the body (its size already capped by `BodySizeLimitMiddleware`) is validated by
pydantic's own JSON parser, on a worker thread unless it is small, and a failure is an `InvalidInput` that
lists the first `max_validation_errors` errors. The request models keep the number of errors small to begin
with: their lists have ceilings that are checked before their items and stop at their first bad item
(`fail_fast`), and strings have lengths.

A body is JSON when its content type says so (`application/json`, `...+json`), or when it names none (as
curl's `-d` is read, see `app.api.content_types`); any other type is a 415.
"""

from __future__ import annotations

from typing import Any, TypeVar

from fastapi import Depends, Request
from pydantic import TypeAdapter, ValidationError

from app.api.deps import PrincipalDep
from app.api.errors import summarise_errors
from app.errors import InvalidInput, LimitExceeded, UnsupportedMediaType

T = TypeVar("T")

#: Bodies up to this size are validated on the event loop: well under a millisecond of work, cheaper than
#: the trip to a worker thread (an utterance is a few hundred bytes).
INLINE_JSON_BYTES = 16 << 10


def media_type(request: Request, default: str = "application/json") -> str:
    """The request's content type without parameters, lower case (`default` when it names none)."""
    return request.headers.get("content-type", default).split(";")[0].strip().lower() or default


def is_json(kind: str) -> bool:
    """Whether a media type (`media_type`'s) names JSON."""
    return kind == "application/json" or kind.endswith("+json")


def require_json(request: Request) -> None:
    kind = media_type(request)
    if not is_json(kind):
        msg = f"unsupported content type {kind!r}: send application/json"
        raise UnsupportedMediaType(msg, field="content-type")


async def json_bytes(request: Request) -> bytes:
    """The raw body of a JSON request, within `max_json_body_bytes` (413 above: pydantic validates JSON
    holding the interpreter lock, so the loop would wait on a large one however it is run)."""
    limit = request.app.state.services.settings.max_json_body_bytes
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        msg = f"a JSON body of {int(declared)} bytes exceeds the limit of {limit}; send batches as msgpack"
        raise LimitExceeded(msg, limit_name="max_json_body_bytes")
    raw = await request.body()
    if len(raw) > limit:
        msg = f"a JSON body of {len(raw)} bytes exceeds the limit of {limit}; send batches as msgpack"
        raise LimitExceeded(msg, limit_name="max_json_body_bytes")
    return raw


def validate_json(adapter: TypeAdapter[T], raw: bytes, max_errors: int) -> T:
    """`raw` validated as JSON by `adapter`; InvalidInput listing at most `max_errors` errors."""
    try:
        return adapter.validate_json(raw)
    except ValidationError as exc:
        errors = [dict(error) for error in exc.errors(include_url=False, include_input=False)]
        message, field, listed = summarise_errors(errors, exc.error_count(), max_errors)
        raise InvalidInput(message, field=field or "body", details=listed) from None


async def read_json(request: Request, adapter: TypeAdapter[T]) -> T:
    """The request's JSON body validated by `adapter` (415 for another content type)."""
    require_json(request)
    raw = await json_bytes(request)
    services = request.app.state.services
    limit = services.settings.max_validation_errors
    if len(raw) <= INLINE_JSON_BYTES:
        return validate_json(adapter, raw, limit)
    validated: T = await services.run(validate_json, adapter, raw, limit)
    return validated


def JsonBody(model: Any) -> Any:  # noqa: N802 (used like FastAPI's Body(), in Annotated)
    """A dependency giving the request's JSON body validated as `model` (a pydantic model or type), once
    the caller is authenticated and within its rate: nobody unknown or over the rate has the service read
    and validate a body (nor learns how it validates)."""
    adapter: TypeAdapter[Any] = TypeAdapter(model)

    async def read_body(request: Request, principal: PrincipalDep) -> Any:
        return await read_json(request, adapter)

    return Depends(read_body)


def json_request_body(schema: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI `requestBody` of a route that reads a `JsonBody` of this schema (a `$ref` or inline)."""
    return {"required": True, "content": {"application/json": {"schema": schema}}}


def schema_ref(name: str) -> dict[str, str]:
    return {"$ref": f"#/components/schemas/{name}"}
