"""Read a scene graph in any accepted format and normalise it into `SceneGraph`.

Formats and how `detect_format` tells them apart:

- ``native``: the `SceneGraph` JSON itself, an object whose "objects" is a list.
- ``region_grouped``: the reference paper's LLM-prompt serialization,
  ``{"<region name>": {"objects": {...}, "region_id": int}}`` (`app.scene_graph.region_grouped`).
- ``spark_dsg_json``: what ``spark_dsg.DynamicSceneGraph.save("x.json")`` writes, an object holding
  "SPARK_DSG_header" (files older than that header: "nodes", "edges" and "layer_ids" or "layer_keys").
- ``spark_dsg_binary``: bytes that are not JSON text (not UTF-8, or not opening with "{" or "["):
  ``DynamicSceneGraph.to_binary()`` (what Hydra streams) or a ``.sparkdsg`` file (`app.scene_graph.hydra`).
- ``vla3d``: ``{"object_result_csv": str, "region_result_csv": str (optional), "scene_graph": dict
  (optional)}``, the text of one VLA-3D scene's files (`app.scene_graph.vla3d`).

Every failure raises `InvalidSceneGraph` whose `field` is a dotted path into the input as its own format
spells it ("objects.3.size", "Office.objects.7.center", "nodes.4.attributes.bounding_box.dimensions",
"object_result_csv.12.object_bbox_xlength"), or None when the payload as a whole is at fault (not JSON,
no known format). More objects than `max_objects` raises `LimitExceeded(limit_name="max_objects")`.
The small validators below are shared by the format readers so that all of them word errors alike.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Callable, Iterable, Mapping
from enum import StrEnum
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from app.errors import InvalidSceneGraph, LimitExceeded
from app.scene_graph.model import Region, SceneGraph, SceneObject

logger = logging.getLogger(__name__)

# The Spark-DSG binary opens with a msgpack-style array tag (0xdd): the layer list, or the file header.
SPARK_DSG_ARRAY_TAG = 0xDD
INTERNAL_ERROR_MESSAGE = "internal error while reading the scene graph"


class SceneGraphFormat(StrEnum):
    NATIVE = "native"
    REGION_GROUPED = "region_grouped"
    SPARK_DSG_JSON = "spark_dsg_json"
    SPARK_DSG_BINARY = "spark_dsg_binary"
    VLA3D = "vla3d"


# --- validators shared by the readers ---------------------------------------------------------------


def join_field(prefix: str | None, *parts: object) -> str:
    """Dotted path: join_field("Office.objects", 7, "center") == "Office.objects.7.center"."""
    head = [prefix] if prefix else []
    return ".".join([*head, *(str(p) for p in parts)])


def describe(value: object, limit: int = 60) -> str:
    """A short repr for error messages (payloads can be huge)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_mapping(value: object, field: str | None) -> dict[str, Any]:
    """`value` as a JSON object with string keys."""
    if not isinstance(value, dict):
        msg = f"expected a JSON object, got {type(value).__name__} {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    for key in value:
        if not isinstance(key, str):
            msg = f"keys must be strings, got {describe(key)}"
            raise InvalidSceneGraph(msg, field=field)
    return value


def as_list(value: object, field: str | None) -> list[Any]:
    if not isinstance(value, list):
        msg = f"expected a JSON array, got {type(value).__name__} {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    return value


def as_text(value: object, field: str) -> str:
    """A non-empty string."""
    if not isinstance(value, str) or not value:
        msg = f"expected a non-empty string, got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    return value


def as_int(value: object, field: str) -> int:
    # bool is an int in Python but never a meaningful id or layer number.
    if isinstance(value, bool) or not isinstance(value, int):
        msg = f"expected an integer, got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    return value


