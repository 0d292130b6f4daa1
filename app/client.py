"""`VLMapClient` (sync) and `AsyncVLMapClient`: what robots, dashboards and the simulator use.

Numpy arrays in, msgpack on the wire for observation batches; JSON for everything else, except a scene graph
given as bytes: Spark-DSG binary (``DynamicSceneGraph.to_binary()``, what Hydra streams) goes as the body
itself, the request's other fields as query parameters. Every non-2xx answer raises `VLMapHTTPError` carrying
the service's error code, message and field.

Retries: every call that changes a session carries an `Idempotency-Key` (a fresh UUID per call unless the
caller gives one), so every call can be repeated safely: one whose connection failed or timed out, or that
got a 429, 502, 503 or 504, is sent again with the same key up to `retries` times (after Retry-After when
the service gives one, else an exponential backoff), and the service applies it once.

    with VLMapClient("http://127.0.0.1:8000", api_key=KEY) as vl:
        session = vl.create_session("robot-7", scene_graph)
        vl.send_utterance(session["id"], "I left my backpack on the table")
        vl.send_observations(session["id"], voxels=ijk, labels=label_ids)
        belief, etag = vl.get_belief(session["id"])

Push streams: `session_events(id)` and `fleet_events(robot_id)` iterate a stream's events (`StreamEvent`:
"belief" for each version, "sync" when the state should be read again; docs/api.md), reconnecting with
Last-Event-ID when the connection ends (the server ends each stream after a while), so that no event is
missed or repeated while the service's history reaches back that far (else a "sync" says so). A session
stream ends after the session's "deleted" event.

    for event in vl.session_events(session["id"]):
        if event.event == "sync" or event.data["version"] != shown:
            belief, etag = vl.get_belief(session["id"], etag)
"""

from __future__ import annotations

import asyncio
import base64
import json
import random
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import msgpack
import numpy as np

from app.sessions.batch import encode_msgpack_batch


