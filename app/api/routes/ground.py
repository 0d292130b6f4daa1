"""The stateless language sensor: scene graph + utterance -> hypotheses + Gaussian mixture."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter

from app.api.bodies import json_request_body, schema_ref
from app.api.deps import PrincipalDep, SensorsDep, ServicesDep, SettingsDep
from app.api.errors import error_responses
from app.api.scene_graph_bodies import SceneGraphBody, with_spark_dsg
from app.api.schemas import (
    ComponentOut,
    GroundOptions,
    GroundRequest,
    GroundResponse,
    HypothesisOut,
    MixtureOut,
    ModelRef,
    ParseOut,
    TargetOut,
    UniformBoxOut,
)
from app.errors import InvalidInput, LimitExceeded
from app.grounding.hypotheses import Hypothesis
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.limits import check_coordinates, check_scene_graph
from app.scene_graph.loader import parse_scene_graph
from app.scene_graph.model import SceneGraph
from app.settings import Settings

router = APIRouter(prefix="/v1", tags=["grounding"])
#: Scene graphs up to this many objects and regions are checked on the event loop (0.1-0.2 ms at 60).
INLINE_OBJECTS = 100


@router.post(
    "/ground",
    operation_id="ground",
    response_model=GroundResponse,
    responses=error_responses(400, 401, 408, 413, 415, 422, 429, 503),
    openapi_extra={"requestBody": with_spark_dsg(json_request_body(schema_ref("GroundRequest")))},
)
async def ground(
    body: Annotated[GroundRequest, SceneGraphBody(GroundRequest)],
    sensors: SensorsDep,
    settings: SettingsDep,
    services: ServicesDep,
    _: PrincipalDep,
) -> GroundResponse:
    """Ground an utterance in a scene graph: weighted hypotheses and a Gaussian mixture over the target."""
    options = body.options or GroundOptions()
    if is_small(body):  # a fraction of a millisecond: cheaper here than the trip to a worker thread
        scene_graph = checked_request(body, settings)
    else:
        scene_graph = await services.run(checked_request, body, settings)
    result, sensor = await services.ground(
        sensors, options.grounder, options.proposer, scene_graph, body.utterance, caller_hypotheses(options)
    )
    if not body.query_points:
        return respond(result, sensor, None)
    return await services.run(respond, result, sensor, body.query_points)


def is_small(body: GroundRequest) -> bool:
    """Whether the request's scene graph is native and small enough to check on the event loop."""
    graph = body.scene_graph
    return isinstance(graph, SceneGraph) and len(graph.objects) + len(graph.regions) <= INLINE_OBJECTS


def resolve_scene_graph(
    payload: SceneGraph | dict[str, Any], settings: Settings, field: str = "scene_graph"
) -> SceneGraph:
    """The request's scene graph as a native one (normalised from another format), within the limits."""
    if isinstance(payload, SceneGraph):
        return within_limits(payload, settings, field)
    return within_limits(parse_scene_graph(payload, max_objects=settings.max_objects), settings, field)


def within_limits(scene_graph: SceneGraph, settings: Settings, field: str) -> SceneGraph:
    """`check_scene_graph` with the settings' limits."""
    return check_scene_graph(
        scene_graph,
        max_objects=settings.max_objects,
        max_regions=settings.max_regions,
        max_coordinate_m=settings.max_coordinate_m,
        field=field,
    )


def check_utterance(utterance: str, settings: Settings) -> None:
    """InvalidInput if the utterance is longer than `max_utterance_chars` (the schema allows the ceiling)."""
    if len(utterance) > settings.max_utterance_chars:
        msg = f"{len(utterance)} characters exceed the limit of {settings.max_utterance_chars}"
        raise InvalidInput(msg, field="utterance")


def checked_request(body: GroundRequest, settings: Settings) -> SceneGraph:
    """The request's scene graph, native, after its limits are checked."""
    check_utterance(body.utterance, settings)
    scene_graph = resolve_scene_graph(body.scene_graph, settings)
    if body.query_points is not None:
        if len(body.query_points) > settings.max_query_points:
            count, limit = len(body.query_points), settings.max_query_points
            msg = f"query_points: {count} points exceed the limit of {limit}"
            raise LimitExceeded(msg, limit_name="max_query_points")
        check_coordinates("query_points", body.query_points, settings.max_coordinate_m)
    return scene_graph


def respond(
    result: Grounding, sensor: LanguageSensor, query_points: list[list[float]] | None
) -> GroundResponse:
    densities = None
    if query_points:
        densities = result.mixture.logpdf(np.asarray(query_points, dtype=np.float64)).tolist()
    return to_response(result, sensor, densities)


def caller_hypotheses(options: GroundOptions | None) -> list[Hypothesis] | None:
    """The hypotheses a caller asked to ground instead of the proposer's, if any."""
    if options is None or options.hypotheses is None:
        return None
    return [Hypothesis(tuple(h.anchor_ids), h.relation, weight=h.weight) for h in options.hypotheses]


def to_response(result: Grounding, sensor: LanguageSensor, densities: list[float] | None) -> GroundResponse:
    parse = result.proposal.parse
    mixture = result.mixture
    owners = result.component_hypotheses()
    return GroundResponse(
        target=TargetOut(label=parse.target),
        parse=ParseOut(
            target=parse.target,
            relation=parse.relation,
            relation_phrase=parse.relation_phrase,
            anchor_phrases=list(parse.anchor_phrases),
            region_phrase=parse.region_phrase,
        ),
        grounded=result.grounded,
        reason=result.proposal.reason,
        hypotheses=[
            HypothesisOut(
                anchor_ids=list(h.anchor_ids),
                relation=h.relation,
                region_id=h.region_id,
                weight=h.weight,
                text=h.text,
            )
            for h in result.hypotheses
        ],
        mixture=MixtureOut(
            components=[
                ComponentOut(weight=float(w), mean=m.tolist(), covariance=c.tolist(), hypothesis=h)
                for w, m, c, h in zip(
                    mixture.weights, mixture.means, mixture.covariances, owners, strict=True
                )
            ],
            uniform=[
                UniformBoxOut(weight=float(v), low=lo.tolist(), high=hi.tolist())
                for v, lo, hi in zip(mixture.box_weights, mixture.box_lows, mixture.box_highs, strict=True)
            ],
        ),
        query_log_density=densities,
        model=ModelRef(name=sensor.grounder.name, version=sensor.grounder.version),
        timings_ms=result.timings_ms,
    )
