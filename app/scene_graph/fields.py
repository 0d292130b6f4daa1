"""The small validators every scene-graph reader shares, so that all formats word their errors alike.

Each raises `InvalidSceneGraph` whose `field` is a dotted path into the input as its own format spells it
(`join_field`); `build_object`, `build_region` and `build_scene_graph` turn pydantic's errors into the same
form. `app.scene_graph.loader` dispatches to the readers; the readers import only this module.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import ValidationError

from app.errors import InvalidSceneGraph, LimitExceeded
from app.scene_graph.model import Region, SceneGraph, SceneObject


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
        raise from_validation_error(exc, field, source_fields or {}) from exc


def build_region(field: str, source_fields: Mapping[str, str] | None = None, **values: Any) -> Region:
    try:
        return Region(**values)
    except ValidationError as exc:
        raise from_validation_error(exc, field, source_fields or {}) from exc


def build_scene_graph(regions: list[Region], objects: list[SceneObject], frame_id: str = "map") -> SceneGraph:
    """Assemble a validated graph; readers check ids first, so errors here name native paths."""
    try:
        return SceneGraph(frame_id=frame_id, regions=regions, objects=objects)
    except ValidationError as exc:
        raise from_validation_error(exc, None, {}) from exc


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


def from_validation_error(
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