def as_float(value: object, field: str) -> float:
    """A finite number (JSON number, not bool, not NaN or infinity)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        msg = f"expected a number, got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        msg = f"must be a finite number (no NaN or infinity), got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    return number


def as_vector3(value: object, field: str, *, positive: bool = False) -> list[float]:
    """Three finite numbers (all > 0 when `positive`); errors name the whole vector."""
    if not isinstance(value, list | tuple) or len(value) != 3:
        msg = f"expected [x, y, z] (3 numbers), got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field)
    try:
        vector = [as_float(v, field) for v in value]
    except InvalidSceneGraph as exc:
        msg = f"expected 3 finite numbers, got {describe(value)}"
        raise InvalidSceneGraph(msg, field=field) from exc
    if positive and not all(v > 0 for v in vector):
        msg = f"must be strictly positive in every axis, got {vector}"
        raise InvalidSceneGraph(msg, field=field)
    return vector


def check_object_limit(count: int, max_objects: int | None) -> None:
    if max_objects is not None and count > max_objects:
        msg = f"the scene graph holds {count} objects, more than the limit of {max_objects}"
        raise LimitExceeded(msg, limit_name="max_objects")


def check_unique(ids_and_fields: Iterable[tuple[str, str]], kind: str) -> None:
    """Raise at the second occurrence of an id, naming that occurrence's field; `kind` says what the ids
    are ("object id")."""
    seen: set[str] = set()
    for item_id, field in ids_and_fields:
        if item_id in seen:
            msg = f"duplicate {kind} {item_id!r}"
            raise InvalidSceneGraph(msg, field=field)
        seen.add(item_id)


def build_object(field: str, source_fields: Mapping[str, str] | None = None, **values: Any) -> SceneObject:
    """`SceneObject(**values)`; errors name `source_fields[<model field>]`, else `<field>.<model field>`."""
    try:
        return SceneObject(**values)
    except ValidationError as exc:
        raise _from_validation_error(exc, field, source_fields or {}) from exc


def build_region(field: str, source_fields: Mapping[str, str] | None = None, **values: Any) -> Region:
    try:
        return Region(**values)
    except ValidationError as exc:
        raise _from_validation_error(exc, field, source_fields or {}) from exc


def build_scene_graph(regions: list[Region], objects: list[SceneObject], frame_id: str = "map") -> SceneGraph:
    """Assemble a validated graph; readers check ids first, so errors here name native paths."""
    try:
        return SceneGraph(frame_id=frame_id, regions=regions, objects=objects)
    except ValidationError as exc:
        raise _from_validation_error(exc, None, {}) from exc


def bounding_box(objects: Iterable[SceneObject]) -> tuple[list[float], list[float]]:
    """(center, size) of the axis-aligned box around the objects' (yawed) boxes; needs >= 1 object."""
    members = list(objects)
    lows = [obj.min_corner for obj in members]
    highs = [obj.max_corner for obj in members]
    low = [min(c[axis] for c in lows) for axis in range(3)]
    high = [max(c[axis] for c in highs) for axis in range(3)]
    center = [float(0.5 * (lo + hi)) for lo, hi in zip(low, high, strict=True)]
    size = [float(hi - lo) for lo, hi in zip(low, high, strict=True)]
    return center, size


# "objects[3].region_id: unknown region id 'r9'" -> ("objects.3.region_id", "unknown region id 'r9'")
_MODEL_MESSAGE = re.compile(
    r"^(?P<name>[A-Za-z_]+)(?:\[(?P<index>\d+)\])?(?P<rest>(?:\.[A-Za-z_]+)*): (?P<text>.*)$"
)


def _from_validation_error(
    exc: ValidationError, prefix: str | None, source_fields: Mapping[str, str]
) -> InvalidSceneGraph:
    """The first pydantic error as InvalidSceneGraph, with its location as a dotted path."""
    first = exc.errors(include_url=False)[0]
    text = str(first.get("msg", "invalid value")).removeprefix("Value error, ")
    loc = [str(part) for part in first.get("loc", ())]
    if loc:
        field = source_fields.get(loc[0]) or join_field(prefix, *loc)
        return InvalidSceneGraph(text, field=field)
    # A model-level check (duplicate or unknown ids) names its place at the head of the message.
    match = _MODEL_MESSAGE.match(text)
    if match is None:
        return InvalidSceneGraph(text, field=prefix)
    parts = [match["name"], *([match["index"]] if match["index"] else []), *match["rest"].split(".")[1:]]
    return InvalidSceneGraph(match["text"], field=join_field(prefix, *parts))


# --- detection and dispatch ------------------------------------------------------------------------------


