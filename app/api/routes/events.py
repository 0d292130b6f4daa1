"""The push stream: Server-Sent Events of one session (`/v1/sessions/{id}/events`) and of the fleet
(`/v1/events`), one `belief` event per version (`app.sessions.events` delivers them; docs/api.md).

Frames: `event: belief` (data: `BeliefEvent`), `event: sync` (data: `StreamSync`), each with an `id:`
to resume from (`Last-Event-ID`); a `: keep-alive` comment after `events_heartbeat_s` without an event;
`retry:` (ms) on the first frame. A stream ends after `events_max_stream_s`, after its session's deletion,
or when its client stops reading: a stream that has `events_buffer` events waiting is cut (its connection
closed, `EventStreamResponse`), never buffered further.
"""

from __future__ import annotations

import asyncio
import signal
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from types import FrameType
from typing import Annotated, Any, Literal

import anyio
from fastapi import APIRouter, FastAPI, Header
from fastapi.sse import format_sse_event
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter
from starlette.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from app.api import schemas
from app.api.deps import PrincipalDep, ServicesDep, SessionsDep
from app.api.errors import error_responses
from app.sessions.events import EventStream, StreamEnded, Sync
from app.settings import Settings
from app.stores.events import StoredEvent

#: The reconnection delay the first frame asks browsers for (ms).
RETRY_MS = 1000

# -- the events' JSON, documented (the stores write it: `app.stores.events.event_parts`) ---------------------


