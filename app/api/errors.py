"""Domain exceptions -> HTTP errors, in one place. Every error body is an `ErrorResponse`."""

from __future__ import annotations

import contextvars
import logging
import math
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path

from app.errors import (
    Conflict,
    Forbidden,
    IdempotencyKeyReused,
    InvalidInput,
    LimitExceeded,
    ModelUnavailable,
    NotFound,
    Unauthenticated,
    UnsupportedMediaType,
    VLMapError,
)

#: The id of the request being answered (set by `app.api.observability.RequestContextMiddleware`).
request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar("request_id", default=None)

log = logging.getLogger("vlmap.api")

# Limits whose breach is not a malformed body but a too-large or too-slow one, or too many requests.
_LIMIT_STATUS = {
    "max_body_bytes": 413,
    "max_json_body_bytes": 413,
    "body_timeout_s": 408,
    "rate_limit": 429,
    "decode_rate": 429,
    "max_sessions_per_robot": 429,
    "max_concurrent_decodes": 429,
    "max_concurrent_grids": 429,
    "max_event_streams": 429,
}
#: Characters of a validation message or context value kept in a 422 answer (inputs can be huge).
_DETAIL_CHARS = 200
# Tags of discriminated unions that pydantic puts in error locations; they are not field names.
_UNION_TAGS = frozenset({"native", "other"})


class ErrorResponse(BaseModel):
    """What every 4xx/5xx answer carries."""

    code: str = Field(description="Stable machine-readable error code, e.g. invalid_input, not_found.")
    message: str = Field(description="What went wrong, naming the field when one is at fault.")
    field: str | None = Field(default=None, description="Dotted path of the offending field, if any.")
    request_id: str | None = None
    errors: list[dict[str, Any]] = Field(
        default_factory=list, description="Every validation error, when several."
    )


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries documenting these error statuses with the ErrorResponse schema."""
    text = {
        304: "Not modified",
        400: "Bad request",
        401: "Missing or invalid API key",
        403: "Outside the key's scope",
        404: "Not found",
        408: "The request body did not arrive in time",
        409: "Conflict",
        413: "Request too large",
        415: "Unsupported media type",
        422: "Invalid input; the message names the field",
        429: "Too many requests, or the resource is busy; Retry-After says when to try again",
        503: "Temporarily unavailable",
    }
    return {s: {"model": ErrorResponse, "description": text.get(s, "Error")} for s in statuses}


def error_body(
    code: str, message: str, field: str | None = None, errors: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    return ErrorResponse(
        code=code, message=message, field=field, request_id=request_id_var.get(), errors=errors or []
    ).model_dump()


def field_path(loc: tuple[Any, ...] | list[Any]) -> str:
    """("body", "scene_graph", "native", "objects", 3, "size") -> "scene_graph.objects.3.size"; pydantic's
    names of union members ("list[constrained-int]") and of dict keys ("[key]") are left out too."""
    parts = [str(p) for p in loc if p not in _UNION_TAGS and not (isinstance(p, str) and p.endswith("]"))]
    if parts and parts[0] in {"body", "query", "path", "header"}:
        parts = parts[1:]
    return ".".join(parts)


def _short(value: Any) -> Any:
    text = value if isinstance(value, str) else repr(value)
    return text if len(text) <= _DETAIL_CHARS else text[: _DETAIL_CHARS - 3] + "..."


def summarise_errors(
    errors: Sequence[dict[str, Any]], total: int, limit: int
) -> tuple[str, str | None, list[dict[str, Any]]]:
    """(message, field, listed errors) for a 422: the first `limit` errors, each without its input and with
    its message and context values cut short, the first's message and field, and how many there were."""
    listed = []
    for error in errors[:limit]:
        entry: dict[str, Any] = {
            "type": str(error.get("type", "invalid")),
            "loc": [p if isinstance(p, int) else _short(str(p)) for p in error.get("loc", ())],
            "msg": _short(str(error.get("msg", "invalid value"))),
        }
        if error.get("ctx"):
            entry["ctx"] = {str(k): _short(v) for k, v in list(error["ctx"].items())[:8]}
        listed.append(entry)
    first = listed[0] if listed else {"loc": [], "msg": "invalid request"}
    field = field_path(tuple(first["loc"])) or None
    message = str(first["msg"])
    if total > 1:
        message += f" (and {total - 1} more errors; {len(listed)} listed)"
    return message, field, listed


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    # Path, query and header parameters only (bodies are read by app.api.bodies): a few errors at most.
    limit = request.app.state.services.settings.max_validation_errors
    errors = list(exc.errors())
    message, field, listed = summarise_errors(errors, len(errors), limit)
    text = f"{field}: {message}" if field else message
    return JSONResponse(status_code=422, content=error_body("invalid_input", text, field, listed))


async def _domain_error(request: Request, exc: VLMapError) -> JSONResponse:
    if isinstance(exc, Unauthenticated):
        headers = {"WWW-Authenticate": "Bearer"}
        return JSONResponse(status_code=401, content=error_body("unauthenticated", str(exc)), headers=headers)
    if isinstance(exc, Forbidden):
        return JSONResponse(status_code=403, content=error_body("forbidden", str(exc)))
    if isinstance(exc, UnsupportedMediaType):
        return JSONResponse(
            status_code=415, content=error_body("unsupported_media_type", str(exc), exc.field)
        )
    if isinstance(exc, IdempotencyKeyReused):
        return JSONResponse(
            status_code=422, content=error_body("idempotency_key_reused", str(exc), exc.field)
        )
    if isinstance(exc, InvalidInput):
        body = error_body("invalid_input", str(exc), exc.field, exc.details)
        return JSONResponse(status_code=422, content=body)
    if isinstance(exc, LimitExceeded):
        status = _LIMIT_STATUS.get(exc.limit_name, 422)
        retry = {}
        if exc.retry_after_s is not None:
            retry["Retry-After"] = str(max(1, math.ceil(exc.retry_after_s)))
        return JSONResponse(
            status_code=status, content=error_body("limit_exceeded", str(exc), exc.limit_name), headers=retry
        )
    if isinstance(exc, Conflict):
        return JSONResponse(status_code=409, content=error_body("conflict", str(exc)))
    if isinstance(exc, NotFound):
        return JSONResponse(status_code=404, content=error_body("not_found", str(exc)))
    if isinstance(exc, ModelUnavailable):
        return JSONResponse(status_code=503, content=error_body("unavailable", str(exc)))
    log.error("unmapped domain error", exc_info=exc)
    return JSONResponse(status_code=500, content=error_body("internal_error", "internal error"))


def allowed_methods(request: Request) -> str:
    """Every method some operation serves at this path (Starlette's 405 names only the first route's)."""
    methods: set[str] = set()
    for template, operations in request.app.openapi()["paths"].items():
        regex, _, _ = compile_path(template)
        if regex.match(request.url.path):
            methods |= {m.upper() for m in operations}
    return ", ".join(sorted(methods))


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    codes = {404: "not_found", 405: "method_not_allowed", 413: "limit_exceeded"}
    code = codes.get(exc.status_code, "http_error")
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 405:
        headers["Allow"] = allowed_methods(request)
    return JSONResponse(
        status_code=exc.status_code, content=error_body(code, str(exc.detail)), headers=headers
    )


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(VLMapError, _domain_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    # Anything else is answered by `RequestContextMiddleware`, inside the request's context (its id).