class VLMapHTTPError(Exception):
    """A non-2xx answer from the service."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.field = status, code, message, field


@dataclass(frozen=True)
class Request:
    """One HTTP call, built the same way for the sync and the async client."""

    method: str
    path: str
    kwargs: dict[str, Any]


#: Answers after which the same request (with its Idempotency-Key) may succeed.
RETRIED_STATUSES = frozenset({429, 502, 503, 504})
#: Longest pause between two attempts (seconds), whatever Retry-After says.
MAX_PAUSE_S = 10.0
#: The content type of a Spark-DSG binary scene graph.
SPARK_DSG = "application/x-spark-dsg"


def _with_scene_graph(scene_graph: Any, fields: dict[str, Any]) -> dict[str, Any]:
    """Request arguments of a body of `scene_graph` and `fields`: JSON, or for Spark-DSG binary bytes the
    bytes as the body and the fields as query parameters (text as it is, any other value as JSON)."""
    if isinstance(scene_graph, bytes | bytearray):
        params = {k: v if isinstance(v, str) else json.dumps(v) for k, v in fields.items()}
        return {"content": bytes(scene_graph), "headers": {"content-type": SPARK_DSG}, "params": params}
    return {"json": {"scene_graph": scene_graph, **fields}}


def _keyed(key: str | None, **kwargs: Any) -> dict[str, Any]:
    """Request arguments with an Idempotency-Key header (a fresh one unless given)."""
    headers = {**kwargs.pop("headers", {}), "Idempotency-Key": key or uuid.uuid4().hex}
    return {**kwargs, "headers": headers}


def _pause(attempt: int, backoff_s: float, response: httpx.Response | None) -> float:
    """Seconds to wait before attempt `attempt + 1`: Retry-After when the service gave one (within
    [0, MAX_PAUSE_S]: a negative one would make time.sleep raise), else an exponential backoff with jitter."""
    if response is not None:
        try:
            return max(0.0, min(MAX_PAUSE_S, float(response.headers.get("retry-after", ""))))
        except ValueError:
            pass
    return min(MAX_PAUSE_S, backoff_s * 2.0**attempt) * random.uniform(0.5, 1.0)


@dataclass(frozen=True)
class BeliefGrid:
    """The whole posterior of a session (and its layers when asked for), as numpy arrays."""

    version: int
    origin: tuple[float, float, float]
    shape: tuple[int, int, int]
    voxel_size: float
    posterior: np.ndarray  # (N,) float32, sums to 1
    lang: np.ndarray | None = None
    vis: np.ndarray | None = None


@dataclass(frozen=True)
class TopDownView:
    """The posterior seen from above (`TopDownOut` in the OpenAPI): `mass[i, j]` is the mass of the column of
    voxels over x in [x0 + i s, x0 + (i + 1) s), y in [y0 + j s, y0 + (j + 1) s), (x0, y0) = `min_corner`."""

    version: int
    min_corner: tuple[float, float]
    voxel_size: float
    mass: np.ndarray  # (nx, ny) float32, sums to 1


@dataclass(frozen=True)
class StreamEvent:
    """One event of a push stream: `event` ("belief" or "sync"), its `id` (a stream resumes after it) and
    its `data` (the JSON object: `BeliefEvent` or `StreamSync` in the OpenAPI)."""

    event: str
    id: str | None
    data: dict[str, Any]


class _SseParser:
    """Server-Sent Events from lines, as the WHATWG spec reads them (comments and unknown fields ignored)."""

    def __init__(self) -> None:
        self.retry_ms: int | None = None
        self._event, self._id, self._data = "message", None, []  # type: tuple[str, str | None, list[str]]

    def feed(self, line: str) -> StreamEvent | None:
        if not line:
            event = None
            if self._data:
                event = StreamEvent(self._event, self._id, json.loads("\n".join(self._data)))
            self._event, self._data = "message", []
            return event
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "data":
            self._data.append(value)
        elif name == "event":
            self._event = value
        elif name == "id" and "\0" not in value:
            self._id = value
        elif name == "retry" and value.isdigit():
            self.retry_ms = int(value)
        return None


@dataclass
class _Follow:
    """A push stream as a client follows it: where, from which event on, and when it is over."""

    path: str
    params: dict[str, str]
    last_event_id: str | None
    reconnect: bool
    idle_timeout_s: float
    session: bool  # a session's stream: over after its "deleted" event
    connected: bool = False
    failures: int = 0  # attempts that failed in a row

    def request(self) -> Request:
        headers = {"Accept": "text/event-stream"}
        if self.last_event_id:
            headers["Last-Event-ID"] = self.last_event_id
        return Request("GET", self.path, {"params": self.params, "headers": headers})

    def took(self, event: StreamEvent) -> bool:
        """Note an event; True when the stream is over with it."""
        if event.id is not None:
            self.last_event_id = event.id
        kind = event.data.get("cause", {}).get("kind") if event.event == "belief" else None
        return self.session and kind == "deleted"

    def gone(self, response: httpx.Response) -> bool:
        """Whether an error answer ends the iteration quietly: a followed session that is gone."""
        return self.connected and self.session and response.status_code == 404

    def opened(self) -> None:
        self.connected, self.failures = True, 0

    def refused(self, response: httpx.Response, retries: int) -> httpx.Response:
        """An error answer: raised (`VLMapHTTPError`) unless it is worth another attempt."""
        if response.status_code not in RETRIED_STATUSES or self.failures >= retries:
            _checked(response)
        self.failures += 1
        return response

    def lost(self, retries: int) -> bool:
        """A connection that failed: whether to try again (not once `retries` failed in a row)."""
        self.failures += 1
        return self.failures <= retries


def _array(packed: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(packed["data"], dtype=np.dtype(packed["dtype"])).reshape(packed["shape"])


class _Calls:
    """The service's operations as `Request`s; no I/O here."""

    @staticmethod
    def ground(scene_graph: Any, utterance: str, **extra: Any) -> Request:
        fields = {"utterance": utterance, **extra}
        return Request("POST", "/v1/ground", _with_scene_graph(scene_graph, fields))

    @staticmethod
    def create_session(robot_id: str, scene_graph: Any, key: str | None = None, **fields: Any) -> Request:
        given = {"robot_id": robot_id, **{k: v for k, v in fields.items() if v is not None}}
        return Request("POST", "/v1/sessions", _keyed(key, **_with_scene_graph(scene_graph, given)))

    @staticmethod
    def list_sessions(robot_id: str | None) -> Request:
        return Request("GET", "/v1/sessions", {"params": {"robot_id": robot_id} if robot_id else {}})

    @staticmethod
    def get_session(session_id: str) -> Request:
        return Request("GET", f"/v1/sessions/{session_id}", {})

    @staticmethod
    def delete_session(session_id: str, key: str | None = None) -> Request:
        return Request("DELETE", f"/v1/sessions/{session_id}", _keyed(key))

    @staticmethod
    def replace_scene_graph(session_id: str, scene_graph: Any, key: str | None = None) -> Request:
        if isinstance(scene_graph, bytes | bytearray):
            body: dict[str, Any] = {"content": bytes(scene_graph), "headers": {"content-type": SPARK_DSG}}
        else:
            body = {"json": scene_graph}
        return Request("PUT", f"/v1/sessions/{session_id}/scene-graph", _keyed(key, **body))

    @staticmethod
    def send_utterance(
        session_id: str, utterance: str, options: dict[str, Any] | None, key: str | None = None
    ) -> Request:
        body = {"utterance": utterance, **({"options": options} if options else {})}
        return Request("POST", f"/v1/sessions/{session_id}/utterances", _keyed(key, json=body))

    @staticmethod
    def send_observations(
        session_id: str, summary: bool = True, key: str | None = None, **batch: Any
    ) -> Request:
        kwargs: dict[str, Any] = _keyed(
            key, content=encode_msgpack_batch(**batch), headers={"content-type": "application/msgpack"}
        )
        if not summary:
            kwargs["params"] = {"summary": "false"}
        return Request("POST", f"/v1/sessions/{session_id}/observations", kwargs)

    @staticmethod
    def get_belief(session_id: str, etag: str | None, top_k: int) -> Request:
        headers = {"If-None-Match": etag} if etag else {}
        return Request(
            "GET", f"/v1/sessions/{session_id}/belief", {"params": {"top_k": top_k}, "headers": headers}
        )

    @staticmethod
    def get_belief_topdown(session_id: str, etag: str | None) -> Request:
        headers = {"If-None-Match": etag} if etag else {}
        return Request("GET", f"/v1/sessions/{session_id}/belief/topdown", {"headers": headers})

    @staticmethod
    def get_scene_graph(session_id: str) -> Request:
        return Request("GET", f"/v1/sessions/{session_id}/scene-graph", {})

    @staticmethod
    def list_utterances(session_id: str) -> Request:
        return Request("GET", f"/v1/sessions/{session_id}/utterances", {})

    @staticmethod
    def session_events(session_id: str, after: str | None, reconnect: bool, idle_s: float) -> _Follow:
        return _Follow(f"/v1/sessions/{session_id}/events", {}, after, reconnect, idle_s, session=True)

    @staticmethod
    def fleet_events(robot_id: str | None, after: str | None, reconnect: bool, idle_s: float) -> _Follow:
        params = {"robot_id": robot_id} if robot_id else {}
        return _Follow("/v1/events", params, after, reconnect, idle_s, session=False)

    @staticmethod
    def get_recording(session_id: str, after: int | None) -> Request:
        params = {"after": after} if after is not None else {}
        return Request("GET", f"/v1/sessions/{session_id}/recording", {"params": params})

    @staticmethod
    def get_recording_mcap(session_id: str) -> Request:
        return Request("GET", f"/v1/sessions/{session_id}/recording.mcap", {})

    @staticmethod
    def get_belief_grid(session_id: str, layers: bool) -> Request:
        params = {"format": "grid", "layers": str(layers).lower()}
        return Request("GET", f"/v1/sessions/{session_id}/belief", {"params": params})