def detect_format(payload: bytes | str | dict[str, Any]) -> SceneGraphFormat:
    """Which format `payload` is in (see the module docstring); InvalidSceneGraph when none fits."""
    return _detect_decoded(_decode(payload))


def parse_scene_graph(
    payload: bytes | str | dict[str, Any],
    fmt: SceneGraphFormat | str | None = None,
    max_objects: int | None = None,
) -> SceneGraph:
    """Normalise `payload` (auto-detected when `fmt` is None) into a validated `SceneGraph`.

    Raises only InvalidSceneGraph (with the offending field) or LimitExceeded("max_objects").
    """
    return _guarded(lambda: _parse(payload, fmt, max_objects))


def load_scene_graph_file(
    path: Path | str, fmt: SceneGraphFormat | str | None = None, max_objects: int | None = None
) -> SceneGraph:
    """Read a scene graph from disk: a JSON file (any JSON format), a Spark-DSG binary (`.sparkdsg` or
    raw `to_binary()` bytes), or a VLA-3D scene: its folder or any one of its files. Raises like
    `parse_scene_graph`."""
    return _guarded(lambda: _load_file(Path(path), fmt, max_objects))


def _guarded(read: Callable[[], SceneGraph]) -> SceneGraph:
    try:
        return read()
    except (InvalidSceneGraph, LimitExceeded):
        raise
    except Exception as exc:
        # A reader bug must not surface as a 500 with a stack trace; log it loudly and still answer 422.
        logger.exception("unexpected error while reading a scene graph")
        msg = f"{INTERNAL_ERROR_MESSAGE} ({type(exc).__name__})"
        raise InvalidSceneGraph(msg) from exc


def _load_file(path: Path, fmt: SceneGraphFormat | str | None, max_objects: int | None) -> SceneGraph:
    from app.scene_graph.vla3d import find_vla3d_scene_of_file, load_vla3d_scene

    requested = _format_or_none(fmt)
    if path.is_dir():
        _expect_format(requested, SceneGraphFormat.VLA3D, path)
        return load_vla3d_scene(path, max_objects=max_objects)
    scene_name = find_vla3d_scene_of_file(path)
    if scene_name is not None and requested in (None, SceneGraphFormat.VLA3D):
        return load_vla3d_scene(path.parent, scene_name, max_objects=max_objects)
    try:
        payload = path.read_bytes()
    except OSError as exc:
        msg = f"cannot read {path}: {exc.strerror or exc}"
        raise InvalidSceneGraph(msg) from exc
    return _parse(payload, requested, max_objects)


def _parse(
    payload: bytes | str | dict[str, Any], fmt: SceneGraphFormat | str | None, max_objects: int | None
) -> SceneGraph:
    from app.scene_graph.hydra import parse_spark_dsg_binary

    requested = _format_or_none(fmt)
    if requested is SceneGraphFormat.SPARK_DSG_BINARY:
        if not isinstance(payload, bytes | bytearray):
            msg = f"the spark_dsg_binary format needs bytes, got {type(payload).__name__}"
            raise InvalidSceneGraph(msg)
        return parse_spark_dsg_binary(bytes(payload), max_objects=max_objects)
    decoded = _decode(payload)
    if isinstance(decoded, bytes):
        if requested is not None:
            msg = f"the {requested.value} format is JSON, got bytes that are not UTF-8 JSON text"
            raise InvalidSceneGraph(msg)
        return parse_spark_dsg_binary(decoded, max_objects=max_objects)
    return _read_json(decoded, requested or _detect_decoded(decoded), max_objects)


def _read_json(data: dict[str, Any], fmt: SceneGraphFormat, max_objects: int | None) -> SceneGraph:
    # The readers import this module's validators, so they are imported here rather than at the top.
    if fmt is SceneGraphFormat.REGION_GROUPED:
        from app.scene_graph.region_grouped import parse_region_grouped

        return parse_region_grouped(data, max_objects=max_objects)
    if fmt is SceneGraphFormat.SPARK_DSG_JSON:
        from app.scene_graph.hydra import parse_spark_dsg_json

        return parse_spark_dsg_json(data, max_objects=max_objects)
    if fmt is SceneGraphFormat.VLA3D:
        from app.scene_graph.vla3d import parse_vla3d_payload

        return parse_vla3d_payload(data, max_objects=max_objects)
    return _parse_native(data, max_objects)


