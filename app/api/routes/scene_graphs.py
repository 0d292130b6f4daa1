"""Scene-graph normalisation: any accepted format in, the native SceneGraph out."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Query, Request

from app.api.deps import PrincipalDep, ServicesDep, SettingsDep
from app.api.errors import error_responses
from app.errors import InvalidSceneGraph, UnsupportedMediaType
from app.scene_graph.loader import SceneGraphFormat, parse_scene_graph
from app.scene_graph.model import SceneGraph

router = APIRouter(prefix="/v1", tags=["scene graphs"])

_BINARY_TYPES = ("application/octet-stream", "application/x-spark-dsg")

_REQUEST_BODY = {
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
        "application/octet-stream": {
            "schema": {
                "type": "string",
                "format": "binary",
                "description": "Spark-DSG binary (Hydra stream).",
            }
        },
    },
}


@router.post(
    "/scene-graphs/normalize",
    operation_id="normalize_scene_graph",
    response_model=SceneGraph,
    responses=error_responses(400, 401, 413, 415, 422, 429),
    openapi_extra={"requestBody": _REQUEST_BODY},
)
async def normalize_scene_graph(
    request: Request,
    settings: SettingsDep,
    services: ServicesDep,
    _: PrincipalDep,
    format: Annotated[SceneGraphFormat | None, Query(description="Skip auto-detection.")] = None,
) -> SceneGraph:
    """Read a scene graph in any accepted format and return it as a native SceneGraph."""
    raw = await request.body()
    content_type = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    payload: bytes | dict
    if content_type in _BINARY_TYPES:
        payload = raw
    elif content_type == "application/json" or content_type.endswith("+json"):
        try:
            decoded = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            msg = f"body is not valid JSON: {exc}"
            raise InvalidSceneGraph(msg, field="body") from exc
        if not isinstance(decoded, dict):
            msg = "a JSON scene graph must be an object"
            raise InvalidSceneGraph(msg, field="body")
        payload = decoded
    else:
        msg = f"unsupported content type {content_type!r}; send application/json or application/octet-stream"
        raise UnsupportedMediaType(msg, field="content-type")
    return await services.run(parse_scene_graph, payload, format, settings.max_objects)
