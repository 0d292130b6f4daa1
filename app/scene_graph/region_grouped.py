"""The region-grouped scene-graph JSON of the reference paper's hypothesis prompt (its appendix
"Hypothesis Generation LLM Prompt"), read into `SceneGraph` and written back for LLM prompts::

    {"<region name>": {"objects": {"<key>": {"semantics": "desk", "raw_label": "wooden desk",
                                             "center": [x, y, z], "volume": 2.5, "object_id": "0"}},
                       "region_id": 0}}

Reading (`parse_region_grouped`):

- region: id = str(region_id), name = the region's key. The format carries no region geometry, so the
  region's box is the bounding box of its objects' boxes, and a region without objects is dropped.
  ``region_id == -1`` is reserved for "no region" (what `to_region_grouped` writes for objects without
  one): its objects get ``region_id=None``.
- object: id = "object_id" (else the key); label = "semantics" (else "raw_label"), with "raw_label" kept in
  ``attributes["raw_label"]``; center as given; yaw = "yaw" or 0. Keys beyond these (and "size") are kept
  in ``attributes``.
- size = the object's "size" when given, else a cube of side ``volume ** (1/3)``. That cube is a DERIVED
  size: the paper's format carries only the volume, so the box has the right volume but a guessed shape.
  The volume must then be finite and > 0.

Writing (`to_region_grouped`): one entry per region, keyed by its name (``region <id>`` when unnamed;
``<name> (2)``, ``<name> (3)``, ... for repeated names), then the objects without a region under
"Unassigned" with region_id -1. The contract wants integer region ids: `region_integer_ids` keeps ids that
are already canonical non-negative integers ("0", "12") and numbers the others after the largest of
those, in region order, so the mapping is stable for a given graph and invertible by the caller.
"""

from __future__ import annotations

import math
from typing import Any

from app.errors import InvalidSceneGraph
from app.scene_graph.fields import (
    as_float,
    as_int,
    as_mapping,
    as_text,
    as_vector3,
    bounding_box,
    build_object,
    build_region,
    build_scene_graph,
    check_object_limit,
    check_unique,
    describe,
    join_field,
)
from app.scene_graph.model import Region, SceneGraph, SceneObject

UNASSIGNED_REGION_ID = -1
UNASSIGNED_REGION_NAME = "Unassigned"
_OBJECT_KEYS = frozenset({"semantics", "raw_label", "center", "volume", "object_id", "size", "yaw"})
_REGION_KEYS = frozenset({"objects", "region_id"})
_MAX_REGION_ID = 2**63


def parse_region_grouped(data: object, max_objects: int | None = None) -> SceneGraph:
    """Normalise a region-grouped map (see the module docstring) into a `SceneGraph`."""
    regions_in = as_mapping(data, None)
    entries: list[tuple[str, int, dict[str, Any]]] = []
    for name, entry in regions_in.items():
        region = as_mapping(entry, name)
        unknown = sorted(set(region) - _REGION_KEYS)
        if unknown:
            msg = f"unexpected key {describe(unknown[0])}; a region holds only 'objects' and 'region_id'"
            raise InvalidSceneGraph(msg, field=join_field(name, unknown[0]))
        if "region_id" not in region:
            msg = "missing region_id (an integer)"
            raise InvalidSceneGraph(msg, field=join_field(name, "region_id"))
        region_id = as_int(region["region_id"], join_field(name, "region_id"))
        if abs(region_id) >= _MAX_REGION_ID:
            msg = f"region_id must fit in 64 bits, got {describe(region_id)}"
            raise InvalidSceneGraph(msg, field=join_field(name, "region_id"))
        entries.append((name, region_id, as_mapping(region.get("objects"), join_field(name, "objects"))))

    check_object_limit(sum(len(objects) for _, _, objects in entries), max_objects)
    check_unique(((str(rid), join_field(name, "region_id")) for name, rid, _ in entries), "region id")

    regions: list[Region] = []
    objects: list[SceneObject] = []
    object_ids: list[tuple[str, str]] = []
    for name, region_id, objects_in in entries:
        region_key = None if region_id == UNASSIGNED_REGION_ID else str(region_id)
        members = []
        for key, record in objects_in.items():
            field = join_field(name, "objects", key)
            obj = _parse_object(key, record, field, region_key)
            id_field = join_field(field, "object_id") if "object_id" in record else field
            object_ids.append((obj.id, id_field))
            members.append(obj)
        objects.extend(members)
        if region_key is not None and members:
            center, size = bounding_box(members)
            regions.append(
                build_region(
                    name,
                    {"id": join_field(name, "region_id")},
                    id=region_key,
                    name=name,
                    center=center,
                    size=size,
                )
            )
    check_unique(object_ids, "object id")
    return build_scene_graph(regions, objects)


