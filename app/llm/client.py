"""A small client for any OpenAI-compatible chat-completions endpoint (hosted APIs, vLLM, llama.cpp, Ollama).

One call is POST {base_url}/chat/completions with the model, the messages and a temperature, asking for a
JSON object reply (`response_format`) unless the endpoint rejects that. Connection errors, timeouts, 429 and
5xx answers are retried with exponential backoff: before retry k (1, 2, ...) it waits
min(backoff_s * 2^(k-1), max_backoff_s), or the answer's Retry-After when it gives one (capped alike).
What comes back is checked and the first JSON object in the reply's text is extracted, wherever the model
put it (bare, in a ```json fence, after some prose).

Errors are domain errors: `EndpointUnavailable` (a `ModelUnavailable`, with a short `reason` fit for a
metrics label) when the endpoint cannot be reached or will not answer, `LLMResponseError` when it answers
with something unusable.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import httpx

from app.errors import LLMResponseError, ModelUnavailable

log = logging.getLogger("vlmap.llm")

_FENCE = re.compile(r"```[ \t]*(?:json|JSON)?[ \t]*\n?(.*?)```", re.DOTALL)
_THINK_OPEN, _THINK_CLOSE = "<think>", "</think>"
# Replies longer than this are not read: no prompt of this package asks for anything near it.
_MAX_REPLY_CHARS = 200_000


@dataclass(frozen=True)
class LLMEndpoint:
    """Where and how to call the model. `base_url` ends before /chat/completions (e.g. ".../v1")."""

    base_url: str
    model: str
    api_key: str | None = None
    timeout_s: float = 30.0  # per HTTP attempt: connect, each read, each write
    max_retries: int = 2  # attempts = 1 + max_retries
    backoff_s: float = 0.5
    max_backoff_s: float = 8.0
    temperature: float = 0.0
    json_mode: bool = True  # send response_format={"type": "json_object"}; dropped if the server refuses it

    def __post_init__(self) -> None:
        if not self.base_url.startswith(("http://", "https://")):
            msg = f"LLM base_url must start with http:// or https://, got {self.base_url!r}"
            raise ValueError(msg)
        if self.timeout_s <= 0 or self.max_retries < 0 or self.backoff_s < 0:
            msg = "LLM timeout_s must be > 0, max_retries and backoff_s >= 0"
            raise ValueError(msg)

    @property
    def url(self) -> str:
        return self.base_url.rstrip("/") + "/chat/completions"

    def describe(self) -> dict[str, Any]:
        """The settings that shape answers, for model cards; never the API key."""
        return {"base_url": self.base_url, "model": self.model, "temperature": self.temperature}


class EndpointUnavailable(ModelUnavailable):
    """The endpoint could not be reached or would not answer; `reason` is one of `UNAVAILABLE_REASONS`."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


#: Why an endpoint can be unavailable: no answer in time, no connection, still rate-limited or failing
#: after every retry, or refused outright (4xx: wrong key, unknown model, bad request).
UNAVAILABLE_REASONS = ("timeout", "unreachable", "rate_limited", "server_error", "rejected")


class ChatClient:
    """Chat completions against one `LLMEndpoint`; thread-safe (one pooled httpx client)."""

    def __init__(self, endpoint: LLMEndpoint, sleep: Callable[[float], None] = time.sleep) -> None:
        self.endpoint = endpoint
        self._sleep = sleep
        self._json_mode = endpoint.json_mode
        headers = {"Authorization": f"Bearer {endpoint.api_key}"} if endpoint.api_key else {}
        self._http = httpx.Client(timeout=httpx.Timeout(endpoint.timeout_s), headers=headers)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> ChatClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def complete(self, messages: Sequence[Mapping[str, str]]) -> str:
        """The assistant's reply text to `messages` (each {"role", "content"}), after retries."""
        ep = self.endpoint
        payload: dict[str, Any] = {
            "model": ep.model,
            "messages": [dict(m) for m in messages],
            "temperature": ep.temperature,
        }
        failure: EndpointUnavailable | None = None
        retry_after: float | None = None
        for attempt in range(ep.max_retries + 1):
            if failure is not None:
                delay = ep.backoff_s * 2 ** (attempt - 1) if retry_after is None else retry_after
                delay = min(delay, ep.max_backoff_s)
                log.warning(
                    "LLM call failed (%s), retry %d/%d in %.2f s", failure, attempt, ep.max_retries, delay
                )
                self._sleep(delay)
            retry_after = None
            try:
                response = self._post(payload)
            except httpx.TimeoutException as exc:
                failure = EndpointUnavailable(
                    f"LLM endpoint {ep.url} timed out after {ep.timeout_s} s", "timeout"
                )
                failure.__cause__ = exc
                continue
            except httpx.DecodingError as exc:
                # The body is read (and decompressed) inside the call: one its Content-Encoding does not
                # fit is an answer, and an unusable one, not a failure to connect.
                msg = f"LLM endpoint {ep.url} answered a body that does not decode: {exc}"
                raise LLMResponseError(msg) from exc
            except httpx.TransportError as exc:
                failure = EndpointUnavailable(f"LLM endpoint {ep.url} unreachable: {exc}", "unreachable")
                failure.__cause__ = exc
                continue
            status = response.status_code
            if status == 429 or status >= 500:
                reason = "rate_limited" if status == 429 else "server_error"
                failure = EndpointUnavailable(f"LLM endpoint {ep.url} answered HTTP {status}", reason)
                retry_after = _retry_after_s(response)
                continue
            if status >= 400:
                msg = f"LLM endpoint {ep.url} refused the call: HTTP {status} {_snippet(response.text)}"
                raise EndpointUnavailable(msg, "rejected")
            return reply_text(response)
        assert failure is not None  # the loop runs at least once and returns on success
        raise failure

    def complete_json(self, messages: Sequence[Mapping[str, str]]) -> dict[str, Any]:
        """The first JSON object in the reply to `messages`."""
        return extract_json_object(self.complete(messages))

    def _post(self, payload: dict[str, Any]) -> httpx.Response:
        if not self._json_mode:
            return self._http.post(self.endpoint.url, json=payload)
        response = self._http.post(
            self.endpoint.url, json={**payload, "response_format": {"type": "json_object"}}
        )
        if response.status_code in (400, 422) and "response_format" in response.text:
            # Some servers do not implement JSON mode; the prompts ask for JSON anyway.
            log.warning(
                "LLM endpoint %s does not support response_format; asking without it", self.endpoint.url
            )
            self._json_mode = False
            response = self._http.post(self.endpoint.url, json=payload)
        return response


