"""VL-Map sessions: a per-robot voxel belief fusing utterances (language) and observation batches (vision).

Posterior over the target's voxel i: b_i = softmax_i(lang_i + vis_i), where each utterance adds
log(p_GMM(c_i) V) to lang and each observed voxel adds a log-likelihood ratio to vis (see app.belief).
"""

from __future__ import annotations

import json
import math
from collections.abc import AsyncIterator, Callable, Iterator
from functools import partial
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import TypeAdapter

from app.api.auth import Principal
from app.api.bodies import JsonBody, json_bytes, json_request_body, media_type, schema_ref, validate_json
from app.api.deps import PrincipalDep, SensorsDep, ServicesDep, SettingsDep, StoreDep
from app.api.errors import error_responses
from app.api.idempotency import IdempotencyKeyHeader, idempotency_of, replay, session_id_for, with_answer
from app.api.routes.ground import (
    caller_hypotheses,
    check_coordinates,
    resolve_scene_graph,
    scene_graph_payload_schema,
    to_response,
)
from app.api.schemas import (
    ROBOT_ID_PATTERN,
    BeliefOut,
    GridOut,
    GridSpec,
    GroundOptions,
    GroundResponse,
    ObservationBatchJson,
    ObservationOut,
    PosteriorSummaryOut,
    SceneGraphPayload,
    SessionCreate,
    SessionList,
    SessionOut,
    UtteranceIn,
    UtteranceOut,
)
from app.api.services import Services, SummaryCache
from app.api.wire import (
    MSGPACK_TYPES,
    ObservationBatch,
    belief_grid_stream,
    check_batch_size,
    decode_msgpack_batch,
)
from app.belief.grid import VoxelGrid
from app.belief.session import (
    LabelNames,
    SensorModel,
    SessionInfo,
    UpdateResult,
    check_target_label,
    new_session,
)
from app.belief.summary import place_voxels
from app.errors import AlreadyApplied, InvalidInput, LimitExceeded, UnsupportedMediaType
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from app.stores.base import Idempotency, SessionStore
from app.vocabulary import head_noun, lemmas, lexical_match, object_nouns

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_AUTH_ERRORS = (401, 403, 429)
_WRITE_ERRORS = error_responses(400, *_AUTH_ERRORS, 404, 408, 413, 415, 422, 503)
_READ_ERRORS = error_responses(*_AUTH_ERRORS, 404, 422, 503)
_REPLAYED = {
    "Idempotent-Replayed": {
        "description": "true when this answers a request repeated with its Idempotency-Key.",
        "schema": {"type": "string", "enum": ["true"]},
    }
}

_OBSERVATION_BODY = {
    "required": True,
    "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/ObservationBatchJson"}},
        "application/msgpack": {
            "schema": {
                "type": "object",
                "description": "The same batch as msgpack with raw little-endian arrays (app/api/wire.py).",
                "additionalProperties": False,
                "properties": {
                    "stamp": {"type": "number"},
                    "voxels": {"$ref": "#/components/schemas/PackedArray"},
                    "points": {"$ref": "#/components/schemas/PackedArray"},
                    "labels": {
                        "oneOf": [
                            {"$ref": "#/components/schemas/PackedArray"},
                            {"type": "array", "items": {"type": "string"}},
                        ]
                    },
                    "p_target": {"$ref": "#/components/schemas/PackedArray"},
                    "sensor_model": {"$ref": "#/components/schemas/SensorModelIn"},
                },
            }
        },
    },
}


def grid_out(grid: VoxelGrid) -> GridOut:
    return GridOut(
        min_corner=list(grid.origin),
        shape=list(grid.shape),
        voxel_size=grid.voxel_size,
        n_voxels=grid.n_voxels,
    )


def session_out(info: SessionInfo) -> SessionOut:
    return SessionOut(
        id=info.id,
        robot_id=info.robot_id,
        target_label=info.target_label or None,
        version=info.version,
        created_at=info.created_at,
        updated_at=info.updated_at,
        grid=grid_out(info.grid),
    )


def belief_out(
    store: SessionStore, cache: SummaryCache, session_id: str, top_k: int = 5, info: SessionInfo | None = None
) -> BeliefOut:
    """The posterior summary of the current version, computed once per version."""
    info = info or store.info(session_id)
    cached = cache.get((session_id, info.version, top_k))
    if cached is not None:
        return cached
    summary = store.summary(session_id, top_k=top_k)
    version = info.version if summary.version is None else summary.version
    body = BeliefOut(
        session_id=session_id,
        version=version,
        target_label=info.target_label or None,
        summary=PosteriorSummaryOut.model_validate(summary.to_dict()),
    )
    cache.put((session_id, version, top_k), body)
    return body


