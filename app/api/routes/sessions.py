"""VL-Map sessions over HTTP: each route decodes, calls `SessionService`, encodes (`app.sessions`)."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Annotated, TypeVar

from fastapi import APIRouter, Header, Request, Response

from app.api import schemas
from app.api.bodies import JsonBody, json_request_body, schema_ref
from app.api.deps import PrincipalDep, SensorsDep, ServicesDep, SessionsDep
from app.api.errors import error_responses
from app.api.idempotency import REPLAYED_HEADER, IdempotencyDep, replayable, with_answer
from app.api.routes.ground import caller_hypotheses, check_utterance, resolve_scene_graph, to_response
from app.api.scene_graph_bodies import SceneGraphBody, with_spark_dsg
from app.api.wire import BELIEF_RESPONSES, OBSERVATION_REQUEST_BODY, belief_grid_response, read_batch
from app.belief.summary import DEFAULT_TOP_K
from app.scene_graph.model import SceneGraph
from app.sessions import Applied

T = TypeVar("T")

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_AUTH = (401, 403, 429)
_WRITE_ERRORS = error_responses(400, *_AUTH, 404, 408, 413, 415, 422, 503)
_READ_ERRORS = error_responses(*_AUTH, 404, 422, 503)
_DELETE_RESPONSES = {**_READ_ERRORS, **replayable(204)}
_CONDITIONAL: dict[int | str, dict[str, object]] = {
    200: {"headers": {"ETag": {"description": "The belief version.", "schema": {"type": "string"}}}},
    304: {"description": "Not modified since the ETag given in If-None-Match."},
}


def _version_tag(version: int) -> str:
    """The ETag of a belief version ("v<version>"): the top-down view's, the grid's, the default summary's."""
    return f'"v{version}"'


def _summary_tag(version: int, top_k: int) -> str:
    """The ETag of a version's summary with `top_k` top voxels: the version's with the default top_k (what
    clients build from an event's version), "v<version>-k<top_k>" with another, so that a tag held for one
    top_k never makes a request for another a 304."""
    return _version_tag(version) if top_k == DEFAULT_TOP_K else f'"v{version}-k{top_k}"'


def _unchanged(etag: str, if_none_match: str | None) -> bool:
    """Whether If-None-Match names `etag`, the answer's current ETag, or is "*" (RFC 9110 §13.1.2: weak
    comparison, so a W/ tag that a proxy weakened still matches)."""
    if if_none_match is None:
        return False
    tags = [t.strip().removeprefix("W/") for t in if_none_match.split(",")]
    return "*" in tags or etag in tags


def _marked(applied: Applied[T], response: Response) -> Applied[T]:
    """The outcome, its answer marked as a replay when it is one."""
    if applied.replayed:
        response.headers[REPLAYED_HEADER] = "true"
    return applied


@router.post(
    "",
    operation_id="create_session",
    status_code=201,
    response_model=schemas.SessionOut,
    responses={**_WRITE_ERRORS, **replayable(201)},
    openapi_extra={"requestBody": with_spark_dsg(json_request_body(schema_ref("SessionCreate")))},
)
async def create_session(
    response: Response,
    body: Annotated[schemas.SessionCreate, SceneGraphBody(schemas.SessionCreate)],
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    idempotency: IdempotencyDep,
) -> schemas.SessionOut:
    """Start a belief for a robot: a uniform prior over a voxel grid around its scene graph."""
    principal.require_write(body.robot_id)
    request = body.request(await services.run(resolve_scene_graph, body.scene_graph, services.settings))
    applied = await sessions.create(principal, request, idempotency)
    return schemas.SessionOut.of(_marked(applied, response).value)


@router.get("", operation_id="list_sessions", response_model=schemas.SessionList, responses=_READ_ERRORS)
async def list_sessions(
    principal: PrincipalDep, sessions: SessionsDep, robot_id: schemas.RobotIdQuery = None
) -> schemas.SessionList:
    """List the sessions the caller may read, optionally of one robot (for dashboards)."""
    return schemas.SessionList(
        sessions=[schemas.SessionOut.of(i) for i in await sessions.sessions(principal, robot_id)]
    )