def region_integer_ids(scene_graph: SceneGraph) -> dict[str, int]:
    """Integer region ids for the region-grouped format: canonical non-negative integer ids keep their
    value, the others are numbered after the largest of those, in region order."""
    numeric = {r.id: int(r.id) for r in scene_graph.regions if _is_canonical_index(r.id)}
    next_id = max(numeric.values(), default=-1) + 1
    integer_ids: dict[str, int] = {}
    for region in scene_graph.regions:
        if region.id in numeric:
            integer_ids[region.id] = numeric[region.id]
        else:
            integer_ids[region.id] = next_id
            next_id += 1
    return integer_ids


def to_region_grouped(
    scene_graph: SceneGraph, *, include_geometry: bool = False
) -> dict[str, dict[str, Any]]:
    """The paper's region-grouped map of `scene_graph`; `include_geometry` adds each object's "size" and
    "yaw" so that `parse_region_grouped` gets the boxes back exactly (the paper's prompt has only volume)."""
    integer_ids = region_integer_ids(scene_graph)
    members: dict[str | None, list[SceneObject]] = {r.id: [] for r in scene_graph.regions}
    members[None] = []
    for obj in scene_graph.objects:
        members[obj.region_id].append(obj)

    grouped: dict[str, dict[str, Any]] = {}
    for region in scene_graph.regions:
        key = _unused_key(region.name or f"region {region.id}", grouped)
        grouped[key] = {
            "objects": {o.id: _object_entry(o, include_geometry) for o in members[region.id]},
            "region_id": integer_ids[region.id],
        }
    if members[None]:
        key = _unused_key(UNASSIGNED_REGION_NAME, grouped)
        grouped[key] = {
            "objects": {o.id: _object_entry(o, include_geometry) for o in members[None]},
            "region_id": UNASSIGNED_REGION_ID,
        }
    return grouped


def _parse_object(key: str, record: object, field: str, region_id: str | None) -> SceneObject:
    entry = as_mapping(record, field)
    object_id = entry.get("object_id", key)
    if isinstance(object_id, int) and not isinstance(object_id, bool):
        object_id = str(object_id)
    object_id = as_text(object_id, join_field(field, "object_id"))

    raw_label = entry.get("raw_label")
    if raw_label is not None:
        raw_label = as_text(raw_label, join_field(field, "raw_label"))
    if "semantics" in entry or raw_label is None:
        label = as_text(entry.get("semantics"), join_field(field, "semantics"))
    else:
        label = raw_label

    center = as_vector3(entry.get("center"), join_field(field, "center"))
    if "size" in entry:
        size = as_vector3(entry["size"], join_field(field, "size"), positive=True)
    else:
        volume = as_float(entry.get("volume"), join_field(field, "volume"))
        if volume <= 0:
            msg = f"volume must be > 0 (it sets the object's derived size), got {volume}"
            raise InvalidSceneGraph(msg, field=join_field(field, "volume"))
        side = volume ** (1.0 / 3.0)
        size = [side, side, side]
    yaw = as_float(entry["yaw"], join_field(field, "yaw")) if "yaw" in entry else 0.0

    attributes = {k: v for k, v in entry.items() if k not in _OBJECT_KEYS}
    if raw_label is not None:
        attributes["raw_label"] = raw_label
    source_fields = {
        "id": join_field(field, "object_id"),
        "label": join_field(field, "semantics"),
        "size": join_field(field, "size" if "size" in entry else "volume"),
    }
    return build_object(
        field,
        source_fields,
        id=object_id,
        label=label,
        center=center,
        size=size,
        yaw=yaw,
        region_id=region_id,
        attributes=attributes,
    )


def _object_entry(obj: SceneObject, include_geometry: bool) -> dict[str, Any]:
    raw_label = obj.attributes.get("raw_label")
    entry: dict[str, Any] = {
        "semantics": obj.label,
        "raw_label": raw_label if isinstance(raw_label, str) and raw_label else obj.label,
        "center": list(obj.center),
        "volume": math.prod(obj.size),
        "object_id": obj.id,
    }
    if include_geometry:
        entry["size"] = list(obj.size)
        entry["yaw"] = obj.yaw
    return entry


def _unused_key(base: str, taken: dict[str, Any]) -> str:
    key, count = base, 2
    while key in taken:
        key, count = f"{base} ({count})", count + 1
    return key


def _is_canonical_index(region_id: str) -> bool:
    return region_id.isascii() and region_id.isdigit() and str(int(region_id)) == region_id
