"""The HTTP server's own limits, below the application: how long and how large a request's head may be.

uvicorn (httptools) waits for a request's line and headers for as long as a client takes to send them, and
keeps every byte of them: a client trickling a header, or sending megabytes of them, held a connection and
its memory indefinitely. `GuardedHttpToolsProtocol` closes a connection whose request head has not arrived
within `header_timeout_s` (counted from the connection's opening, then from each later request's first
byte) and answers 431 to a head larger than `max_header_bytes`. Bodies are the application's business
(`app.api.limits`); the connection cap is uvicorn's `limit_concurrency` (503 beyond it).
"""

from __future__ import annotations

import asyncio
from typing import Any

from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """httptools' protocol with a deadline and a size limit on each request's line and headers (the class
    attributes; `guarded_protocol` makes a subclass with the service's)."""

    header_timeout_s = 10.0
    max_header_bytes = 32 * 1024

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_bytes = 0
        self._head_too_large = False
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._start_head()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_head()
        super().connection_lost(exc)

    def _start_head(self) -> None:
        self._stop_head()
        self._head_bytes = 0
        self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_too_slow)

    def _stop_head(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_too_slow(self) -> None:
        self._head_timer = None
        if not self.transport.is_closing():
            self.logger.info("closing a connection whose request head took over %g s", self.header_timeout_s)
            self.transport.close()

    def data_received(self, data: bytes) -> None:
        if self._head_timer is None and self.cycle is not None and self.cycle.response_complete:
            self._start_head()  # the next request on a kept-alive connection: its head gets its own time
        super().data_received(data)

    def _count_head(self, size: int) -> None:
        self._head_bytes += size
        if self._head_bytes > self.max_header_bytes:
            self._head_too_large = True
            msg = "request head too large"
            raise ValueError(msg)  # httptools stops parsing; `send_400_response` answers 431

    def on_url(self, url: bytes) -> None:
        self._count_head(len(url))
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._count_head(len(name) + len(value) + 4)
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        self._stop_head()
        super().on_headers_complete()

    def send_400_response(self, msg: str) -> None:
        if not self._head_too_large:
            super().send_400_response(msg)
            return
        self._stop_head()
        body = b"request line and headers exceed the limit"
        head = STATUS_LINE[431] + b"content-type: text/plain; charset=utf-8\r\n"
        head += b"content-length: " + str(len(body)).encode() + b"\r\nconnection: close\r\n\r\n"
        self.transport.write(head + body)
        self.transport.close()


def guarded_protocol(header_timeout_s: float, max_header_bytes: int) -> type[HttpToolsProtocol]:
    """The protocol class to give uvicorn (which makes one per connection with its own arguments)."""
    limits = {"header_timeout_s": header_timeout_s, "max_header_bytes": max_header_bytes}
    return type("GuardedHttpTools", (GuardedHttpToolsProtocol,), limits)