@router.get(
    "/{session_id}", operation_id="get_session", response_model=schemas.SessionOut, responses=_READ_ERRORS
)
async def get_session(session_id: str, principal: PrincipalDep, sessions: SessionsDep) -> schemas.SessionOut:
    """A session's metadata: robot, target class, grid and belief version."""
    return schemas.SessionOut.of(await sessions.get(principal, session_id))


@router.delete("/{session_id}", operation_id="delete_session", status_code=204, responses=_DELETE_RESPONSES)
async def delete_session(
    session_id: str, principal: PrincipalDep, sessions: SessionsDep, idempotency: IdempotencyDep
) -> Response:
    """Delete a session and its belief."""
    response = Response(status_code=204)
    _marked(await sessions.delete(principal, session_id, idempotency), response)
    return response


@router.put(
    "/{session_id}/scene-graph",
    operation_id="replace_scene_graph",
    response_model=schemas.SessionOut,
    responses={**_WRITE_ERRORS, **replayable()},
    openapi_extra={"requestBody": with_spark_dsg(json_request_body(schemas.scene_graph_payload_schema()))},
)
async def put_scene_graph(
    response: Response,
    session_id: str,
    scene_graph: Annotated[object, SceneGraphBody(schemas.SceneGraphPayload)],
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    idempotency: IdempotencyDep,
) -> schemas.SessionOut:
    """Replace the session's scene graph (Hydra keeps mapping); later utterances ground in the new one."""
    replacement = await services.run(resolve_scene_graph, scene_graph, services.settings)
    applied = await sessions.replace_scene_graph(principal, session_id, replacement, idempotency)
    return schemas.SessionOut.of(_marked(applied, response).value)


@router.post(
    "/{session_id}/utterances",
    operation_id="add_utterance",
    response_model=schemas.UtteranceOut,
    responses={**error_responses(400, *_AUTH, 404, 408, 409, 413, 415, 422, 503), **replayable()},
    openapi_extra={"requestBody": json_request_body(schema_ref("UtteranceIn"))},
)
async def post_utterance(
    response: Response,
    session_id: str,
    body: Annotated[schemas.UtteranceIn, JsonBody(schemas.UtteranceIn)],
    principal: PrincipalDep,
    sensors: SensorsDep,
    services: ServicesDep,
    sessions: SessionsDep,
    idempotency: IdempotencyDep,
) -> schemas.UtteranceOut:
    """Ground an utterance in the session's scene graph and fuse it unless its target is another class."""
    check_utterance(body.utterance, services.settings)
    options = body.options or schemas.GroundOptions()
    ground = partial(services.ground, sensors, options.grounder, options.proposer)
    ground = partial(ground, utterance=body.utterance, hypotheses=caller_hypotheses(options))
    prepared = await sessions.prepare_utterance(principal, session_id, ground, body.utterance)
    grounding, reason, fused = (
        to_response(prepared.grounding, prepared.sensor, None),
        prepared.reason,
        prepared.fused,
    )
    keyed = with_answer(idempotency, schemas.UtteranceOut.answer(grounding, reason, fused))
    applied = _marked(await sessions.fuse_utterance(principal, prepared, keyed), response)
    if applied.replayed:
        grounding, reason, fused = schemas.UtteranceOut.first_answer(applied.answer, fused)
    belief = schemas.BeliefOut.of(applied.value)
    return schemas.UtteranceOut(grounding=grounding, belief=belief, fused=fused, reason=reason)


