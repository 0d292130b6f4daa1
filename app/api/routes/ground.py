"""The stateless language sensor: scene graph + utterance -> hypotheses + Gaussian mixture."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter
from pydantic import TypeAdapter

from app.api.bodies import JsonBody, json_request_body, schema_ref
from app.api.deps import PrincipalDep, SensorsDep, ServicesDep, SettingsDep
from app.api.errors import error_responses
from app.api.schemas import (
    ComponentOut,
    GroundOptions,
    GroundRequest,
    GroundResponse,
    HypothesisOut,
    MixtureOut,
    ModelRef,
    ParseOut,
    SceneGraphPayload,
    TargetOut,
    UniformBoxOut,
)
from app.errors import InvalidInput, LimitExceeded
from app.grounding.hypotheses import Hypothesis
from app.grounding.sensor import Grounding, LanguageSensor
from app.scene_graph.loader import parse_scene_graph
from app.scene_graph.model import SceneGraph
from app.settings import Settings

router = APIRouter(prefix="/v1", tags=["grounding"])


@router.post(
    "/ground",
    operation_id="ground",
    response_model=GroundResponse,
    responses=error_responses(400, 401, 408, 413, 415, 422, 429, 503),
    openapi_extra={"requestBody": json_request_body(schema_ref("GroundRequest"))},
)
async def ground(
    body: Annotated[GroundRequest, JsonBody(GroundRequest)],
    sensors: SensorsDep,
    settings: SettingsDep,
    services: ServicesDep,
    _: PrincipalDep,
) -> GroundResponse:
    """Ground an utterance in a scene graph: weighted hypotheses and a Gaussian mixture over the target."""
    options = body.options or GroundOptions()
    scene_graph = await services.run(checked_request, body, settings)
    result, sensor = await services.ground(
        sensors, options.grounder, options.proposer, scene_graph, body.utterance, caller_hypotheses(options)
    )
    return await services.run(respond, result, sensor, body.query_points)


def scene_graph_payload_schema() -> dict[str, Any]:
    """The OpenAPI schema of a bare `SceneGraphPayload` body (PUT .../scene-graph), as FastAPI wrote it when
    it read that body itself (the definitions it refers to are the components')."""
    schema = TypeAdapter(SceneGraphPayload).json_schema(ref_template="#/components/schemas/{model}")
    schema.pop("$defs", None)
    return {**schema, "title": "Scene Graph"}


def check_coordinates(field: str, vectors: Sequence[Sequence[float]], settings: Settings) -> None:
    """InvalidInput unless every number of `vectors` lies within +-`max_coordinate_m`: a map spans metres to
    kilometres, and squares of larger numbers (a covariance, a distance) overflow downstream."""
    values = np.asarray(vectors, dtype=np.float64)
    if values.size and not np.all(np.abs(values) <= settings.max_coordinate_m):
        msg = f"coordinates and sizes must lie within +-{settings.max_coordinate_m:g} m"
        raise InvalidInput(msg, field=field)


def check_scene_graph(scene_graph: SceneGraph, settings: Settings, field: str = "scene_graph") -> SceneGraph:
    """The scene graph, once within the limits on objects, regions and coordinates (whatever its format)."""
    if len(scene_graph.objects) > settings.max_objects:
        msg = f"{field}: {len(scene_graph.objects)} objects exceed the limit of {settings.max_objects}"
        raise LimitExceeded(msg, limit_name="max_objects")
    if len(scene_graph.regions) > settings.max_regions:
        msg = f"{field}: {len(scene_graph.regions)} regions exceed the limit of {settings.max_regions}"
        raise LimitExceeded(msg, limit_name="max_regions")
    check_coordinates(
        f"{field}.objects", [v for o in scene_graph.objects for v in (o.center, o.size)], settings
    )
    check_coordinates(
        f"{field}.regions", [v for r in scene_graph.regions for v in (r.center, r.size)], settings
    )
    return scene_graph


def resolve_scene_graph(
    payload: SceneGraph | dict, settings: Settings, field: str = "scene_graph"
) -> SceneGraph:
    """The request's scene graph as a native one (normalised from another format), within the limits."""
    if isinstance(payload, SceneGraph):
        return check_scene_graph(payload, settings, field)
    return check_scene_graph(parse_scene_graph(payload, max_objects=settings.max_objects), settings, field)


def checked_request(body: GroundRequest, settings: Settings) -> SceneGraph:
    """The request's scene graph, native, after its limits are checked."""
    scene_graph = resolve_scene_graph(body.scene_graph, settings)
    if body.query_points is not None:
        if len(body.query_points) > settings.max_query_points:
            count, limit = len(body.query_points), settings.max_query_points
            msg = f"query_points: {count} points exceed the limit of {limit}"
            raise LimitExceeded(msg, limit_name="max_query_points")
        check_coordinates("query_points", body.query_points, settings)
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


def component_hypotheses(result: Grounding) -> list[int | None]:
    """The index in `result.hypotheses` of each Gaussian of the mixture, None for one of no hypothesis.

    The mixture holds the densities' Gaussians first, in hypothesis order; a Gaussian after them (a broad
    prior, all of them when the utterance was not grounded) belongs to no hypothesis.
    """
    owners: list[int | None] = [h for h, density in enumerate(result.densities) for _ in density.weights]
    return owners + [None] * (len(result.mixture.weights) - len(owners))


def to_response(result: Grounding, sensor: LanguageSensor, densities: list[float] | None) -> GroundResponse:
    parse = result.proposal.parse
    mixture = result.mixture
    owners = component_hypotheses(result)
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
