"""`VLMapClient` (sync) and `AsyncVLMapClient`: what robots, dashboards and the simulator use.

Numpy arrays in, msgpack on the wire for observation batches; JSON for everything else. Every non-2xx
answer raises `VLMapHTTPError` carrying the service's error code, message and field.

    with VLMapClient("http://127.0.0.1:8000", api_key=KEY) as vl:
        session = vl.create_session("robot-7", scene_graph)
        vl.send_utterance(session["id"], "I left my backpack on the table")
        vl.send_observations(session["id"], voxels=ijk, labels=label_ids)
        belief, etag = vl.get_belief(session["id"])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import httpx
import msgpack
import numpy as np

from app.api.wire import encode_msgpack_batch


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


def _array(packed: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(packed["data"], dtype=np.dtype(packed["dtype"])).reshape(packed["shape"])


class _Calls:
    """The service's operations as `Request`s; no I/O here."""

    @staticmethod
    def ground(scene_graph: Any, utterance: str, **extra: Any) -> Request:
        return Request(
            "POST", "/v1/ground", {"json": {"scene_graph": scene_graph, "utterance": utterance, **extra}}
        )

    @staticmethod
    def create_session(robot_id: str, scene_graph: Any, **fields: Any) -> Request:
        body = {
            "robot_id": robot_id,
            "scene_graph": scene_graph,
            **{k: v for k, v in fields.items() if v is not None},
        }
        return Request("POST", "/v1/sessions", {"json": body})

    @staticmethod
    def list_sessions(robot_id: str | None) -> Request:
        return Request("GET", "/v1/sessions", {"params": {"robot_id": robot_id} if robot_id else {}})

    @staticmethod
    def get_session(session_id: str) -> Request:
        return Request("GET", f"/v1/sessions/{session_id}", {})

    @staticmethod
    def delete_session(session_id: str) -> Request:
        return Request("DELETE", f"/v1/sessions/{session_id}", {})

    @staticmethod
    def replace_scene_graph(session_id: str, scene_graph: Any) -> Request:
        return Request("PUT", f"/v1/sessions/{session_id}/scene-graph", {"json": scene_graph})

    @staticmethod
    def send_utterance(session_id: str, utterance: str, options: dict[str, Any] | None) -> Request:
        body = {"utterance": utterance, **({"options": options} if options else {})}
        return Request("POST", f"/v1/sessions/{session_id}/utterances", {"json": body})

    @staticmethod
    def send_observations(session_id: str, summary: bool = True, **batch: Any) -> Request:
        kwargs: dict[str, Any] = {
            "content": encode_msgpack_batch(**batch),
            "headers": {"content-type": "application/msgpack"},
        }
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
    raise VLMapHTTPError(
        response.status_code,
        str(body.get("code", "http_error")),
        str(body.get("message", response.text[:200])),
        body.get("field"),
    )


def _json(response: httpx.Response) -> Any:
    return _checked(response).json() if response.status_code != 204 else None


def _belief(response: httpx.Response) -> tuple[dict[str, Any] | None, str | None]:
    """(summary, etag); summary is None when the belief has not changed (304)."""
    etag = response.headers.get("etag")
    if response.status_code == 304:
        return None, etag
    return _checked(response).json(), etag


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


