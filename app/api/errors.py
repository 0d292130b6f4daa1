"""Domain exceptions -> HTTP errors, in one place. Every error body is an `ErrorResponse`."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path

from app.api.observability import request_id_var
from app.errors import (
    Conflict,
    Forbidden,
    InvalidInput,
    LimitExceeded,
    ModelUnavailable,
    NotFound,
    Unauthenticated,
    UnsupportedMediaType,
    VLMapError,
)

log = logging.getLogger("vlmap.api")

# Limits whose breach is not a malformed body but a too-large one or too many requests.
_LIMIT_STATUS = {"max_body_bytes": 413, "rate_limit": 429, "max_sessions_per_robot": 429}
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
        409: "Conflict",
        413: "Request too large",
        415: "Unsupported media type",
        422: "Invalid input; the message names the field",
        429: "Too many requests",
        503: "Temporarily unavailable",
    }
    return {s: {"model": ErrorResponse, "description": text.get(s, "Error")} for s in statuses}


def error_body(
    code: str, message: str, field: str | None = None, errors: list[dict[str, Any]] | None = None
) -> dict:
    return ErrorResponse(
        code=code, message=message, field=field, request_id=request_id_var.get(), errors=errors or []
    ).model_dump()


def field_path(loc: tuple[Any, ...] | list[Any]) -> str:
    """("body", "scene_graph", "native", "objects", 3, "size") -> "scene_graph.objects.3.size"."""
    parts = [str(p) for p in loc if p not in _UNION_TAGS]
    if parts and parts[0] in {"body", "query", "path", "header"}:
        parts = parts[1:]
    return ".".join(parts)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = jsonable_encoder(exc.errors(), custom_encoder={BaseException: str})
    for e in errors:
        e.pop("input", None)  # echoing a whole scene graph back helps nobody
        e.pop("url", None)
    first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
    field = field_path(tuple(first.get("loc", ())))
    message = f"{field}: {first.get('msg')}" if field else str(first.get("msg"))
    return JSONResponse(status_code=422, content=error_body("invalid_input", message, field or None, errors))


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
    if isinstance(exc, InvalidInput):
        return JSONResponse(status_code=422, content=error_body("invalid_input", str(exc), exc.field))
    if isinstance(exc, LimitExceeded):
        status = _LIMIT_STATUS.get(exc.limit_name, 422)
        return JSONResponse(
            status_code=status, content=error_body("limit_exceeded", str(exc), exc.limit_name)
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
    if "GET" in methods:
        methods.add("HEAD")  # Starlette answers HEAD wherever it answers GET
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


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled error", exc_info=exc)
    return JSONResponse(status_code=500, content=error_body("internal_error", "internal error"))


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(VLMapError, _domain_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, _unexpected_error)