def reply_text(response: httpx.Response) -> str:
    """choices[0].message.content of a chat-completions answer (a string, or a list of text parts)."""
    try:
        body = response.json()
        content = body["choices"][0]["message"]["content"]
    except (ValueError, KeyError, IndexError, TypeError, RecursionError) as exc:
        msg = f"LLM reply is not a chat completion: {_snippet(response.text)}"
        raise LLMResponseError(msg) from exc
    if isinstance(content, list):
        content = "".join(
            p["text"] for p in content if isinstance(p, dict) and isinstance(p.get("text"), str)
        )
    if not isinstance(content, str) or not content.strip():
        msg = "LLM reply has no text content"
        raise LLMResponseError(msg)
    return content


def extract_json_object(text: str) -> dict[str, Any]:
    """The first JSON object in `text`: the whole text, else the first fenced block holding one, else the
    first '{' from which a complete object decodes (prose before and after is ignored)."""
    if len(text) > _MAX_REPLY_CHARS:
        msg = f"LLM reply is {len(text)} characters long, more than the {_MAX_REPLY_CHARS} read"
        raise LLMResponseError(msg)
    text = strip_thinking(text).strip()
    try:
        found = _first_object(text)
    except RecursionError as exc:  # the decoder recurses once per level of nesting
        msg = "LLM reply nests JSON too deeply to decode"
        raise LLMResponseError(msg) from exc
    if found is None:
        msg = f"LLM reply holds no JSON object: {_snippet(text)}"
        raise LLMResponseError(msg)
    return found


def _first_object(text: str) -> dict[str, Any] | None:
    candidates = [text, *(m.group(1).strip() for m in _FENCE.finditer(text))]
    for candidate in candidates:
        try:
            value = json.loads(candidate)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    decoder = json.JSONDecoder()
    start = text.find("{")
    while start != -1:
        try:
            value, _ = decoder.raw_decode(text, start)
        except ValueError:
            value = None
        if isinstance(value, dict):
            return value
        start = text.find("{", start + 1)
    return None


def strip_thinking(text: str) -> str:
    """`text` less its complete <think>...</think> blocks (a reasoning model's), each from an opening tag
    to the first closing tag after it; from an opening tag that is never closed on, the text is kept.

    One linear pass with str.find: a lazy regex would look for a closing tag again from every later opening
    tag, quadratic in a reply of unclosed tags.
    """
    kept: list[str] = []
    position = 0
    while (start := text.find(_THINK_OPEN, position)) != -1:
        end = text.find(_THINK_CLOSE, start + len(_THINK_OPEN))
        if end == -1:
            break
        kept.append(text[position:start])
        position = end + len(_THINK_CLOSE)
    kept.append(text[position:])
    return "".join(kept)


def _retry_after_s(response: httpx.Response) -> float | None:
    value = response.headers.get("retry-after")
    try:
        seconds = float(value) if value is not None else None
    except ValueError:  # an HTTP date: keep the exponential backoff
        return None
    # float() also reads "nan" and "inf", which are no delay: keep the exponential backoff for those too.
    return max(seconds, 0.0) if seconds is not None and math.isfinite(seconds) else None


def _snippet(text: str, limit: int = 200) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[:limit] + "..."
