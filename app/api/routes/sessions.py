"""VL-Map sessions: a per-robot voxel belief fusing utterances (language) and observation batches (vision).

Posterior over the target's voxel i: b_i = softmax_i(lang_i + vis_i), where each utterance adds
log(p_GMM(c_i) V) to lang and each observed voxel adds a log-likelihood ratio to vis (see app.belief).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Annotated, Any

import msgpack
import numpy as np
from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import ValidationError

from app.api.auth import Principal
from app.api.deps import PrincipalDep, SensorsDep, ServicesDep, SettingsDep, StoreDep
from app.api.errors import error_responses, field_path
from app.api.routes.ground import caller_hypotheses, resolve_scene_graph, to_response
from app.api.schemas import (
    ROBOT_ID_PATTERN,
    BeliefOut,
    GridOut,
    GridSpec,
    GroundOptions,
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
from app.api.wire import MSGPACK_TYPES, ObservationBatch, check_batch_size, decode_msgpack_batch, pack_array
from app.belief.grid import VoxelGrid
from app.belief.session import SensorModel, SessionInfo, UpdateResult, check_target_label, new_session
from app.errors import InvalidInput, LimitExceeded, UnsupportedMediaType
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from app.stores.base import SessionStore
from app.vocabulary import head_noun, lemmas, lexical_match, object_nouns

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

_AUTH_ERRORS = (401, 403, 429)
_WRITE_ERRORS = error_responses(400, *_AUTH_ERRORS, 404, 413, 422, 503)
_READ_ERRORS = error_responses(*_AUTH_ERRORS, 404, 422, 503)

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
    if (spec.min_corner is None) != (spec.max_corner is None):
        msg = "give both min_corner and max_corner, or neither"
        raise InvalidInput(msg, field="grid.min_corner")
    if spec.min_corner is None:
        return VoxelGrid.around(
            scene_graph, voxel_size=spec.voxel_size, margin=spec.margin, max_voxels=settings.max_grid_voxels
        )
    low, high = np.asarray(spec.min_corner, dtype=np.float64), np.asarray(spec.max_corner, dtype=np.float64)
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(high > low)):
        msg = "max_corner must be finite and above min_corner on every axis"
        raise InvalidInput(msg, field="grid.max_corner")
    shape = np.ceil((high - low) / spec.voxel_size).astype(np.int64)
    if float(np.prod(shape.astype(np.float64))) > settings.max_grid_voxels:
        msg = f"the grid needs {int(np.prod(shape))} voxels, more than the limit {settings.max_grid_voxels}"
        raise LimitExceeded(msg, limit_name="max_grid_voxels")
    nx, ny, nz = (int(s) for s in shape)
    return VoxelGrid(origin=tuple(low), shape=(nx, ny, nz), voxel_size=spec.voxel_size)


def _label_map(raw: dict[str, str] | None) -> dict[int, str]:
    out: dict[int, str] = {}
    for key, name in (raw or {}).items():
        if not key.isdigit() or len(key) > 9:
            msg = f"label ids must be non-negative integers, got {key!r}"
            raise InvalidInput(msg, field=f"label_map.{key}")
        out[int(key)] = name
    return out


def create(body: SessionCreate, store: SessionStore, settings: Settings) -> SessionOut:
    scene_graph = resolve_scene_graph(body.scene_graph, settings)
    if len(store.list(body.robot_id)) >= settings.max_sessions_per_robot:
        limit = settings.max_sessions_per_robot
        msg = f"robot {body.robot_id!r} already has {limit} sessions; delete one first"
        raise LimitExceeded(msg, limit_name="max_sessions_per_robot")
    sensor = body.sensor_model
    session = new_session(
        body.robot_id,
        scene_graph,
        body.target_label or "",
        label_map=_label_map(body.label_map),
        sensor_model=SensorModel(sensor.tp, sensor.fp) if sensor else None,
        grid=_grid(body.grid, scene_graph, settings),
        max_voxels=settings.max_grid_voxels,
    )
    return session_out(store.create(session))


@router.post(
    "", operation_id="create_session", status_code=201, response_model=SessionOut, responses=_WRITE_ERRORS
)
async def create_session(
    body: SessionCreate,
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
) -> SessionOut:
    """Start a belief for a robot: a uniform prior over a voxel grid around its scene graph."""
    principal.require_write(body.robot_id)
    return await services.run(create, body, store, settings)


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


def delete(store: SessionStore, principal: Principal, session_id: str) -> None:
    _writable(store, principal, session_id)
    store.delete(session_id)


@router.delete("/{session_id}", operation_id="delete_session", status_code=204, responses=_READ_ERRORS)
async def delete_session(
    session_id: str, principal: PrincipalDep, store: StoreDep, services: ServicesDep
) -> Response:
    """Delete a session and its belief."""
    await services.run(delete, store, principal, session_id)
    return Response(status_code=204)


def replace_scene_graph(
    store: SessionStore, principal: Principal, session_id: str, payload: object, settings: Settings
) -> SessionOut:
    _writable(store, principal, session_id)
    store.replace_scene_graph(session_id, resolve_scene_graph(payload, settings))  # type: ignore[arg-type]
    return session_out(store.info(session_id))


@router.put(
    "/{session_id}/scene-graph",
    operation_id="replace_scene_graph",
    response_model=SessionOut,
    responses=_WRITE_ERRORS,
)
async def put_scene_graph(
    session_id: str,
    scene_graph: SceneGraphPayload,
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
) -> SessionOut:
    """Replace the session's scene graph (Hydra keeps mapping); later utterances ground in the new one."""
    return await services.run(replace_scene_graph, store, principal, session_id, scene_graph, settings)


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
    store: SessionStore, cache: SummaryCache, info: SessionInfo, result: Grounding, sensor: LanguageSensor
) -> UtteranceOut:
    """Add an utterance to the belief unless `utterance_verdict` refuses it; while the session has no target
    class, the utterance's target phrase names it."""
    fused, reason = utterance_verdict(info.target_label, result)
    if fused:
        store.apply_utterance(info.id, result.mixture)
        target = result.proposal.parse.target
        if not info.target_label and target and names_a_class(target, info.label_map):
            store.set_target_label(info.id, target)
    belief = belief_out(store, cache, info.id)
    grounding = to_response(result, sensor, None)
    return UtteranceOut(grounding=grounding, belief=belief, fused=fused, reason=reason)