def _parse_native(data: dict[str, Any], max_objects: int | None) -> SceneGraph:
    objects = data.get("objects")
    if isinstance(objects, list):
        check_object_limit(len(objects), max_objects)
    try:
        return SceneGraph.model_validate(data)
    except ValidationError as exc:
        raise _from_validation_error(exc, None, {}) from exc


def _format_or_none(fmt: SceneGraphFormat | str | None) -> SceneGraphFormat | None:
    if fmt is None:
        return None
    try:
        return SceneGraphFormat(fmt)
    except ValueError as exc:
        known = ", ".join(f.value for f in SceneGraphFormat)
        msg = f"unknown scene-graph format {describe(fmt)}; expected one of {known}"
        raise InvalidSceneGraph(msg, field="format") from exc


def _expect_format(requested: SceneGraphFormat | None, actual: SceneGraphFormat, path: Path) -> None:
    if requested not in (None, actual):
        msg = f"{path} is a {actual.value} scene, not {requested.value}"
        raise InvalidSceneGraph(msg)


def _decode(payload: object) -> bytes | dict[str, Any]:
    """A JSON object (from a dict, JSON text or UTF-8 JSON bytes) or, for other bytes, the bytes."""
    if isinstance(payload, dict):
        return as_mapping(payload, None)
    if isinstance(payload, bytes | bytearray):
        raw = bytes(payload)
        if raw[:1] == bytes([SPARK_DSG_ARRAY_TAG]):
            return raw
        try:
            text = raw.decode("utf-8-sig")
        except UnicodeDecodeError:
            return raw
        # Text that opens like JSON is JSON (its errors are JSON errors); other bytes go to the binary reader.
        stripped = text.lstrip()
        return _parse_json_object(text) if not stripped or stripped[0] in "{[" else raw
    if isinstance(payload, str):
        return _parse_json_object(payload.removeprefix("\ufeff"))
    msg = f"expected JSON text, bytes or a JSON object, got {type(payload).__name__}"
    raise InvalidSceneGraph(msg)


def _parse_json_object(text: str) -> dict[str, Any]:
    if not text.strip():
        msg = "empty payload"
        raise InvalidSceneGraph(msg)
    try:
        data = json.loads(text)
    except RecursionError as exc:
        msg = "not valid JSON: nested too deeply"
        raise InvalidSceneGraph(msg) from exc
    except ValueError as exc:  # JSONDecodeError, and int() refusing a number with too many digits
        msg = f"not valid JSON: {exc}"
        raise InvalidSceneGraph(msg) from exc
    if not isinstance(data, dict):
        msg = f"a scene graph must be a JSON object, got {type(data).__name__}"
        raise InvalidSceneGraph(msg)
    return as_mapping(data, None)


def _detect_decoded(decoded: bytes | dict[str, Any]) -> SceneGraphFormat:
    if isinstance(decoded, bytes):
        return SceneGraphFormat.SPARK_DSG_BINARY
    if "SPARK_DSG_header" in decoded or (
        "nodes" in decoded and "edges" in decoded and ("layer_ids" in decoded or "layer_keys" in decoded)
    ):
        return SceneGraphFormat.SPARK_DSG_JSON
    if "object_result_csv" in decoded:
        return SceneGraphFormat.VLA3D
    objects = decoded.get("objects", None)
    # A region called "objects" holds a dict with its own "objects"; the native format holds a list.
    if "objects" in decoded and not (isinstance(objects, dict) and "objects" in objects):
        return SceneGraphFormat.NATIVE
    if all(isinstance(region, dict) and "objects" in region for region in decoded.values()):
        return SceneGraphFormat.REGION_GROUPED
    keys = ", ".join(describe(k, 30) for k in list(decoded)[:5])
    msg = (
        "unrecognised scene-graph format: expected a native graph ('objects' list), a region-grouped map, "
        f"Spark-DSG JSON ('SPARK_DSG_header') or VLA-3D ('object_result_csv'); top-level keys: {keys}"
    )
    raise InvalidSceneGraph(msg)
