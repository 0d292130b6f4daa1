"""The request-body limits, inside the request-id and metrics middleware so their answers are counted.

Size (413): a declared Content-Length above the limit is answered before the body is read; a chunked body
is counted as it streams, and the read that passes the limit raises a 413 that the error handlers render.

Time (408): the whole body must arrive within `body_timeout_s` of the request's start, so that a client
trickling bytes cannot hold a request (and the memory of its partial body) open for ever. Once the body is
complete, reads (an app listening for the client's hang-up) wait as long as they like.
"""

from __future__ import annotations

import time

import anyio
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.api.errors import error_body
from app.errors import LimitExceeded


class BodySizeLimitMiddleware:
    def __init__(self, app: ASGIApp, max_body_bytes: int, body_timeout_s: float = 30.0) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.body_timeout_s = body_timeout_s

    def _too_large(self, size: int) -> str:
        return f"request body of {size} bytes or more exceeds the limit of {self.max_body_bytes}"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.max_body_bytes:
            body = error_body("limit_exceeded", self._too_large(int(declared)), "max_body_bytes")
            await JSONResponse(body, status_code=413)(scope, receive, send)
            return
        seen = 0
        complete = False
        deadline = time.monotonic() + self.body_timeout_s

        async def limited_receive() -> Message:
            nonlocal seen, complete
            if complete:
                return await receive()
            try:
                with anyio.fail_after(max(0.0, deadline - time.monotonic())):
                    message = await receive()
            except TimeoutError:
                msg = f"the request body did not arrive within {self.body_timeout_s:g} s"
                raise LimitExceeded(msg, limit_name="body_timeout_s") from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_body_bytes:
                    raise LimitExceeded(self._too_large(seen), limit_name="max_body_bytes")
                complete = not message.get("more_body", False)
            return message

        await self.app(scope, limited_receive, send)