@router.post(
    "/{session_id}/utterances",
    operation_id="add_utterance",
    response_model=UtteranceOut,
    responses=_WRITE_ERRORS,
)
async def post_utterance(
    session_id: str,
    body: UtteranceIn,
    principal: PrincipalDep,
    store: StoreDep,
    sensors: SensorsDep,
    services: ServicesDep,
) -> UtteranceOut:
    """Ground an utterance in the session's scene graph and fuse it unless its target is another class."""
    options = body.options or GroundOptions()
    info, scene_graph = await services.run(utterance_context, store, principal, session_id)
    result, sensor = await services.ground(
        sensors, options.grounder, options.proposer, scene_graph, body.utterance, caller_hypotheses(options)
    )
    return await services.run(fuse_utterance, store, services.summaries, info, result, sensor)


def decode_json_batch(raw: bytes, max_voxels: int) -> ObservationBatch:
    try:
        body = ObservationBatchJson.model_validate_json(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = field_path(first["loc"]) or "body"
        msg = f"{first['msg']}"
        raise InvalidInput(msg, field=field) from exc
    n = len(body.voxels or body.points or [])
    check_batch_size(max(n, len(body.labels or body.p_target or [])), max_voxels)
    labels = None
    if body.labels is not None:
        labels = np.asarray(body.labels) if body.labels else np.zeros(0, dtype=np.int64)
        if labels.dtype.kind == "i":
            labels = labels.astype(np.int64)
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
    store: SessionStore, principal: Principal, session_id: str, batch: ObservationBatch, on_loop: bool
) -> Callable[[], Any]:
    """The store call that fuses the batch (its event-loop method if `on_loop`). The store checks the caller's
    right to write against the state it updates, and counts voxels outside the grid."""
    common: dict[str, Any] = {
        "points": batch.points,
        "voxels": batch.voxels,
        "authorize": principal.require_write,
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
    responses=error_responses(400, *_AUTH_ERRORS, 404, 409, 413, 415, 422, 503),
    openapi_extra={"requestBody": _OBSERVATION_BODY},
)
async def post_observations(
    session_id: str,
    request: Request,
    principal: PrincipalDep,
    store: StoreDep,
    settings: SettingsDep,
    services: ServicesDep,
    summary: Annotated[
        bool,
        Query(description="Return the posterior summary (false: just the version, for sensor-rate streams)."),
    ] = True,
) -> ObservationOut:
    """Fuse one batch of semantic observations (JSON or msgpack) and return the posterior summary."""
    raw = await request.body()
    content_type = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    decode: Callable[[bytes, int], ObservationBatch]
    if content_type in MSGPACK_TYPES:
        decode = decode_msgpack_batch
    elif content_type == "application/json":
        decode = decode_json_batch
    else:
        msg = f"unsupported content type {content_type!r}: send application/json or application/msgpack"
        raise UnsupportedMediaType(msg, field="content-type")

    if decode is decode_msgpack_batch and len(raw) <= INLINE_BATCH_BYTES:
        batch = decode(raw, settings.max_batch_voxels)
        result = await batch_update(store, principal, session_id, batch, on_loop=True)()
    else:
        # One trip to a worker thread, not two.
        def decode_and_fuse() -> tuple[ObservationBatch, UpdateResult]:
            batch = decode(raw, settings.max_batch_voxels)
            return batch, batch_update(store, principal, session_id, batch, on_loop=False)()

        batch, result = await services.run(decode_and_fuse)
    return await observation_out(store, services, session_id, batch, result, summary)


def belief_grid(store: SessionStore, info: SessionInfo, layers: bool) -> tuple[bytes, int]:
    """The whole posterior (and layers) as msgpack, with the version it belongs to."""
    state = store.read_layers(info.id)
    payload = {
        "session_id": info.id,
        "version": state.version,
        "grid": state.grid.to_dict(),
        "posterior": pack_array(state.posterior().astype(np.float32)),
    }
    if layers:
        payload["lang"] = pack_array(state.lang)
        payload["vis"] = pack_array(state.vis)
    return msgpack.packb(payload, use_bin_type=True), state.version


def read_belief(
    store: SessionStore,
    cache: SummaryCache,
    principal: Principal,
    session_id: str,
    fmt: str,
    layers: bool,
    top_k: int,
) -> Response:
    """The belief as `get_belief` answers it when it is neither unchanged nor summarised already."""
    info = _readable(store, principal, session_id)
    if fmt == "grid":
        data, version = belief_grid(store, info, layers)  # the layers may be newer than `info`
        return Response(data, media_type="application/msgpack", headers={"ETag": etag(version)})
    body = belief_out(store, cache, session_id, top_k, info)
    return Response(
        body.model_dump_json(), media_type="application/json", headers={"ETag": etag(body.version)}
    )


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
    ready = cache.get((session_id, version, top_k)) if format == "summary" else None
    if ready is not None:
        return Response(ready.model_dump_json(), media_type="application/json", headers={"ETag": tag})
    return await services.run(read_belief, store, cache, principal, session_id, format, layers, top_k)
