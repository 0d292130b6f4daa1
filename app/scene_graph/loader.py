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
The validators the readers share are in `app.scene_graph.fields`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from app.errors import InvalidSceneGraph, LimitExceeded
from app.scene_graph.fields import as_mapping, check_object_limit, describe, from_validation_error
from app.scene_graph.hydra import SPARK_DSG_ARRAY_TAG, parse_spark_dsg_binary, parse_spark_dsg_json
from app.scene_graph.model import SceneGraph
from app.scene_graph.region_grouped import parse_region_grouped
from app.scene_graph.vla3d import find_vla3d_scene_of_file, load_vla3d_scene, parse_vla3d_payload

logger = logging.getLogger(__name__)

INTERNAL_ERROR_MESSAGE = "internal error while reading the scene graph"


class SceneGraphFormat(StrEnum):
    NATIVE = "native"
    REGION_GROUPED = "region_grouped"
    SPARK_DSG_JSON = "spark_dsg_json"
    SPARK_DSG_BINARY = "spark_dsg_binary"
    VLA3D = "vla3d"


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
    if fmt is SceneGraphFormat.REGION_GROUPED:
        return parse_region_grouped(data, max_objects=max_objects)
    if fmt is SceneGraphFormat.SPARK_DSG_JSON:
        return parse_spark_dsg_json(data, max_objects=max_objects)
    if fmt is SceneGraphFormat.VLA3D:
        return parse_vla3d_payload(data, max_objects=max_objects)
    return _parse_native(data, max_objects)


def _parse_native(data: dict[str, Any], max_objects: int | None) -> SceneGraph:
    objects = data.get("objects")
    if isinstance(objects, list):
        check_object_limit(len(objects), max_objects)
    try:
        return SceneGraph.model_validate(data)
    except ValidationError as exc:
        raise from_validation_error(exc, None, {}) from exc


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


def _looks_native(data: dict[str, Any]) -> bool:
    """A native graph has "objects" (a list when valid), or at least one of its other fields, "regions" (a
    list) or "frame_id" (a string): all three are optional. A region-grouped map's values are all
    objects, so a region named "objects", "regions" or "frame_id" holds a dict with its own "objects"."""
    objects = data.get("objects")
    if "objects" in data:
        return not (isinstance(objects, dict) and "objects" in objects)
    return isinstance(data.get("regions"), list) or isinstance(data.get("frame_id"), str)


def _detect_decoded(decoded: bytes | dict[str, Any]) -> SceneGraphFormat:
    if isinstance(decoded, bytes):
        return SceneGraphFormat.SPARK_DSG_BINARY
    if "SPARK_DSG_header" in decoded or (
        "nodes" in decoded and "edges" in decoded and ("layer_ids" in decoded or "layer_keys" in decoded)
    ):
        return SceneGraphFormat.SPARK_DSG_JSON
    if "object_result_csv" in decoded:
        return SceneGraphFormat.VLA3D
    if _looks_native(decoded):
        return SceneGraphFormat.NATIVE
    if all(isinstance(region, dict) and "objects" in region for region in decoded.values()):
        return SceneGraphFormat.REGION_GROUPED
    keys = ", ".join(describe(k, 30) for k in list(decoded)[:5])
    msg = (
        "unrecognised scene-graph format: expected a native graph ('objects' list), a region-grouped map, "
        f"Spark-DSG JSON ('SPARK_DSG_header') or VLA-3D ('object_result_csv'); top-level keys: {keys}"
    )
    raise InvalidSceneGraph(msg)