@router.post(
    "/{session_id}/observations",
    operation_id="add_observations",
    response_model=schemas.ObservationOut,
    responses={**error_responses(400, *_AUTH, 404, 408, 409, 413, 415, 422, 503), **replayable()},
    openapi_extra={"requestBody": OBSERVATION_REQUEST_BODY},
)
async def post_observations(
    session_id: str,
    request: Request,
    response: Response,
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    summary: schemas.WithSummaryQuery = True,
    idempotency: IdempotencyDep = None,
) -> schemas.ObservationOut:
    """Fuse one batch of semantic observations (JSON or msgpack) and return the posterior summary."""
    limits = services.settings.max_batch_voxels, services.settings.max_validation_errors
    batch = await read_batch(request, services.run, *limits)
    applied = await sessions.observe(principal, session_id, batch, idempotency, with_summary=summary)
    result, belief = _marked(applied, response).value
    return schemas.ObservationOut.of(result, batch.stamp, belief)


@router.get(
    "/{session_id}/belief",
    operation_id="get_belief",
    response_model=schemas.BeliefOut,
    responses={**_READ_ERRORS, **BELIEF_RESPONSES},
)
async def get_belief(
    session_id: str,
    principal: PrincipalDep,
    services: ServicesDep,
    sessions: SessionsDep,
    format: schemas.BeliefFormatQuery = "summary",
    layers: schemas.LayersQuery = False,
    top_k: schemas.TopKQuery = DEFAULT_TOP_K,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The fused posterior: summary (MAP, top voxels, moments, entropy, mass per object) or the whole grid."""
    info = await sessions.poll(principal, session_id, top_k)
    # The grid is every voxel, whatever top_k says: its tag is the version's (belief_grid_response).
    etag = _version_tag(info.version) if format == "grid" else _summary_tag(info.version, top_k)
    if _unchanged(etag, if_none_match):
        return Response(status_code=304, headers={"ETag": etag})
    if format == "grid":

        async def download(release: Callable[[], None]) -> Response:
            state = await sessions.grid(principal, session_id)
            return await services.run(belief_grid_response, state, layers, services.run, release)

        return await services.with_slot(
            services.grids, "max_concurrent_grids", "whole-grid downloads", download
        )
    belief = await sessions.belief(principal, session_id, top_k, info)
    body = schemas.BeliefOut.of(belief).model_dump_json()
    return Response(
        body, media_type="application/json", headers={"ETag": _summary_tag(belief.version, top_k)}
    )


@router.get(
    "/{session_id}/belief/topdown",
    operation_id="get_belief_topdown",
    response_model=schemas.TopDownOut,
    responses={**_READ_ERRORS, **_CONDITIONAL},
)
async def get_belief_topdown(
    session_id: str,
    principal: PrincipalDep,
    sessions: SessionsDep,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The posterior seen from above: its mass per (x, y) column of voxels, for a dashboard's heat map."""
    info = await sessions.get(principal, session_id)
    etag = _version_tag(info.version)
    if _unchanged(etag, if_none_match):
        return Response(status_code=304, headers={"ETag": etag})
    view = await sessions.top_down(principal, session_id)
    body = schemas.TopDownOut.of(view).model_dump_json()
    return Response(body, media_type="application/json", headers={"ETag": _version_tag(view.version)})


@router.get(
    "/{session_id}/scene-graph",
    operation_id="get_scene_graph",
    response_model=SceneGraph,
    responses=_READ_ERRORS,
)
async def get_scene_graph(session_id: str, principal: PrincipalDep, sessions: SessionsDep) -> Response:
    """The scene graph the session grounds utterances in (native format), e.g. to draw its objects."""
    scene_graph = await sessions.scene_graph(principal, session_id)
    return Response(scene_graph.model_dump_json(), media_type="application/json")


@router.get(
    "/{session_id}/utterances",
    operation_id="list_utterances",
    response_model=schemas.UtteranceHistoryOut,
    responses=_READ_ERRORS,
)
async def list_utterances(
    session_id: str, principal: PrincipalDep, sessions: SessionsDep
) -> schemas.UtteranceHistoryOut:
    """The utterances of the session's retained event history, with their readings and weights."""
    return schemas.UtteranceHistoryOut.of(await sessions.utterances(principal, session_id))
