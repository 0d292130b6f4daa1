"""Prometheus metrics, JSON logs and the request-id middleware.

Metric names follow Prometheus conventions: base units (seconds), `_total` for counters, and labels of
bounded cardinality only (route templates, never raw paths or ids).
"""

from __future__ import annotations

import json
import logging
import sys
import time
import uuid
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.errors import error_body, request_id_var

#: The status recorded (never sent) for a request whose client hung up before its answer: nginx's 499.
CLIENT_CLOSED_REQUEST = 499
#: Characters of one log field kept (a message or traceback quoting a hostile input could be megabytes).
_LOG_FIELD_CHARS = 8192

_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class Metrics:
    """The service's metrics, in a registry of their own (one per app, so tests can build many apps)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "vlmap_http_requests_total",
            "HTTP requests answered.",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "vlmap_http_request_duration_seconds",
            "Time from request start to the end of the response.",
            ["method", "route"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.in_flight = Gauge(
            "vlmap_http_requests_in_flight", "Requests being served now.", registry=self.registry
        )
        self.inference = Histogram(
            "vlmap_inference_duration_seconds",
            "Time spent per language-sensor stage (proposer, grounder, text_encoder).",
            ["stage"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )

        self.llm_fallbacks = Counter(
            "vlmap_llm_fallbacks_total",
            "LLM proposer calls answered by the built-in proposer instead, by reason.",
            ["reason"],
            registry=self.registry,
        )

    def observe_stage(self, stage: str, seconds: float) -> None:
        self.inference.labels(stage=stage).observe(seconds)


def _cut(text: str) -> str:
    return text if len(text) <= _LOG_FIELD_CHARS else text[:_LOG_FIELD_CHARS] + f"... [{len(text)} chars]"


class JsonFormatter(logging.Formatter):
    """One JSON object per line with time, level, logger, message, request id and any `extra` fields, each
    cut to a bounded length."""

    _RESERVED = frozenset(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {"message", "asctime"}

    def format(self, record: logging.LogRecord) -> str:
        payload: dict[str, Any] = {
            "time": self.formatTime(record, "%Y-%m-%dT%H:%M:%S%z"),
            "level": record.levelname,
            "logger": record.name,
            "message": _cut(record.getMessage()),
        }
        request_id = request_id_var.get()
        if request_id:
            payload["request_id"] = request_id
        extra = {k: v for k, v in record.__dict__.items() if k not in self._RESERVED}
        payload.update({k: _cut(v) if isinstance(v, str) else v for k, v in extra.items()})
        if record.exc_info:
            payload["exc_info"] = _cut(self.formatException(record.exc_info))
        return json.dumps(payload, default=lambda value: _cut(str(value)))


def configure_logging(level: str = "INFO", json_lines: bool = True) -> None:
    """Route the app's and uvicorn's logs through one handler on stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        JsonFormatter() if json_lines else logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s")
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error"):
        logging.getLogger(name).handlers[:] = []
        logging.getLogger(name).propagate = True
    logging.getLogger("uvicorn.access").disabled = True  # replaced by our access log with request ids


access_log = logging.getLogger("vlmap.access")


class RequestContextMiddleware:
    """Accepts or creates `X-Request-ID`, echoes it, counts and times every request, logs one access line.

    The outermost layer, so it also answers what nothing inside handled: an unexpected exception is a 500
    `ErrorResponse` carrying the request id; a client that hung up (a body read found it gone) gets nothing
    and is counted and logged as 499, not as a server error.
    """

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = dict(scope["headers"]).get(b"x-request-id", b"").decode("latin-1")
        request_id = incoming if 0 < len(incoming) <= 128 and incoming.isprintable() else uuid.uuid4().hex
        token = request_id_var.set(request_id)
        status = 500
        started = False
        start = time.perf_counter()

        async def send_with_id(message: Message) -> None:
            nonlocal status, started
            if message["type"] == "http.response.start":
                status, started = message["status"], True
                message["headers"] = [
                    *message.get("headers", []),
                    (b"x-request-id", request_id.encode("latin-1")),
                ]
            await send(message)

        self.metrics.in_flight.inc()
        try:
            await self.app(scope, receive, send_with_id)
        except ClientDisconnect:
            status = CLIENT_CLOSED_REQUEST
            access_log.info("client disconnected before the answer", extra={"path": scope["path"]})
        except Exception as exc:
            access_log.error("unhandled error", exc_info=exc)
            if not started:
                await self._internal_error(send_with_id)
        finally:
            self.metrics.in_flight.dec()
            elapsed = time.perf_counter() - start
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            method = scope["method"]
            self.metrics.requests.labels(method=method, route=route, status=str(status)).inc()
            self.metrics.latency.labels(method=method, route=route).observe(elapsed)
            access_log.info(
                "%s %s %d",
                method,
                scope["path"],
                status,
                extra={"route": route, "status": status, "duration_ms": round(elapsed * 1000, 3)},
            )
            request_id_var.reset(token)

    @staticmethod
    async def _internal_error(send: Send) -> None:
        from starlette.responses import JSONResponse

        response = JSONResponse(error_body("internal_error", "internal error"), status_code=500)
        await send({"type": "http.response.start", "status": 500, "headers": response.raw_headers})
        await send({"type": "http.response.body", "body": response.body})
