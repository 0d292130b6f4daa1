"""A real HTTP server on 127.0.0.1 speaking the chat-completions protocol, with scripted replies.

Each POST /v1/chat/completions is recorded (headers, JSON body) and answered with the next scripted
`Reply`: a chat completion wrapping `content`, or a raw `body`, with any status, headers and delay. With
the script empty it answers 500 so that a test expecting fewer calls fails loudly.
"""

from __future__ import annotations

import json
import threading
from collections import deque
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

CHAT_PATH = "/v1/chat/completions"


@dataclass(frozen=True)
class Reply:
    """One scripted answer; `body` (raw text) wins over `content` (wrapped as a chat completion)."""

    content: str | None = None
    status: int = 200
    body: str | None = None
    delay_s: float = 0.0
    headers: dict[str, str] = field(default_factory=dict)

    def encoded_body(self, model: str) -> bytes:
        if self.body is not None:
            return self.body.encode()
        completion = {
            "id": "chatcmpl-fake",
            "object": "chat.completion",
            "model": model,
            "choices": [
                {
                    "index": 0,
                    "message": {"role": "assistant", "content": self.content},
                    "finish_reason": "stop",
                }
            ],
        }
        return json.dumps(completion).encode()


@dataclass(frozen=True)
class RecordedRequest:
    path: str
    headers: dict[str, str]  # lower-case names
    body: Any


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, owner: FakeLLMServer) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.owner = owner

    def handle_error(self, request: Any, client_address: Any) -> None:
        # A client that timed out has closed its socket; writing the late answer then fails, as expected.
        pass


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        pass

    def do_POST(self) -> None:
        owner = self.server.owner
        raw = self.rfile.read(int(self.headers.get("Content-Length", "0")))
        try:
            body: Any = json.loads(raw)
        except ValueError:
            body = raw.decode(errors="replace")
        owner.record(RecordedRequest(self.path, {k.lower(): v for k, v in self.headers.items()}, body))
        if self.path != CHAT_PATH:
            self._send(Reply(status=404, body='{"error": "not found"}'), "")
            return
        reply = owner.next_reply()
        if reply.delay_s and owner.stopping.wait(reply.delay_s):
            self.close_connection = True  # the test is over: drop the connection unanswered
            return
        self._send(reply, body.get("model", "") if isinstance(body, dict) else "")

    def _send(self, reply: Reply, model: str) -> None:
        payload = reply.encoded_body(model)
        self.send_response(reply.status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        for name, value in reply.headers.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(payload)


class FakeLLMServer:
    """Start with `with FakeLLMServer() as server:`; `server.base_url` ends in /v1."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._script: deque[Reply] = deque()
        self._requests: list[RecordedRequest] = []
        self.stopping = threading.Event()
        self._server = _Server(self)
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05})

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self._server.server_port}/v1"

    @property
    def requests(self) -> list[RecordedRequest]:
        with self._lock:
            return list(self._requests)

    def script(self, *replies: Reply) -> None:
        with self._lock:
            self._script.extend(replies)

    def record(self, request: RecordedRequest) -> None:
        with self._lock:
            self._requests.append(request)

    def next_reply(self) -> Reply:
        with self._lock:
            if self._script:
                return self._script.popleft()
        return Reply(status=500, body='{"error": "no scripted reply left"}')

    def __enter__(self) -> FakeLLMServer:
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stopping.set()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join()