def names_a_class(target: str, label_map: dict[int, str]) -> bool:
    """Whether an utterance's target phrase can serve as the session's target class."""
    try:
        check_target_label(target, label_map)
    except InvalidInput:
        return False
    return True


def etag(version: int) -> str:
    return f'"v{version}"'


def _grid(spec: GridSpec | None, scene_graph: SceneGraph, settings: Settings) -> VoxelGrid:
    spec = spec or GridSpec()
    low_corner, high_corner = spec.min_corner, spec.max_corner
    if low_corner is None and high_corner is None:
        return VoxelGrid.around(
            scene_graph, voxel_size=spec.voxel_size, margin=spec.margin, max_voxels=settings.max_grid_voxels
        )
    if low_corner is None or high_corner is None:
        msg = "give both min_corner and max_corner, or neither"
        raise InvalidInput(msg, field="grid.min_corner")
    check_coordinates("grid.min_corner", [low_corner], settings)
    check_coordinates("grid.max_corner", [high_corner], settings)
    low, high = np.asarray(low_corner, dtype=np.float64), np.asarray(high_corner, dtype=np.float64)
    if not np.all(high > low):
        msg = "max_corner must be above min_corner on every axis"
        raise InvalidInput(msg, field="grid.max_corner")
    shape = [math.ceil(float(extent) / spec.voxel_size) for extent in high - low]  # Python ints: no overflow
    if math.prod(shape) > settings.max_grid_voxels:
        msg = f"the grid needs {math.prod(shape):,} voxels, more than the limit {settings.max_grid_voxels:,}"
        raise LimitExceeded(msg, limit_name="max_grid_voxels")
    nx, ny, nz = shape
    return VoxelGrid(origin=tuple(low), shape=(nx, ny, nz), voxel_size=spec.voxel_size)


def _label_map(raw: dict[str, str] | None, settings: Settings) -> dict[int, str]:
    """The label map with integer ids (the schema has checked that each key is 1-10 ASCII digits)."""
    if raw is not None and len(raw) > settings.max_label_map_entries:
        msg = f"{len(raw)} entries exceed the limit of {settings.max_label_map_entries}"
        raise LimitExceeded(f"label_map: {msg}", limit_name="max_label_map_entries")
    out: dict[int, str] = {}
    for key, name in (raw or {}).items():
        if int(key) >= 2**32:
            msg = f"label ids are uint32 (below 4294967296), got {key}"
            raise InvalidInput(msg, field=f"label_map.{key}")
        out[int(key)] = name
    return out


def check_places(grid: VoxelGrid, scene_graph: SceneGraph, settings: Settings) -> None:
    """LimitExceeded unless the voxels of the scene graph's places on `grid` are within the limit: every
    summary of the session sums the belief over them."""
    total = place_voxels(grid, scene_graph)
    if total > settings.max_place_voxels:
        msg = (
            f"the scene graph's objects and regions cover {total:,} voxels of the grid (summed over them), "
            f"more than the limit {settings.max_place_voxels:,}; use larger voxels or fewer, smaller boxes"
        )
        raise LimitExceeded(msg, limit_name="max_place_voxels")


def create(
    body: SessionCreate,
    store: SessionStore,
    settings: Settings,
    idempotency: Idempotency | None,
    response: Response,
) -> SessionOut:
    scene_graph = resolve_scene_graph(body.scene_graph, settings)
    sensor = body.sensor_model
    grid = _grid(body.grid, scene_graph, settings)
    check_places(grid, scene_graph, settings)
    session = new_session(
        body.robot_id,
        scene_graph,
        body.target_label or "",
        label_map=_label_map(body.label_map, settings),
        sensor_model=SensorModel(sensor.tp, sensor.fp) if sensor else None,
        grid=grid,
        max_voxels=settings.max_grid_voxels,
        session_id=session_id_for(body.robot_id, idempotency) if idempotency is not None else None,
    )
    try:
        info = store.create(session, max_per_robot=settings.max_sessions_per_robot, idempotency=idempotency)
    except AlreadyApplied as exc:
        replay(exc.record, idempotency, response)
        info = store.info(session.id)
    return session_out(info)


