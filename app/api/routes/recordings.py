"""A session's recording (`app.sessions.recording`): its frames as JSON, or as an MCAP file for Foxglove."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, Field

from app.api import schemas
from app.api.deps import PrincipalDep, ServicesDep, SessionsDep
from app.api.errors import error_responses

router = APIRouter(prefix="/v1/sessions", tags=["recordings"])

_READ_ERRORS = error_responses(401, 403, 429, 404, 422, 503)
MCAP_MEDIA_TYPE = "application/x-mcap"


class RecordedHypothesis(BaseModel):
    text: str
    weight: float


class RecordedUtterance(BaseModel):
    """An utterance as the recording keeps it."""

    text: str
    fused: bool
    reason: str | None
    hypotheses: list[RecordedHypothesis]
    mixture: schemas.MixtureOut


class RecordingFrame(BaseModel):
    """One belief version (or an utterance that was not fused: no summary, the version it left)."""

    version: int
    at: float = Field(description="When the version was committed (s since the epoch, the store's clock).")
    cause: dict[str, Any] = Field(description="What made the version: the `cause` of its `belief` event.")
    target_label: str | None
    summary: schemas.PosteriorSummaryOut | None = Field(
        description="The version's posterior summary with its 100 most probable voxels (the belief snapshot)."
    )
    utterance: RecordedUtterance | None = Field(
        description="The utterance that made the version, if one did."
    )
    scene_graph: dict[str, Any] | None = Field(
        description="The scene graph (objects without attributes), on the first frame and at each change."
    )


class RecordingOut(BaseModel):
    session_id: str
    voxel_size: float
    frames: list[RecordingFrame] = Field(
        description="Oldest first; older frames thinned past `recording_frames` (docs/api.md)."
    )


AfterQuery = Annotated[
    int | None, Query(ge=0, description="Only the frames of later versions (and unfused utterances at it).")
]


@router.get(
    "/{session_id}/recording",
    operation_id="get_recording",
    response_model=RecordingOut,
    responses=_READ_ERRORS,
)
async def get_recording(
    session_id: str, principal: PrincipalDep, sessions: SessionsDep, after: AfterQuery = None
) -> Response:
    """The session's recorded frames: per version its summary and top voxels, utterances, scene graphs."""
    info = await sessions.get(principal, session_id)
    frames = [f.to_json() for f in await sessions.recording(principal, session_id, after)]
    body = {"session_id": session_id, "voxel_size": info.grid.voxel_size, "frames": frames}
    return Response(json.dumps(body), media_type="application/json")


@router.get(
    "/{session_id}/recording.mcap",
    operation_id="get_recording_mcap",
    response_class=Response,
    responses={
        200: {
            "description": "The recording as MCAP, with the topics of the live Foxglove view (docs/api.md).",
            "content": {MCAP_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
        **_READ_ERRORS,
    },
)
async def get_recording_mcap(
    session_id: str, principal: PrincipalDep, services: ServicesDep, sessions: SessionsDep
) -> Response:
    """The session's recording as an MCAP file that Foxglove opens (`vlmap record` downloads it)."""
    from app.foxglove.recording import mcap_bytes

    info = await sessions.get(principal, session_id)
    frames = [f.to_json() for f in await sessions.recording(principal, session_id)]
    data = await services.run(mcap_bytes, session_id, info.grid.voxel_size, frames)
    disposition = f'attachment; filename="{session_id}.mcap"'
    return Response(data, media_type=MCAP_MEDIA_TYPE, headers={"Content-Disposition": disposition})