def _checked(response: httpx.Response) -> httpx.Response:
    if response.status_code < 400:
        return response
    try:
        body = response.json()
    except ValueError:
        body = {}
    if not isinstance(body, dict):  # JSON, but not the service's error object (a proxy's, say): no details
        body = {}
    raise VLMapHTTPError(
        response.status_code,
        str(body.get("code", "http_error")),
        str(body.get("message", response.text[:200])),
        body.get("field"),
    )


def _json(response: httpx.Response) -> Any:
    return _checked(response).json() if response.status_code != 204 else None


def _object(response: httpx.Response) -> dict[str, Any]:
    """The JSON object that every endpoint but delete answers with."""
    body: dict[str, Any] = _json(response)
    return body


def _belief(response: httpx.Response) -> tuple[dict[str, Any] | None, str | None]:
    """(summary, etag); summary is None when the belief has not changed (304)."""
    etag = response.headers.get("etag")
    if response.status_code == 304:
        return None, etag
    return _checked(response).json(), etag


def _top_down(response: httpx.Response) -> tuple[TopDownView | None, str | None]:
    """(view, etag); view is None when the belief has not changed (304)."""
    etag = response.headers.get("etag")
    if response.status_code == 304:
        return None, etag
    body = _checked(response).json()
    nx, ny = body["shape"]
    mass = np.frombuffer(base64.b64decode(body["mass"]), dtype="<f4").reshape(nx, ny)
    corner = (float(body["min_corner"][0]), float(body["min_corner"][1]))
    return TopDownView(body["version"], corner, float(body["voxel_size"]), mass), etag


