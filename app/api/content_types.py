"""Form-encoded bodies read as JSON.

`curl -d @request.json` sends `application/x-www-form-urlencoded`; this API takes no forms, so such a body
is read as the JSON it almost always is (one that is not JSON then fails validation with a clear 422).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Receive, Scope, Send

_FORM = b"application/x-www-form-urlencoded"


class FormAsJsonMiddleware:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            headers = scope["headers"]
            if any(k == b"content-type" and v.split(b";")[0].strip().lower() == _FORM for k, v in headers):
                scope = dict(scope)
                scope["headers"] = [
                    (k, b"application/json") if k == b"content-type" else (k, v) for k, v in headers
                ]
        await self.app(scope, receive, send)
