"""Scene-graph request bodies: JSON, or the Spark-DSG binary that Hydra streams, through one decoder.

`POST /v1/scene-graphs/normalize`, `PUT /v1/sessions/{id}/scene-graph`, `POST /v1/sessions` and
`POST /v1/ground` read a body of `application/x-spark-dsg` (or `application/octet-stream`) as
``DynamicSceneGraph.to_binary()`` bytes or a ``.sparkdsg`` file's content. Each such decode is a child
process (`app.scene_graph.hydra.decode_spark_dsg_binary`: a fraction of a second of CPU, up to a few GiB of
address space), so all of them go through `decode_binary_scene_graph`: a per-key rate of their own
(`decode_rate`) and a few at a time per process (`max_concurrent_decodes`).

A binary body is the scene graph alone. The request's other fields (`robot_id`, `utterance`, `options`, ...)
then come as query parameters of the same names: a text field as it is, any other as JSON text
(``grid={"voxel_size":0.25}``), validated by the same model as a JSON body, before the decode. A JSON body
carries them itself, and a query parameter beside it is refused rather than silently ignored or merged.
"""

from __future__ import annotations

import inspect
import json
import types
from typing import Annotated, Any, get_args

from fastapi import Depends, Query, Request
from pydantic import BaseModel, TypeAdapter
from pydantic.fields import FieldInfo

from app.api.auth import Principal
from app.api.bodies import is_json, media_type, read_json, validate_json
from app.api.deps import PrincipalDep, ServicesDep
from app.api.services import Services
from app.errors import InvalidInput, UnsupportedMediaType
from app.scene_graph.loader import SceneGraphFormat, parse_scene_graph
from app.scene_graph.model import SceneGraph

#: Media types of a Spark-DSG binary body; the first is the one to send.
SPARK_DSG_MEDIA_TYPES = ("application/x-spark-dsg", "application/octet-stream")

_SPARK_DSG_CONTENT = {
    "schema": {
        "type": "string",
        "format": "binary",
        "description": (
            "Spark-DSG binary: DynamicSceneGraph.to_binary() bytes (what Hydra streams) or a .sparkdsg "
            "file's content."
        ),
    }
}
#: The model field a binary body stands for; the placeholder it has while the other fields are validated.
_GRAPH_FIELD = "scene_graph"
_NO_GRAPH: dict[str, Any] = {"objects": []}


def is_spark_dsg(request: Request) -> bool:
    """Whether the body is Spark-DSG binary; else it must be JSON (415 for any other content type)."""
    kind = media_type(request)
    if kind in SPARK_DSG_MEDIA_TYPES:
        return True
    if not is_json(kind):
        msg = f"unsupported content type {kind!r}; send application/json or {SPARK_DSG_MEDIA_TYPES[0]}"
        raise UnsupportedMediaType(msg, field="content-type")
    return False


async def decode_binary_scene_graph(
    request: Request, services: Services, principal: Principal, fmt: SceneGraphFormat | None = None
) -> SceneGraph:
    """The request's binary body as a native scene graph (at most `max_objects` objects; the caller checks
    the other limits, as for JSON), decoded in a child process within the decode rate and slots."""
    services.decode_rate.check(principal.name)
    raw = await request.body()
    async with services.slot(services.decodes, "max_concurrent_decodes", "Spark-DSG binary decodes"):
        return await services.run(parse_scene_graph, raw, fmt, services.settings.max_objects)


def with_spark_dsg(request_body: dict[str, Any]) -> dict[str, Any]:
    """An OpenAPI `requestBody` that also takes a Spark-DSG binary body."""
    binary = dict.fromkeys(SPARK_DSG_MEDIA_TYPES, _SPARK_DSG_CONTENT)
    return {**request_body, "content": {**request_body["content"], **binary}}


def _is_text(field: FieldInfo) -> bool:
    """Whether a field takes a JSON string (so that its query parameter is the text itself)."""
    kinds = set(get_args(field.annotation) or (field.annotation,))
    return kinds - {types.NoneType} == {str}


def _query_fields(model: Any) -> dict[str, FieldInfo]:
    """The fields besides the scene graph of a body model (none for a body that is the scene graph)."""
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        return {}
    return {name: f for name, f in model.model_fields.items() if name != _GRAPH_FIELD}


def _query_parameter(name: str, field: FieldInfo) -> inspect.Parameter:
    form = "" if _is_text(field) else ", as JSON text"
    about = f" {field.description}" if field.description else ""
    description = f"With a Spark-DSG binary body only: the body's `{name}` field{form}.{about}"
    annotation = Annotated[str | None, Query(description=description)]
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=annotation)


def _fields_of(query: dict[str, str], fields: dict[str, FieldInfo]) -> dict[str, Any]:
    """The body's fields from their query parameters, as the JSON body would hold them."""
    document: dict[str, Any] = {}
    for name, text in query.items():
        if _is_text(fields[name]):
            document[name] = text
            continue
        try:
            document[name] = json.loads(text)
        except (ValueError, RecursionError) as exc:
            msg = f"{name}: the query parameter is not JSON text ({str(exc)[:100]})"
            raise InvalidInput(msg, field=name) from exc
    return document


def SceneGraphBody(model: Any) -> Any:  # noqa: N802 (used like FastAPI's Body(), in Annotated)
    """A dependency giving the request's body as `model`: its JSON, or for a Spark-DSG binary body the
    decoded graph (as the model's `scene_graph`) with the other fields from the query string."""
    adapter: TypeAdapter[Any] = TypeAdapter(model)
    fields = _query_fields(model)

    async def read_body(
        request: Request, services: ServicesDep, principal: PrincipalDep, **query: str | None
    ) -> Any:
        given = {name: value for name, value in query.items() if value is not None}
        if not is_spark_dsg(request):
            if given:
                name = next(iter(given))
                msg = f"query parameter {name!r}: only a Spark-DSG binary body takes fields in the query"
                raise InvalidInput(msg, field=name)
            return await read_json(request, adapter)
        if not fields:
            return await decode_binary_scene_graph(request, services, principal)
        # The fields are checked first: a bad one should not cost a decode.
        document = {**_fields_of(given, fields), _GRAPH_FIELD: _NO_GRAPH}
        limit = services.settings.max_validation_errors
        body = validate_json(adapter, json.dumps(document).encode(), limit)
        graph = await decode_binary_scene_graph(request, services, principal)
        return body.model_copy(update={_GRAPH_FIELD: graph})

    # FastAPI reads the query parameters from the signature; these are the model's own fields.
    own = [
        inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=annotation)
        for name, annotation in (("request", Request), ("services", ServicesDep), ("principal", PrincipalDep))
    ]
    read_body.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
        [*own, *(_query_parameter(name, f) for name, f in fields.items())]
    )
    return Depends(read_body)
