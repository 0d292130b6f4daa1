"""Scene-graph normalisation: any accepted format in, the native SceneGraph out."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Query, Request

from app.api.bodies import json_bytes
from app.api.deps import PrincipalDep, ServicesDep, SettingsDep
from app.api.errors import error_responses
from app.api.routes.ground import within_limits
from app.api.scene_graph_bodies import decode_binary_scene_graph, is_spark_dsg, with_spark_dsg
from app.errors import InvalidSceneGraph
from app.scene_graph.loader import SceneGraphFormat, parse_scene_graph
from app.scene_graph.model import SceneGraph
from app.settings import Settings

router = APIRouter(prefix="/v1", tags=["scene graphs"])

_JSON_BODY = {
    "required": True,
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "description": (
                    "A native SceneGraph, the region-grouped serialization, a Spark-DSG JSON graph "
                    "(with SPARK_DSG_header), or a VLA-3D bundle {object_result_csv, region_result_csv?, "
                    "scene_graph?}."
                ),
            }
        },
    },
}


@router.post(
    "/scene-graphs/normalize",
    operation_id="normalize_scene_graph",
    response_model=SceneGraph,
    responses=error_responses(400, 401, 408, 413, 415, 422, 429),
    openapi_extra={"requestBody": with_spark_dsg(_JSON_BODY)},
)
async def normalize_scene_graph(
    request: Request,
    settings: SettingsDep,
    services: ServicesDep,
    principal: PrincipalDep,
    format: Annotated[SceneGraphFormat | None, Query(description="Skip auto-detection.")] = None,
) -> SceneGraph:
    """Read a scene graph in any accepted format and return it as a native SceneGraph."""
    if format is SceneGraphFormat.SPARK_DSG_BINARY or is_spark_dsg(request):
        graph = await decode_binary_scene_graph(request, services, principal, format)
        return await services.run(within_limits, graph, settings, "body")
    return await services.run(normalize, await json_bytes(request), format, settings)


def normalize(raw: bytes, fmt: SceneGraphFormat | None, settings: Settings) -> SceneGraph:
    """The JSON body as a native scene graph within the limits."""
    try:
        decoded = json.loads(raw)
    except RecursionError as exc:
        msg = "body is not valid JSON: nested too deeply"
        raise InvalidSceneGraph(msg, field="body") from exc
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, int() refusing too many digits
        msg = f"body is not valid JSON: {str(exc)[:200]}"
        raise InvalidSceneGraph(msg, field="body") from exc
    if not isinstance(decoded, dict):
        msg = "a JSON scene graph must be an object"
        raise InvalidSceneGraph(msg, field="body")
    return within_limits(parse_scene_graph(decoded, fmt, settings.max_objects), settings, "body")
