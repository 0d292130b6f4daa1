"""Scene-graph normalisation: any accepted format in, the native SceneGraph out."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request

from app.api.bodies import json_bytes, media_type
from app.api.deps import PrincipalDep, ServicesDep, SettingsDep
from app.api.errors import error_responses
from app.api.routes.ground import within_limits
from app.errors import InvalidSceneGraph, UnsupportedMediaType
from app.scene_graph.loader import SceneGraphFormat, parse_scene_graph
from app.scene_graph.model import SceneGraph
from app.settings import Settings

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
    responses=error_responses(400, 401, 408, 413, 415, 422, 429),
    openapi_extra={"requestBody": _REQUEST_BODY},
)
async def normalize_scene_graph(
    request: Request,
    settings: SettingsDep,
    services: ServicesDep,
    principal: PrincipalDep,
    format: Annotated[SceneGraphFormat | None, Query(description="Skip auto-detection.")] = None,
) -> SceneGraph:
    """Read a scene graph in any accepted format and return it as a native SceneGraph."""
    content_type = media_type(request)
    if content_type in _BINARY_TYPES or format is SceneGraphFormat.SPARK_DSG_BINARY:
        # Each binary decode is a child process (a fraction of a second of CPU, up to a few GiB of address
        # space): a per-key rate of their own, and a few at a time per process.
        services.decode_rate.check(principal.name)
        raw = await request.body()
        async with services.slot(services.decodes, "max_concurrent_decodes", "Spark-DSG binary decodes"):
            return await services.run(normalize, raw, True, format, settings)
    if content_type != "application/json" and not content_type.endswith("+json"):
        msg = f"unsupported content type {content_type!r}; send application/json or application/octet-stream"
        raise UnsupportedMediaType(msg, field="content-type")
    return await services.run(normalize, await json_bytes(request), False, format, settings)


def normalize(raw: bytes, binary: bool, fmt: SceneGraphFormat | None, settings: Settings) -> SceneGraph:
    """The body as a native scene graph within the limits: binary bytes as they are, JSON decoded first."""
    payload: bytes | dict[str, Any]
    if binary:
        payload = raw
    else:
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
        payload = decoded
    return within_limits(parse_scene_graph(payload, fmt, settings.max_objects), settings, "body")