@router.post(
    "",
    operation_id="create_session",
    status_code=201,
    response_model=SessionOut,
    responses={**_WRITE_ERRORS, 201: {"description": "Successful Response", "headers": _REPLAYED}},
    openapi_extra={"requestBody": json_request_body(schema_ref("SessionCreate"))},
)
async def create_session(
    request: Request,
    response: Response,
    body: Annotated[SessionCreate, JsonBody(SessionCreate)],
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> SessionOut:
    """Start a belief for a robot: a uniform prior over a voxel grid around its scene graph."""
    principal.require_write(body.robot_id)
    idempotency = idempotency_of(request, idempotency_key, await request.body())
    return await services.run(create, body, store, settings, idempotency, response)


@router.get("", operation_id="list_sessions", response_model=SessionList, responses=_READ_ERRORS)
async def list_sessions(
    principal: PrincipalDep,
    store: StoreDep,
    services: ServicesDep,
    robot_id: Annotated[
        str | None,
        Query(
            min_length=1, max_length=128, pattern=ROBOT_ID_PATTERN, description="Only this robot's sessions."
        ),
    ] = None,
) -> SessionList:
    """List the sessions the caller may read, optionally of one robot (for dashboards)."""
    infos = await services.run(store.list, robot_id)
    return SessionList(sessions=[session_out(i) for i in infos if principal.can_read(i.robot_id)])


def _readable(store: SessionStore, principal: Principal, session_id: str) -> SessionInfo:
    info = store.info(session_id)
    principal.require_read(info.robot_id)
    return info


def _writable(store: SessionStore, principal: Principal, session_id: str) -> SessionInfo:
    info = store.info(session_id)
    principal.require_write(info.robot_id)
    return info


@router.get("/{session_id}", operation_id="get_session", response_model=SessionOut, responses=_READ_ERRORS)
async def get_session(
    session_id: str, principal: PrincipalDep, store: StoreDep, services: ServicesDep
) -> SessionOut:
    """A session's metadata: robot, target class, grid and belief version."""
    return session_out(await services.run(_readable, store, principal, session_id))


def delete(
    store: SessionStore, principal: Principal, session_id: str, idempotency: Idempotency | None
) -> Response:
    response = Response(status_code=204)
    try:
        store.delete(session_id, authorize=principal.require_write, idempotency=idempotency)
    except AlreadyApplied as exc:
        replay(exc.record, idempotency, response)
    return response


@router.delete(
    "/{session_id}",
    operation_id="delete_session",
    status_code=204,
    responses={**_READ_ERRORS, 204: {"description": "Successful Response", "headers": _REPLAYED}},
)
async def delete_session(
    request: Request,
    session_id: str,
    principal: PrincipalDep,
    store: StoreDep,
    services: ServicesDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> Response:
    """Delete a session and its belief."""
    idempotency = idempotency_of(request, idempotency_key, b"")
    return await services.run(delete, store, principal, session_id, idempotency)


def replace_scene_graph(
    store: SessionStore,
    principal: Principal,
    session_id: str,
    payload: object,
    settings: Settings,
    idempotency: Idempotency | None,
    response: Response,
) -> SessionOut:
    info = _writable(store, principal, session_id)
    scene_graph = resolve_scene_graph(payload, settings)  # type: ignore[arg-type]
    check_places(info.grid, scene_graph, settings)
    try:
        store.replace_scene_graph(session_id, scene_graph, idempotency=idempotency)
    except AlreadyApplied as exc:
        replay(exc.record, idempotency, response)
    return session_out(store.info(session_id))


@router.put(
    "/{session_id}/scene-graph",
    operation_id="replace_scene_graph",
    response_model=SessionOut,
    responses={**_WRITE_ERRORS, 200: {"description": "Successful Response", "headers": _REPLAYED}},
    openapi_extra={"requestBody": json_request_body(scene_graph_payload_schema())},
)
async def put_scene_graph(
    request: Request,
    response: Response,
    session_id: str,
    scene_graph: Annotated[object, JsonBody(SceneGraphPayload)],
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> SessionOut:
    """Replace the session's scene graph (Hydra keeps mapping); later utterances ground in the new one."""
    idempotency = idempotency_of(request, idempotency_key, await request.body())
    return await services.run(
        replace_scene_graph, store, principal, session_id, scene_graph, settings, idempotency, response
    )


def utterance_context(
    store: SessionStore, principal: Principal, session_id: str
) -> tuple[SessionInfo, SceneGraph]:
    """What grounding an utterance in a session needs, once the caller may write it."""
    return _writable(store, principal, session_id), store.scene_graph(session_id)


def utterance_verdict(target_label: str, result: Grounding) -> tuple[bool, str | None]:
    """Whether a session looking for `target_label` fuses this grounding, and what to tell the caller.

    Not fused: the session has a target class and the utterance's target phrase names an object class (its
    lemmatised head noun, or the whole phrase, is one of `object_nouns()`) that no naming of the session's
    matches (`lexical_match` 0; "bag" names a backpack loosely, "keys" a keychain). A phrase that names no
    object ("it", "something", empty) fuses. An utterance that was not grounded fuses its broad prior, and
    the reason says that the belief got only that.
    """
    spoken = result.proposal.parse.target
    phrase = lemmas(spoken)
    names_an_object = phrase in object_nouns() or head_noun(phrase) in object_nouns()
    if target_label and names_an_object and lexical_match(phrase, lemmas(target_label)) == 0:
        return (
            False,
            f"the utterance's target {spoken!r} is not the session's target {target_label!r}: not fused",
        )
    if not result.grounded:
        why = f" ({result.proposal.reason})" if result.proposal.reason else ""
        return True, f"not grounded{why}: the belief got only the broad prior"
    return True, None


def fuse_utterance(
    store: SessionStore,
    cache: SummaryCache,
    info: SessionInfo,
    result: Grounding,
    sensor: LanguageSensor,
    idempotency: Idempotency | None,
    response: Response,
) -> UtteranceOut:
    """Add an utterance to the belief unless `utterance_verdict` refuses it; while the session has no target
    class, the utterance's target phrase names it (in the same update)."""
    fused, reason = utterance_verdict(info.target_label, result)
    grounding = to_response(result, sensor, None)
    if fused:
        target = result.proposal.parse.target
        names = target if not info.target_label and target and names_a_class(target, info.label_map) else None
        # What the answer says besides the belief: remembered with the key, so that a retry repeats it.
        answer = json.dumps({"grounding": grounding.model_dump(mode="json"), "reason": reason}).encode()
        try:
            store.apply_utterance(
                info.id, result.mixture, target_label=names, idempotency=with_answer(idempotency, answer)
            )
        except AlreadyApplied as exc:
            first = json.loads(replay(exc.record, idempotency, response).answer)
            grounding, reason = GroundResponse.model_validate(first["grounding"]), first["reason"]
    belief = belief_out(store, cache, info.id)
    return UtteranceOut(grounding=grounding, belief=belief, fused=fused, reason=reason)


@router.post(
    "/{session_id}/utterances",
    operation_id="add_utterance",
    response_model=UtteranceOut,
    responses={**_WRITE_ERRORS, 200: {"description": "Successful Response", "headers": _REPLAYED}},
    openapi_extra={"requestBody": json_request_body(schema_ref("UtteranceIn"))},
)
async def post_utterance(
    request: Request,
    response: Response,
    session_id: str,
    body: Annotated[UtteranceIn, JsonBody(UtteranceIn)],
    principal: PrincipalDep,
    store: StoreDep,
    sensors: SensorsDep,
    services: ServicesDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> UtteranceOut:
    """Ground an utterance in the session's scene graph and fuse it unless its target is another class."""
    idempotency = idempotency_of(request, idempotency_key, await request.body())
    options = body.options or GroundOptions()
    info, scene_graph = await services.run(utterance_context, store, principal, session_id)
    result, sensor = await services.ground(
        sensors, options.grounder, options.proposer, scene_graph, body.utterance, caller_hypotheses(options)
    )
    return await services.run(
        fuse_utterance, store, services.summaries, info, result, sensor, idempotency, response
    )


_JSON_BATCH = TypeAdapter(ObservationBatchJson)


def decode_json_batch(raw: bytes, max_voxels: int, max_errors: int) -> ObservationBatch:
    body = validate_json(_JSON_BATCH, raw, max_errors)
    n = len(body.voxels or body.points or [])
    check_batch_size(max(n, len(body.labels or body.p_target or [])), max_voxels)
    labels: np.ndarray | LabelNames | None = None
    if body.labels is not None:
        if body.labels and isinstance(body.labels[0], str):
            labels = LabelNames.of(body.labels)
        else:
            labels = np.asarray(body.labels, dtype=np.int64)
    return ObservationBatch(
        stamp=body.stamp,
        voxels=np.asarray(body.voxels, dtype=np.int64).reshape(-1, 3) if body.voxels is not None else None,
        points=np.asarray(body.points, dtype=np.float64).reshape(-1, 3) if body.points is not None else None,
        labels=labels,
        p_target=np.asarray(body.p_target, dtype=np.float64) if body.p_target is not None else None,
        tp=body.sensor_model.tp if body.sensor_model else None,
        fp=body.sensor_model.fp if body.sensor_model else None,
    )


#: msgpack batches up to this size (a 16k-voxel camera view) are decoded and fused on the event loop.
#: Measured on the fleet bench (README, Performance): with the store's update computed from its mirror (~2 ms
#: of numpy for 10k voxels) and committed through the loop's Redis client, a batch takes no worker thread;
#: the two thread switches it saves had cost more than the work itself on a busy 2-vCPU host.
INLINE_BATCH_BYTES = 256 << 10


def batch_update(
    store: SessionStore,
    principal: Principal,
    session_id: str,
    batch: ObservationBatch,
    on_loop: bool,
    idempotency: Idempotency | None,
) -> Callable[[], Any]:
    """The store call that fuses the batch (its event-loop method if `on_loop`). The store checks the caller's
    right to write against the state it updates, and counts voxels outside the grid."""
    common: dict[str, Any] = {
        "points": batch.points,
        "voxels": batch.voxels,
        "authorize": principal.require_write,
        "idempotency": idempotency,
    }
    if batch.p_target is not None:
        detections = store.apply_detections_async if on_loop else store.apply_detections
        return partial(detections, session_id, batch.p_target, **common)
    assert batch.labels is not None  # ObservationBatch holds exactly one of labels and p_target
    observations = store.apply_observations_async if on_loop else store.apply_observations
    return partial(observations, session_id, batch.labels, tp=batch.tp, fp=batch.fp, **common)


async def observation_out(
    store: SessionStore,
    services: Services,
    session_id: str,
    batch: ObservationBatch,
    result: UpdateResult,
    with_summary: bool,
) -> ObservationOut:
    """The answer to a fused batch: with the posterior summary, or with it made ahead in the background."""
    cache = services.summaries
    belief = None
    if with_summary:
        belief = await services.run(belief_out, store, cache, session_id)
    else:
        cache.refresh(session_id, lambda top_k: belief_out(store, cache, session_id, top_k))
    return ObservationOut(
        version=result.version,
        stamp=batch.stamp,
        voxels_updated=result.voxels_updated,
        voxels_outside=result.voxels_outside,
        belief=belief,
    )


@router.post(
    "/{session_id}/observations",
    operation_id="add_observations",
    response_model=ObservationOut,
    responses={
        **error_responses(400, *_AUTH_ERRORS, 404, 408, 409, 413, 415, 422, 503),
        200: {"description": "Successful Response", "headers": _REPLAYED},
    },
    openapi_extra={"requestBody": _OBSERVATION_BODY},
)
async def post_observations(
    session_id: str,
    request: Request,
    response: Response,
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
    summary: Annotated[
        bool,
        Query(description="Return the posterior summary (false: just the version, for sensor-rate streams)."),
    ] = True,
    idempotency_key: IdempotencyKeyHeader = None,
) -> ObservationOut:
    """Fuse one batch of semantic observations (JSON or msgpack) and return the posterior summary."""
    content_type = media_type(request)
    decode: Callable[[bytes], ObservationBatch]
    if content_type in MSGPACK_TYPES:
        decode = partial(decode_msgpack_batch, max_voxels=settings.max_batch_voxels)
    elif content_type == "application/json":
        decode = partial(
            decode_json_batch, max_voxels=settings.max_batch_voxels, max_errors=settings.max_validation_errors
        )
    else:
        msg = f"unsupported content type {content_type!r}: send application/json or application/msgpack"
        raise UnsupportedMediaType(msg, field="content-type")
    raw = await (request.body() if content_type in MSGPACK_TYPES else json_bytes(request))
    keyed = partial(idempotency_of, request, idempotency_key, raw)  # hashes the body: on the thread if large

    try:
        if content_type in MSGPACK_TYPES and len(raw) <= INLINE_BATCH_BYTES:
            batch = decode(raw)
            result = await batch_update(store, principal, session_id, batch, True, keyed())()
        else:
            # One trip to a worker thread, not two.
            def decode_and_fuse() -> tuple[ObservationBatch, UpdateResult]:
                batch = decode(raw)
                return batch, batch_update(store, principal, session_id, batch, False, keyed())()

            batch, result = await services.run(decode_and_fuse)
    except AlreadyApplied as exc:
        first = replay(exc.record, keyed(), response)
        batch = decode(raw)  # the same body: its stamp is the answer's
        result = UpdateResult(session_id, first.version, first.voxels_updated, first.voxels_outside)
    return await observation_out(store, services, session_id, batch, result, summary)


def read_belief(
    store: SessionStore, cache: SummaryCache, principal: Principal, session_id: str, top_k: int
) -> Response:
    """The summary as `get_belief` answers it when it is neither unchanged nor summarised already."""
    info = _readable(store, principal, session_id)
    body = belief_out(store, cache, session_id, top_k, info)
    return Response(
        body.model_dump_json(), media_type="application/json", headers={"ETag": etag(body.version)}
    )


def grid_stream(
    store: SessionStore, principal: Principal, session_id: str, layers: bool
) -> tuple[int, int, Iterator[bytes]]:
    """(version, length, chunks) of the whole posterior (and layers) as msgpack, of one consistent copy."""
    info = _readable(store, principal, session_id)
    state = store.read_layers(info.id)  # the layers may be newer than `info`
    length, chunks = belief_grid_stream(
        info.id, state.version, state.grid.to_dict(), state.lang, state.vis, layers
    )
    return state.version, length, chunks


async def stream_grid(
    store: SessionStore, services: Services, principal: Principal, session_id: str, layers: bool
) -> Response:
    """The grid download, one of `max_concurrent_grids` at a time, its slot held until the last chunk is sent
    (or the client hangs up); each chunk is made on a worker thread."""
    release = await services.take_slot(services.grids, "max_concurrent_grids", "whole-grid downloads")
    try:
        version, length, chunks = await services.run(grid_stream, store, principal, session_id, layers)
    except BaseException:
        release()
        raise

    async def body() -> AsyncIterator[bytes]:
        try:
            while (chunk := await services.run(next, chunks, None)) is not None:
                yield chunk
        finally:
            release()

    headers = {"ETag": etag(version), "Content-Length": str(length)}
    return StreamingResponse(body(), media_type="application/msgpack", headers=headers)


@router.get(
    "/{session_id}/belief",
    operation_id="get_belief",
    response_model=BeliefOut,
    responses={
        **_READ_ERRORS,
        200: {
            "description": "The posterior summary (JSON), or with format=grid the whole posterior (msgpack).",
            "content": {"application/msgpack": {"schema": {"type": "string", "format": "binary"}}},
            "headers": {"ETag": {"description": "The belief version.", "schema": {"type": "string"}}},
        },
        304: {"description": "Not modified since the ETag given in If-None-Match."},
    },
)
async def get_belief(
    session_id: str,
    principal: PrincipalDep,
    store: StoreDep,
    services: ServicesDep,
    format: Annotated[
        str, Query(pattern="^(summary|grid)$", description="summary (JSON) or grid (msgpack posterior).")
    ] = "summary",
    layers: Annotated[
        bool, Query(description="With format=grid: also the language and vision layers.")
    ] = False,
    top_k: Annotated[int, Query(ge=1, le=100, description="Top voxels in the summary.")] = 5,
    if_none_match: Annotated[str | None, Header()] = None,
) -> Response:
    """The fused posterior: summary (MAP, top voxels, moments, entropy, mass per object) or the whole grid."""
    # Most polls find the belief unchanged (304) or its summary made already: they are answered here on the
    # event loop, without a trip to a worker thread.
    robot_id, version = await store.owner_and_version(session_id)
    principal.require_read(robot_id)
    cache = services.summaries
    cache.watch(session_id, top_k)
    tag = etag(version)
    if if_none_match is not None and tag in [t.strip() for t in if_none_match.split(",")]:
        return Response(status_code=304, headers={"ETag": tag})
    if format == "grid":
        return await stream_grid(store, services, principal, session_id, layers)
    ready = cache.get((session_id, version, top_k))
    if ready is not None:
        return Response(ready.model_dump_json(), media_type="application/json", headers={"ETag": tag})
    return await services.run(read_belief, store, cache, principal, session_id, top_k)