def _grid(response: httpx.Response) -> BeliefGrid:
    data = msgpack.unpackb(_checked(response).content, raw=False)
    grid = data["grid"]
    return BeliefGrid(
        version=data["version"],
        origin=tuple(grid["origin"]),
        shape=tuple(grid["shape"]),
        voxel_size=grid["voxel_size"],
        posterior=_array(data["posterior"]),
        lang=_array(data["lang"]) if "lang" in data else None,
        vis=_array(data["vis"]) if "vis" in data else None,
    )


def _stream_timeout(timeout: httpx.Timeout, follow: _Follow) -> httpx.Timeout:
    """The client's timeouts, reading a stream for up to its idle time (keep-alives come well within it)."""
    return httpx.Timeout(timeout.connect, read=follow.idle_timeout_s, write=timeout.write, pool=timeout.pool)


def _headers(api_key: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {api_key}"} if api_key else {}


def read_api_key(path: Path) -> str:
    """The API key in a file (its first line), for an `--api-key-file`."""
    text = path.read_text(encoding="utf-8").strip()
    if not text:
        msg = f"{path} holds no API key"
        raise ValueError(msg)
    return text.splitlines()[0].strip()


class VLMapClient:
    """Blocking client (httpx); one connection pool, reused across calls. `retries`: attempts after the
    first for a call whose connection failed or that got a retryable status (module docstring)."""

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout_s: float = 30.0,
        retries: int = 4,
        backoff_s: float = 0.2,
        **httpx_kwargs: Any,
    ):
        self.http = httpx.Client(
            base_url=base_url, headers=_headers(api_key), timeout=timeout_s, **httpx_kwargs
        )
        self.retries, self.backoff_s = retries, backoff_s

    def _send(self, call: Request) -> httpx.Response:
        attempt = 0
        while True:
            response = None
            try:
                response = self.http.request(call.method, call.path, **call.kwargs)
            except httpx.TransportError:
                if attempt >= self.retries:
                    raise
            else:
                if response.status_code not in RETRIED_STATUSES or attempt >= self.retries:
                    return response
            time.sleep(_pause(attempt, self.backoff_s, response))
            attempt += 1

    def ground(self, scene_graph: Any, utterance: str, **extra: Any) -> dict[str, Any]:
        return _object(self._send(_Calls.ground(scene_graph, utterance, **extra)))

    def create_session(
        self, robot_id: str, scene_graph: Any, idempotency_key: str | None = None, **fields: Any
    ) -> dict[str, Any]:
        """fields: grid, target_label, sensor_model, label_map (see the OpenAPI's SessionCreate)."""
        return _object(self._send(_Calls.create_session(robot_id, scene_graph, idempotency_key, **fields)))

    def list_sessions(self, robot_id: str | None = None) -> list[dict[str, Any]]:
        sessions: list[dict[str, Any]] = _object(self._send(_Calls.list_sessions(robot_id)))["sessions"]
        return sessions

    def get_session(self, session_id: str) -> dict[str, Any]:
        return _object(self._send(_Calls.get_session(session_id)))

    def delete_session(self, session_id: str, idempotency_key: str | None = None) -> None:
        _json(self._send(_Calls.delete_session(session_id, idempotency_key)))

    def replace_scene_graph(
        self, session_id: str, scene_graph: Any, idempotency_key: str | None = None
    ) -> dict[str, Any]:
        return _object(self._send(_Calls.replace_scene_graph(session_id, scene_graph, idempotency_key)))

    def send_utterance(
        self,
        session_id: str,
        utterance: str,
        options: dict[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> dict[str, Any]:
        """The service's answer as a dict: "grounding", "belief", "fused" (false: the utterance was about
        another class than the session's target and left the belief as it was) and "reason" (why not fused,
        or why only the broad prior of an ungrounded utterance was; None otherwise)."""
        return _object(self._send(_Calls.send_utterance(session_id, utterance, options, idempotency_key)))

    def send_observations(
        self, session_id: str, summary: bool = True, idempotency_key: str | None = None, **batch: Any
    ) -> dict[str, Any]:
        """batch: voxels (N,3) or points (N,3); labels (N,) ids or names, or p_target (N,); stamp, tp, fp.

        summary=False leaves the posterior summary out of the answer (sensor-rate streams poll it apart).
        The batch is sent with an Idempotency-Key (`idempotency_key`, else a fresh one) and retried with it.
        """
        call = _Calls.send_observations(session_id, summary, idempotency_key, **batch)
        return _object(self._send(call))

    def get_belief(
        self, session_id: str, etag: str | None = None, top_k: int = 5
    ) -> tuple[dict[str, Any] | None, str | None]:
        """(summary or None if unchanged since `etag`, the current ETag)."""
        return _belief(self._send(_Calls.get_belief(session_id, etag, top_k)))

    def get_belief_grid(self, session_id: str, layers: bool = False) -> BeliefGrid:
        return _grid(self._send(_Calls.get_belief_grid(session_id, layers)))

    def get_belief_topdown(
        self, session_id: str, etag: str | None = None
    ) -> tuple[TopDownView | None, str | None]:
        """(the posterior seen from above, or None if unchanged since `etag`; the current ETag)."""
        return _top_down(self._send(_Calls.get_belief_topdown(session_id, etag)))

    def get_scene_graph(self, session_id: str) -> dict[str, Any]:
        """The scene graph the session grounds utterances in (native format)."""
        return _object(self._send(_Calls.get_scene_graph(session_id)))

    def list_utterances(self, session_id: str) -> dict[str, Any]:
        """The utterances still in the session's event history: `UtteranceHistoryOut` in the OpenAPI."""
        return _object(self._send(_Calls.list_utterances(session_id)))

    def get_recording(self, session_id: str, after: int | None = None) -> dict[str, Any]:
        """The session's recorded frames (after version `after`): `RecordingOut` in the OpenAPI."""
        return _object(self._send(_Calls.get_recording(session_id, after)))

    def get_recording_mcap(self, session_id: str) -> bytes:
        """The session's recording as an MCAP file (the topics of the live Foxglove view)."""
        return _checked(self._send(_Calls.get_recording_mcap(session_id))).content

    def session_events(
        self,
        session_id: str,
        last_event_id: str | None = None,
        *,
        reconnect: bool = True,
        idle_timeout_s: float = 60.0,
    ) -> Iterator[StreamEvent]:
        """The session's events (after `last_event_id`, if given), until its "deleted" event; reconnecting
        (`reconnect`) when the stream ends or nothing, not even a keep-alive, came for `idle_timeout_s`."""
        return self._follow(_Calls.session_events(session_id, last_event_id, reconnect, idle_timeout_s))

    def fleet_events(
        self,
        robot_id: str | None = None,
        last_event_id: str | None = None,
        *,
        reconnect: bool = True,
        idle_timeout_s: float = 60.0,
    ) -> Iterator[StreamEvent]:
        """The events of every session the key may read (of `robot_id`'s only, if given), as
        `session_events` follows one session's."""
        return self._follow(_Calls.fleet_events(robot_id, last_event_id, reconnect, idle_timeout_s))

    def _follow(self, follow: _Follow) -> Iterator[StreamEvent]:
        while True:
            refused: httpx.Response | None = None
            try:
                call = follow.request()
                timeout = _stream_timeout(self.http.timeout, follow)
                with self.http.stream(call.method, call.path, timeout=timeout, **call.kwargs) as response:
                    if response.status_code >= 400:
                        response.read()
                        if follow.gone(response):
                            return
                        refused = follow.refused(response, self.retries)
                    else:
                        follow.opened()
                        parser = _SseParser()
                        for line in response.iter_lines():
                            event = parser.feed(line)
                            if event is not None:
                                over = follow.took(event)
                                yield event
                                if over:
                                    return
            except httpx.TransportError:
                if not follow.lost(self.retries):
                    raise
            if not follow.reconnect:
                return
            if follow.failures:  # else the server ended the stream: resume at once
                time.sleep(_pause(follow.failures - 1, self.backoff_s, refused))

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> VLMapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncVLMapClient:
    """The same operations for asyncio programs, retried the same way."""

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout_s: float = 30.0,
        retries: int = 4,
        backoff_s: float = 0.2,
        **httpx_kwargs: Any,
    ):
        self.http = httpx.AsyncClient(
            base_url=base_url, headers=_headers(api_key), timeout=timeout_s, **httpx_kwargs
        )
        self.retries, self.backoff_s = retries, backoff_s

    async def _send(self, call: Request) -> httpx.Response:
        attempt = 0
        while True:
            response = None
            try:
                response = await self.http.request(call.method, call.path, **call.kwargs)
            except httpx.TransportError:
                if attempt >= self.retries:
                    raise
            else:
                if response.status_code not in RETRIED_STATUSES or attempt >= self.retries:
                    return response
            await asyncio.sleep(_pause(attempt, self.backoff_s, response))
            attempt += 1

    async def ground(self, scene_graph: Any, utterance: str, **extra: Any) -> dict[str, Any]:
        return _object(await self._send(_Calls.ground(scene_graph, utterance, **extra)))

    async def create_session(
        self, robot_id: str, scene_graph: Any, idempotency_key: str | None = None, **fields: Any
    ) -> dict[str, Any]:
        call = _Calls.create_session(robot_id, scene_graph, idempotency_key, **fields)
        return _object(await self._send(call))

    async def list_sessions(self, robot_id: str | None = None) -> list[dict[str, Any]]:
        sessions: list[dict[str, Any]] = _object(await self._send(_Calls.list_sessions(robot_id)))["sessions"]
        return sessions

    async def get_session(self, session_id: str) -> dict[str, Any]:
        return _object(await self._send(_Calls.get_session(session_id)))

    async def delete_session(self, session_id: str, idempotency_key: str | None = None) -> None:
        _json(await self._send(_Calls.delete_session(session_id, idempotency_key)))

    async def replace_scene_graph(
        self, session_id: str, scene_graph: Any, idempotency_key: str | None = None
    ) -> dict[str, Any]:
        return _object(await self._send(_Calls.replace_scene_graph(session_id, scene_graph, idempotency_key)))

    async def send_utterance(
        self,
        session_id: str,
        utterance: str,
        options: dict[str, Any] | None = None,
        idempotency_key: str | None = None,
    ) -> dict[str, Any]:
        """As `VLMapClient.send_utterance`: a dict with "grounding", "belief", "fused" and "reason"."""
        call = _Calls.send_utterance(session_id, utterance, options, idempotency_key)
        return _object(await self._send(call))

    async def send_observations(
        self, session_id: str, summary: bool = True, idempotency_key: str | None = None, **batch: Any
    ) -> dict[str, Any]:
        call = _Calls.send_observations(session_id, summary, idempotency_key, **batch)
        return _object(await self._send(call))

    async def get_belief(
        self, session_id: str, etag: str | None = None, top_k: int = 5
    ) -> tuple[dict[str, Any] | None, str | None]:
        return _belief(await self._send(_Calls.get_belief(session_id, etag, top_k)))

    async def get_belief_grid(self, session_id: str, layers: bool = False) -> BeliefGrid:
        return _grid(await self._send(_Calls.get_belief_grid(session_id, layers)))

    async def get_belief_topdown(
        self, session_id: str, etag: str | None = None
    ) -> tuple[TopDownView | None, str | None]:
        return _top_down(await self._send(_Calls.get_belief_topdown(session_id, etag)))

    async def get_scene_graph(self, session_id: str) -> dict[str, Any]:
        return _object(await self._send(_Calls.get_scene_graph(session_id)))

    async def list_utterances(self, session_id: str) -> dict[str, Any]:
        return _object(await self._send(_Calls.list_utterances(session_id)))

    async def get_recording(self, session_id: str, after: int | None = None) -> dict[str, Any]:
        return _object(await self._send(_Calls.get_recording(session_id, after)))

    async def get_recording_mcap(self, session_id: str) -> bytes:
        return _checked(await self._send(_Calls.get_recording_mcap(session_id))).content

    def session_events(
        self,
        session_id: str,
        last_event_id: str | None = None,
        *,
        reconnect: bool = True,
        idle_timeout_s: float = 60.0,
    ) -> AsyncIterator[StreamEvent]:
        """As `VLMapClient.session_events`."""
        return self._follow(_Calls.session_events(session_id, last_event_id, reconnect, idle_timeout_s))

    def fleet_events(
        self,
        robot_id: str | None = None,
        last_event_id: str | None = None,
        *,
        reconnect: bool = True,
        idle_timeout_s: float = 60.0,
    ) -> AsyncIterator[StreamEvent]:
        """As `VLMapClient.fleet_events`."""
        return self._follow(_Calls.fleet_events(robot_id, last_event_id, reconnect, idle_timeout_s))

    async def _follow(self, follow: _Follow) -> AsyncIterator[StreamEvent]:
        while True:
            refused: httpx.Response | None = None
            try:
                call = follow.request()
                timeout = _stream_timeout(self.http.timeout, follow)
                stream = self.http.stream(call.method, call.path, timeout=timeout, **call.kwargs)
                async with stream as response:
                    if response.status_code >= 400:
                        await response.aread()
                        if follow.gone(response):
                            return
                        refused = follow.refused(response, self.retries)
                    else:
                        follow.opened()
                        parser = _SseParser()
                        async for line in response.aiter_lines():
                            event = parser.feed(line)
                            if event is not None:
                                over = follow.took(event)
                                yield event
                                if over:
                                    return
            except httpx.TransportError:
                if not follow.lost(self.retries):
                    raise
            if not follow.reconnect:
                return
            if follow.failures:
                await asyncio.sleep(_pause(follow.failures - 1, self.backoff_s, refused))

    async def aclose(self) -> None:
        await self.http.aclose()

    async def __aenter__(self) -> AsyncVLMapClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