class _Cause(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CreatedCause(_Cause):
    """The session was created (version 0)."""

    kind: Literal["created"]


class UtteranceCause(_Cause):
    """An utterance: fused (a new version), or not (the same version: it named another class)."""

    kind: Literal["utterance"]
    utterance: str = Field(description="The utterance's text.")
    fused: bool = Field(description="Whether the belief took it (false: the version did not change).")
    reason: str | None = Field(description="Why it was not fused, or fused only as the broad prior.")
    named_target: str | None = Field(description="The target class it named, for a session that had none.")
    hypotheses: list[schemas.ReadingOut] | None = Field(
        default=None, description="Its readings with their weights, as grounded (absent before this release)."
    )


class ObservationsCause(_Cause):
    """A batch of labels or detector probabilities."""

    kind: Literal["observations"]
    batch: Literal["labels", "detections"]
    voxels_updated: int = Field(ge=0, description="Voxels of the grid the batch changed.")
    voxels_outside: int = Field(ge=0, description="Points or voxels of the batch outside the grid.")
    stamp: float | None = Field(description="The batch's own time stamp, as the robot sent it.")


class SceneGraphCause(_Cause):
    """The scene graph was replaced."""

    kind: Literal["scene_graph"]
    objects: int = Field(ge=0)
    regions: int = Field(ge=0)


class UpdateCause(_Cause):
    """Another change of the session (its writer did not describe it)."""

    kind: Literal["update"]


class DeletedCause(_Cause):
    """The session was deleted (its last event; `version` is its last version)."""

    kind: Literal["deleted"]


Cause = Annotated[
    CreatedCause | UtteranceCause | ObservationsCause | SceneGraphCause | UpdateCause | DeletedCause,
    Field(discriminator="kind"),
]


class BeliefEvent(BaseModel):
    """The data of a `belief` event: a session's new version (or its deletion, or an utterance it did not
    fuse), what caused it, and where its summary is."""

    model_config = ConfigDict(extra="forbid")

    session_id: str
    robot_id: str
    created_at: float = Field(description="When the session was created (Unix s): tells its lives apart.")
    version: int = Field(ge=0, description='The version after the event (its summary\'s ETag: "v<version>").')
    updated_at: float = Field(description="When the event happened (Unix s).")
    target_label: str = Field(description='The session\'s target class after the event ("": none yet).')
    cause: Cause
    summary_url: str = Field(description='The posterior summary to GET (If-None-Match: "v<version>").')


class StreamSync(BaseModel):
    """The data of a `sync` event: read the current state now (the summary, or the session list); every
    event after this one follows. `reason`: "start" (a stream that resumed nothing), "expired" (its
    Last-Event-ID is older than the history, or unknown), "gap" (events were lost on the way)."""

    model_config = ConfigDict(extra="forbid")

    reason: Literal["start", "expired", "gap"]
    session_id: str | None = Field(default=None, description="Session streams: the session.")
    robot_id: str | None = Field(default=None, description="The session's robot, or the one asked for.")
    version: int | None = Field(default=None, description="Session streams: the session's version now.")
    summary_url: str | None = Field(default=None, description="Session streams: what to read again.")
    sessions_url: str | None = Field(default=None, description="Fleet streams: what to read again.")


EventData = Annotated[BeliefEvent | StreamSync, Field(description="A `belief` or a `sync` event's data.")]


# -- the stream's answer -------------------------------------------------------------------------------------


def _frame(item: StoredEvent | Sync, retry: int | None) -> bytes:
    if isinstance(item, StoredEvent):
        return format_sse_event(data_str=item.data, event="belief", id=item.stream_id, retry=retry)
    return format_sse_event(data_str=item.data, event="sync", id=item.id, retry=retry)


async def frames(stream: EventStream, settings: Settings) -> AsyncIterator[bytes]:
    """The stream's frames, a keep-alive comment when it is quiet, until it ends or its time is up."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + settings.events_max_stream_s
    retry: int | None = RETRY_MS
    while (left := deadline - loop.time()) > 0:
        try:
            item = await stream.next(min(settings.events_heartbeat_s, left))
        except StreamEnded:
            return
        if item is not None:
            yield _frame(item, retry)
        elif deadline - loop.time() > 0:
            yield format_sse_event(comment="keep-alive", retry=retry)
        retry = None


class EventStreamResponse(StreamingResponse):
    """An event stream's frames (`frames`), cut off when its subscription is dropped: then their sending is
    abandoned, whatever it waits for, and the server closes the connection (a response left unfinished:
    uvicorn logs that it was). The subscription is closed when the answer ends. (No class `media_type`:
    the routes document their `text/event-stream` content themselves.)"""

    def __init__(self, stream: EventStream, settings: Settings) -> None:
        headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}  # no proxy buffering either
        super().__init__(frames(stream, settings), headers=headers, media_type="text/event-stream")
        self.stream = stream

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            async with anyio.create_task_group() as tasks:

                async def cut_off() -> None:
                    await self.stream.cut.wait()
                    tasks.cancel_scope.cancel()

                tasks.start_soon(cut_off)
                await super().__call__(scope, receive, send)
                tasks.cancel_scope.cancel()
        finally:
            self.stream.close()


# -- the routes ----------------------------------------------------------------------------------------------


@asynccontextmanager
async def end_streams_on_exit(app: FastAPI) -> AsyncIterator[None]:
    """The router's lifespan: on SIGTERM or SIGINT every event stream ends at once, and the signal goes on to
    the handler it had (uvicorn's). uvicorn stops gracefully by waiting for every answer in progress, and
    a stream would last up to `events_max_stream_s` (clients resume elsewhere with Last-Event-ID). Only in
    the main thread, and over a handler that Python runs (not under a test client, not over SIG_DFL)."""
    loop = asyncio.get_running_loop()
    previous: dict[int, Callable[[int, FrameType | None], Any]] = {}

    def end_streams() -> None:
        sessions = app.state.services.sessions
        if sessions is not None:
            sessions.events.shut()

    def on_exit(signum: int, frame: FrameType | None) -> None:
        loop.call_soon_threadsafe(end_streams)
        previous[signum](signum, frame)

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            handler = signal.getsignal(sig)
            if callable(handler):
                previous[sig] = handler
                signal.signal(sig, on_exit)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            if signal.getsignal(signum) is on_exit:
                signal.signal(signum, handler)


router = APIRouter(tags=["events"], lifespan=end_streams_on_exit)

_ERRORS = {
    status: {
        "description": entry["description"],
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}},
    }
    for status, entry in error_responses(401, 403, 404, 422, 429, 503).items()
}

_STREAM_DESCRIPTION = (
    "A Server-Sent Events stream (`text/event-stream`), one frame per event:\n\n"
    "- `event: belief`, data `BeliefEvent`: one per version of a session (created, an utterance fused, an "
    "observation batch, a scene-graph replacement, another update), one per deletion (its last event), and "
    "one per utterance not fused (`cause.fused` false, the same version);\n"
    "- `event: sync`, data `StreamSync`: read the current state now (`summary_url` or `sessions_url`); every "
    'event after it follows. First on a stream that resumes nothing ("start") or that asked to resume from '
    'an id older than the history ("expired"); "gap" where events were lost on the way;\n'
    "- `: keep-alive` comments when the stream is quiet; `retry:` on the first frame.\n\n"
    "Every event has an `id:`; reconnect with `Last-Event-ID: <id>` to get the events after it. Order: by "
    "version within a session. The stream ends after `events_max_stream_s` (resume), after its session's "
    "deletion, or when its client lets `events_buffer` events wait unread (its connection is closed)."
)


def _inlined(schema: Any, defs: dict[str, Any]) -> Any:
    """A JSON schema with its `$defs` references replaced by what they name (an operation's schema cannot
    refer to definitions of its own; OpenAPI's discriminator mappings go, `oneOf` says it all)."""
    if isinstance(schema, list):
        return [_inlined(item, defs) for item in schema]
    if not isinstance(schema, dict):
        return schema
    if "$ref" in schema:
        return _inlined(defs[schema["$ref"].rsplit("/", 1)[1]], defs)
    dropped = ("$defs", "discriminator")
    return {key: _inlined(value, defs) for key, value in schema.items() if key not in dropped}


def _data_schema() -> dict[str, Any]:
    schema = TypeAdapter(EventData).json_schema()
    inlined: dict[str, Any] = _inlined(schema, schema.get("$defs", {}))
    return inlined


#: One frame of the stream, as OpenAPI 3.2 describes a `text/event-stream` item (and FastAPI its own).
FRAME_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["event", "data"],
    "properties": {
        "event": {"type": "string", "enum": ["belief", "sync"]},
        "data": {"type": "string", "contentMediaType": "application/json", "contentSchema": _data_schema()},
        "id": {"type": "string"},
        "retry": {"type": "integer", "minimum": 0},
    },
}


def _responses(what: str) -> dict[int | str, dict[str, Any]]:
    stream = {"text/event-stream": {"itemSchema": FRAME_SCHEMA}}
    return {200: {"description": f"{what}\n\n{_STREAM_DESCRIPTION}", "content": stream}, **_ERRORS}


LastEventIdHeader = Annotated[
    str | None,
    Header(
        max_length=300,
        description="The id of the last event received: the stream resumes after it (browsers send it when "
        "they reconnect).",
    ),
]


@router.get(
    "/v1/sessions/{session_id}/events",
    operation_id="session_events",
    response_class=EventStreamResponse,
    status_code=200,
    responses=_responses("The session's events, from now or after Last-Event-ID."),
)
async def session_events(
    session_id: str,
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    last_event_id: LastEventIdHeader = None,
) -> EventStreamResponse:
    """Push stream of one session's belief versions (Server-Sent Events): their causes and summary links."""
    stream = await sessions.session_events(principal, session_id, last_event_id)
    return EventStreamResponse(stream, services.settings)


@router.get(
    "/v1/events",
    operation_id="fleet_events",
    response_class=EventStreamResponse,
    status_code=200,
    responses=_responses("The events of every session the key may read (of one robot, if given)."),
)
async def fleet_events(
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    robot_id: schemas.RobotIdQuery = None,
    last_event_id: LastEventIdHeader = None,
) -> EventStreamResponse:
    """Push stream of the belief versions of every session the key may read, or of one robot (dashboards)."""
    stream = await sessions.fleet_events(principal, robot_id, last_event_id)
    return EventStreamResponse(stream, services.settings)