def _headers(api_key: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {api_key}"} if api_key else {}


class VLMapClient:
    """Blocking client (httpx); one connection pool, reused across calls."""

    def __init__(
        self, base_url: str, api_key: str | None = None, timeout_s: float = 30.0, **httpx_kwargs: Any
    ):
        self.http = httpx.Client(
            base_url=base_url, headers=_headers(api_key), timeout=timeout_s, **httpx_kwargs
        )

    def _send(self, call: Request) -> httpx.Response:
        return self.http.request(call.method, call.path, **call.kwargs)

    def ground(self, scene_graph: Any, utterance: str, **extra: Any) -> dict[str, Any]:
        return _json(self._send(_Calls.ground(scene_graph, utterance, **extra)))

    def create_session(self, robot_id: str, scene_graph: Any, **fields: Any) -> dict[str, Any]:
        """fields: grid, target_label, sensor_model, label_map (see the OpenAPI's SessionCreate)."""
        return _json(self._send(_Calls.create_session(robot_id, scene_graph, **fields)))

    def list_sessions(self, robot_id: str | None = None) -> list[dict[str, Any]]:
        return _json(self._send(_Calls.list_sessions(robot_id)))["sessions"]

    def get_session(self, session_id: str) -> dict[str, Any]:
        return _json(self._send(_Calls.get_session(session_id)))

    def delete_session(self, session_id: str) -> None:
        _json(self._send(_Calls.delete_session(session_id)))

    def replace_scene_graph(self, session_id: str, scene_graph: Any) -> dict[str, Any]:
        return _json(self._send(_Calls.replace_scene_graph(session_id, scene_graph)))

    def send_utterance(self, session_id: str, utterance: str, options: dict[str, Any] | None = None) -> dict:
        """The service's answer as a dict: "grounding", "belief", "fused" (false: the utterance was about
        another class than the session's target and left the belief as it was) and "reason" (why not fused,
        or why only the broad prior of an ungrounded utterance was; None otherwise)."""
        return _json(self._send(_Calls.send_utterance(session_id, utterance, options)))

    def send_observations(self, session_id: str, summary: bool = True, **batch: Any) -> dict[str, Any]:
        """batch: voxels (N,3) or points (N,3); labels (N,) ids or names, or p_target (N,); stamp, tp, fp.

        summary=False leaves the posterior summary out of the answer (sensor-rate streams poll it apart).
        """
        return _json(self._send(_Calls.send_observations(session_id, summary, **batch)))

    def get_belief(
        self, session_id: str, etag: str | None = None, top_k: int = 5
    ) -> tuple[dict[str, Any] | None, str | None]:
        """(summary or None if unchanged since `etag`, the current ETag)."""
        return _belief(self._send(_Calls.get_belief(session_id, etag, top_k)))

    def get_belief_grid(self, session_id: str, layers: bool = False) -> BeliefGrid:
        return _grid(self._send(_Calls.get_belief_grid(session_id, layers)))

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> VLMapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncVLMapClient:
    """The same operations for asyncio programs."""

    def __init__(
        self, base_url: str, api_key: str | None = None, timeout_s: float = 30.0, **httpx_kwargs: Any
    ):
        self.http = httpx.AsyncClient(
            base_url=base_url, headers=_headers(api_key), timeout=timeout_s, **httpx_kwargs
        )

    async def _send(self, call: Request) -> httpx.Response:
        return await self.http.request(call.method, call.path, **call.kwargs)

    async def ground(self, scene_graph: Any, utterance: str, **extra: Any) -> dict[str, Any]:
        return _json(await self._send(_Calls.ground(scene_graph, utterance, **extra)))

    async def create_session(self, robot_id: str, scene_graph: Any, **fields: Any) -> dict[str, Any]:
        return _json(await self._send(_Calls.create_session(robot_id, scene_graph, **fields)))

    async def list_sessions(self, robot_id: str | None = None) -> list[dict[str, Any]]:
        return _json(await self._send(_Calls.list_sessions(robot_id)))["sessions"]

    async def get_session(self, session_id: str) -> dict[str, Any]:
        return _json(await self._send(_Calls.get_session(session_id)))

    async def delete_session(self, session_id: str) -> None:
        _json(await self._send(_Calls.delete_session(session_id)))

    async def replace_scene_graph(self, session_id: str, scene_graph: Any) -> dict[str, Any]:
        return _json(await self._send(_Calls.replace_scene_graph(session_id, scene_graph)))

    async def send_utterance(
        self, session_id: str, utterance: str, options: dict[str, Any] | None = None
    ) -> dict:
        """As `VLMapClient.send_utterance`: a dict with "grounding", "belief", "fused" and "reason"."""
        return _json(await self._send(_Calls.send_utterance(session_id, utterance, options)))

    async def send_observations(self, session_id: str, summary: bool = True, **batch: Any) -> dict[str, Any]:
        return _json(await self._send(_Calls.send_observations(session_id, summary, **batch)))

    async def get_belief(
        self, session_id: str, etag: str | None = None, top_k: int = 5
    ) -> tuple[dict[str, Any] | None, str | None]:
        return _belief(await self._send(_Calls.get_belief(session_id, etag, top_k)))

    async def get_belief_grid(self, session_id: str, layers: bool = False) -> BeliefGrid:
        return _grid(await self._send(_Calls.get_belief_grid(session_id, layers)))

    async def aclose(self) -> None:
        await self.http.aclose()

    async def __aenter__(self) -> AsyncVLMapClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
