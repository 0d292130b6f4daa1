"""VLA-3D scenes (the benchmark the reference paper evaluates on), read into `SceneGraph`.

A scene ``<scene>`` is a set of files in one folder (see the data README):

- ``<scene>_object_result.csv`` (required): one object a row: object_id, region_id, raw_label, nyu_id,
  nyu40_id, nyu_label, nyu40_label, object_bbox_c{x,y,z}, object_bbox_{x,y,z}length,
  object_bbox_heading, object_front_heading, then three colours (object_color_{r,g,b}<k>,
  object_color_scheme<k>, object_color_scheme_percentage<k>, object_color_scheme_average_dist<k>).
- ``<scene>_region_result.csv``: one region a row: region_id, region_label, region_bbox_c{x,y,z},
  region_bbox_{x,y,z}length, region_bbox_heading.
- ``<scene>_scene_graph.json``: regions with 8-corner boxes, their objects and relations; only its
  regions are read, and only when the region CSV is absent. ``*_referential_statements.json`` is not read.

Normalisation:

- ``_`` marks a missing value, and so does a field absent from a short row (the files have such rows).
- object: id = object_id; label = nyu_label (the class the benchmark's statements name, e.g. "garbage
  bin" for the raw "trash can"), or raw_label when nyu_label is missing; attributes keep raw_label,
  nyu_label, nyu40_label, nyu_id, nyu40_id, front_heading and the colours as
  ``[{"name", "rgb", "fraction", "average_distance"}]`` (missing ones left out). center and size are the
  box's; its x length runs along the heading, which becomes yaw (as in `SceneObject`).
- Objects whose nyu_label is "unknown" (ScanNet segments nobody labelled, raw label "object") are left
  out unless ``include_unknown``: VLA-3D's own scene graph leaves them out (the example scene has 61 rows
  and 59 objects in its scene graph; those two rows are the difference).
- region: id = region_id, name = region_label, box = the CSV box (a heading != 0 becomes the axis-aligned
  box around the turned one). Without a region CSV: the scene-graph JSON's regions (the box around the 8
  corners). Without either: one region per region_id of the objects, spanning them, named "region <id>".
- An object whose region_id is missing gets ``region_id=None``; one naming no known region is an error.

Errors name ``object_result_csv.<row>.<column>`` (row = 0-based data row; the message gives the file
line), ``region_result_csv.<row>.<column>`` or ``scene_graph.regions.<key>.<field>``.
"""

from __future__ import annotations

import csv
import glob
import io
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from app.errors import InvalidSceneGraph
from app.scene_graph.fields import (
    as_list,
    as_mapping,
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

OBJECT_FILE_SUFFIX = "_object_result.csv"
REGION_FILE_SUFFIX = "_region_result.csv"
SCENE_GRAPH_FILE_SUFFIX = "_scene_graph.json"
STATEMENTS_FILE_SUFFIX = "_referential_statements.json"
_SCENE_FILE_SUFFIXES = (
    OBJECT_FILE_SUFFIX,
    REGION_FILE_SUFFIX,
    SCENE_GRAPH_FILE_SUFFIX,
    STATEMENTS_FILE_SUFFIX,
)

UNKNOWN_LABEL = "unknown"
MISSING = "_"
_OBJECT_COLUMNS = (
    "object_id",
    "object_bbox_cx",
    "object_bbox_cy",
    "object_bbox_cz",
    "object_bbox_xlength",
    "object_bbox_ylength",
    "object_bbox_zlength",
)
_REGION_COLUMNS = (
    "region_id",
    "region_bbox_cx",
    "region_bbox_cy",
    "region_bbox_cz",
    "region_bbox_xlength",
    "region_bbox_ylength",
    "region_bbox_zlength",
)
_PAYLOAD_KEYS = frozenset({"object_result_csv", "region_result_csv", "scene_graph"})
_COLOUR_SLOTS = (1, 2, 3)


class _Row:
    """One CSV data row: its values by column, where it is, and converters that name it in errors."""

    def __init__(self, values: dict[str, str], field: str, line: int) -> None:
        self.values = values
        self.field = field
        self.line = line

    def text(self, column: str) -> str | None:
        """The stripped value, None when missing ("_", empty, or absent from a short row)."""
        value = self.values.get(column, "").strip()
        return None if value in ("", MISSING) else value

    def required(self, column: str) -> str:
        value = self.text(column)
        if value is None:
            msg = f"missing value (line {self.line})"
            raise InvalidSceneGraph(msg, field=join_field(self.field, column))
        return value

    def number(self, column: str, *, positive: bool = False) -> float | None:
        text = self.text(column)
        return None if text is None else self._finite(text, column, positive)

    def required_number(self, column: str, *, positive: bool = False) -> float:
        return self._finite(self.required(column), column, positive)

    def _finite(self, text: str, column: str, positive: bool) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            msg = f"expected a finite number, got {describe(text)} (line {self.line})"
            raise InvalidSceneGraph(msg, field=join_field(self.field, column))
        if positive and value <= 0:
            msg = f"must be > 0, got {value} (line {self.line})"
            raise InvalidSceneGraph(msg, field=join_field(self.field, column))
        return value

    def integer(self, column: str) -> int | None:
        text = self.text(column)
        if text is None:
            return None
        try:
            return int(text)
        except ValueError as exc:
            msg = f"expected an integer, got {describe(text)} (line {self.line})"
            raise InvalidSceneGraph(msg, field=join_field(self.field, column)) from exc


def parse_vla3d(
    object_result_csv: str,
    region_result_csv: str | None = None,
    scene_graph: dict[str, Any] | None = None,
    *,
    max_objects: int | None = None,
    include_unknown: bool = False,
) -> SceneGraph:
    """Normalise one VLA-3D scene from its files' contents (see the module docstring)."""
    rows = _read_csv(object_result_csv, "object_result_csv", _OBJECT_COLUMNS)
    if not include_unknown:
        rows = [row for row in rows if row.text("nyu_label") != UNKNOWN_LABEL]
    check_object_limit(len(rows), max_objects)
    objects = [_scene_object(row) for row in rows]
    check_unique(
        ((o.id, join_field(r.field, "object_id")) for o, r in zip(objects, rows, strict=True)), "object id"
    )

    if region_result_csv is not None:
        regions = _regions_from_csv(region_result_csv)
    elif scene_graph is not None:
        regions = _regions_from_scene_graph(scene_graph)
    else:
        regions = _regions_spanning(objects, rows)
    known = {region.id for region in regions}
    for obj, row in zip(objects, rows, strict=True):
        if obj.region_id is not None and obj.region_id not in known:
            msg = f"unknown region id {obj.region_id!r} (line {row.line}); known: {sorted(known)}"
            raise InvalidSceneGraph(msg, field=join_field(row.field, "region_id"))
    return build_scene_graph(regions, objects)


def parse_vla3d_payload(data: object, max_objects: int | None = None) -> SceneGraph:
    """`parse_vla3d` on the JSON form {"object_result_csv": str, "region_result_csv": str | None,
    "scene_graph": dict | None} that `app.scene_graph.loader` accepts."""
    payload = as_mapping(data, None)
    unknown = sorted(set(payload) - _PAYLOAD_KEYS)
    if unknown:
        msg = f"unexpected key; a VLA-3D payload holds only {sorted(_PAYLOAD_KEYS)}"
        raise InvalidSceneGraph(msg, field=unknown[0])
    objects_csv = payload.get("object_result_csv")
    if not isinstance(objects_csv, str):
        msg = f"expected the text of <scene>{OBJECT_FILE_SUFFIX}, got {describe(objects_csv)}"
        raise InvalidSceneGraph(msg, field="object_result_csv")
    regions_csv = payload.get("region_result_csv")
    if regions_csv is not None and not isinstance(regions_csv, str):
        msg = f"expected the text of <scene>{REGION_FILE_SUFFIX} or null, got {describe(regions_csv)}"
        raise InvalidSceneGraph(msg, field="region_result_csv")
    scene_graph = payload.get("scene_graph")
    if scene_graph is not None:
        scene_graph = as_mapping(scene_graph, "scene_graph")
    return parse_vla3d(objects_csv, regions_csv, scene_graph, max_objects=max_objects)


def list_vla3d_scenes(folder: Path | str) -> list[str]:
    """Names of the scenes (``<scene>_object_result.csv`` files) in `folder` and its sub-folders, sorted."""
    root = Path(folder)
    if not root.is_dir():
        msg = f"{root} is not a folder"
        raise InvalidSceneGraph(msg)
    return sorted(
        {
            path.name.removesuffix(OBJECT_FILE_SUFFIX)
            for path in root.rglob(f"*{OBJECT_FILE_SUFFIX}")
            if path.is_file() and path.name != OBJECT_FILE_SUFFIX
        }
    )


def load_vla3d_scene(
    folder: Path | str,
    scene_name: str | None = None,
    *,
    max_objects: int | None = None,
    include_unknown: bool = False,
) -> SceneGraph:
    """Read scene `scene_name` from `folder`, where its files lie in the folder itself, in a sub-folder
    named after it (the benchmark's layout) or deeper. Without `scene_name` the folder must hold
    exactly one scene."""
    root = Path(folder)
    if scene_name is None:
        scenes = list_vla3d_scenes(root)
        if len(scenes) != 1:
            listed = ", ".join(scenes[:5]) + (", ..." if len(scenes) > 5 else "")
            msg = (
                f"{root} holds {len(scenes)} VLA-3D scenes ({listed}); name one"
                if scenes
                else f"{root} holds no VLA-3D scene (no *{OBJECT_FILE_SUFFIX})"
            )
            raise InvalidSceneGraph(msg)
        scene_name = scenes[0]
    object_path = _find_object_file(root, scene_name)
    scene_dir = object_path.parent
    region_path = scene_dir / f"{scene_name}{REGION_FILE_SUFFIX}"
    graph_path = scene_dir / f"{scene_name}{SCENE_GRAPH_FILE_SUFFIX}"
    scene_graph = None
    # Only the fallback for the region CSV's boxes: with that CSV at hand the JSON is not read, so that an
    # unreadable one costs nothing.
    if not region_path.is_file() and graph_path.is_file():
        try:
            scene_graph = json.loads(_read_text(graph_path))
        except (ValueError, RecursionError) as exc:
            msg = f"{graph_path} is not valid JSON: {exc}"
            raise InvalidSceneGraph(msg, field="scene_graph") from exc
        scene_graph = as_mapping(scene_graph, "scene_graph")
    return parse_vla3d(
        _read_text(object_path),
        _read_text(region_path) if region_path.is_file() else None,
        scene_graph,
        max_objects=max_objects,
        include_unknown=include_unknown,
    )


def find_vla3d_scene_of_file(path: Path) -> str | None:
    """The scene a file belongs to when it is one of a VLA-3D scene's files (its object CSV beside it)."""
    for suffix in _SCENE_FILE_SUFFIXES:
        if path.name.endswith(suffix) and path.name != suffix:
            scene_name = path.name.removesuffix(suffix)
            if (path.parent / f"{scene_name}{OBJECT_FILE_SUFFIX}").is_file():
                return scene_name
    return None


def _find_object_file(root: Path, scene_name: str) -> Path:
    if not scene_name or "/" in scene_name or "\\" in scene_name or scene_name in (".", ".."):
        msg = f"not a scene name: {describe(scene_name)}"
        raise InvalidSceneGraph(msg)
    file_name = f"{scene_name}{OBJECT_FILE_SUFFIX}"
    # The usual places first: a whole benchmark folder is walked once per scene otherwise.
    for candidate in (root / file_name, root / scene_name / file_name):
        if candidate.is_file():
            return candidate
    matches = sorted(p for p in root.rglob(glob.escape(file_name)) if p.is_file())
    if len(matches) != 1:
        where = "nowhere" if not matches else ", ".join(str(m.parent) for m in matches[:3])
        msg = f"scene {scene_name!r} must have exactly one {file_name} under {root}; found it {where}"
        raise InvalidSceneGraph(msg)
    return matches[0]


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        msg = f"cannot read {path}: {exc}"
        raise InvalidSceneGraph(msg) from exc


def _read_csv(text: str, field: str, required: tuple[str, ...]) -> list[_Row]:
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff"), newline=""))
    try:
        header = [name.strip() for name in next(reader, [])]
        if not header:
            msg = "empty CSV: no header line"
            raise InvalidSceneGraph(msg, field=field)
        for column in required:
            if column not in header:
                msg = f"missing column {column!r} in the header"
                raise InvalidSceneGraph(msg, field=join_field(field, column))
        check_unique(((name, field) for name in header), "column name")
        rows: list[_Row] = []
        for cells in reader:
            if not any(cell.strip() for cell in cells):
                continue
            row_field = join_field(field, len(rows))
            if len(cells) > len(header):
                msg = f"{len(cells)} fields but the header names {len(header)} (line {reader.line_num})"
                raise InvalidSceneGraph(msg, field=row_field)
            rows.append(_Row(dict(zip(header, cells, strict=False)), row_field, reader.line_num))
    except csv.Error as exc:
        msg = f"not valid CSV (line {reader.line_num}): {exc}"
        raise InvalidSceneGraph(msg, field=field) from exc
    return rows


def _scene_object(row: _Row) -> SceneObject:
    nyu_label, raw_label = row.text("nyu_label"), row.text("raw_label")
    label = nyu_label or raw_label
    if label is None:
        msg = f"no label: nyu_label and raw_label are both missing (line {row.line})"
        raise InvalidSceneGraph(msg, field=join_field(row.field, "nyu_label"))
    center = [row.required_number(f"object_bbox_c{axis}") for axis in "xyz"]
    size = [row.required_number(f"object_bbox_{axis}length", positive=True) for axis in "xyz"]
    attributes: dict[str, Any] = {
        "raw_label": raw_label,
        "nyu_label": nyu_label,
        "nyu40_label": row.text("nyu40_label"),
        "nyu_id": row.integer("nyu_id"),
        "nyu40_id": row.integer("nyu40_id"),
        "front_heading": row.number("object_front_heading"),
        "colors": _colours(row),
    }
    return build_object(
        row.field,
        {"id": join_field(row.field, "object_id"), "label": join_field(row.field, "nyu_label")},
        id=row.required("object_id"),
        label=label,
        center=center,
        size=size,
        yaw=row.number("object_bbox_heading") or 0.0,
        region_id=row.text("region_id"),
        attributes=attributes,
    )


def _colours(row: _Row) -> list[dict[str, Any]]:
    colours = []
    for slot in _COLOUR_SLOTS:
        name = row.text(f"object_color_scheme{slot}")
        if name is None:
            continue
        channels = [row.integer(f"object_color_{channel}{slot}") for channel in "rgb"]
        colours.append(
            {
                "name": name,
                "rgb": None if None in channels else channels,
                "fraction": row.number(f"object_color_scheme_percentage{slot}"),
                "average_distance": row.number(f"object_color_scheme_average_dist{slot}"),
            }
        )
    return colours


def _regions_from_csv(text: str) -> list[Region]:
    rows = _read_csv(text, "region_result_csv", _REGION_COLUMNS)
    regions = []
    for row in rows:
        center = [row.required_number(f"region_bbox_c{axis}") for axis in "xyz"]
        length_x, length_y, length_z = (
            row.required_number(f"region_bbox_{axis}length", positive=True) for axis in "xyz"
        )
        heading = row.number("region_bbox_heading") or 0.0
        # The axis-aligned box around a box turned by `heading` about +z.
        cos, sin = abs(math.cos(heading)), abs(math.sin(heading))
        size = [cos * length_x + sin * length_y, sin * length_x + cos * length_y, length_z]
        regions.append(
            build_region(
                row.field,
                {"id": join_field(row.field, "region_id"), "name": join_field(row.field, "region_label")},
                id=row.required("region_id"),
                name=row.text("region_label") or "",
                center=center,
                size=size,
            )
        )
    id_fields = [join_field(row.field, "region_id") for row in rows]
    check_unique(zip((r.id for r in regions), id_fields, strict=True), "region id")
    return regions


def _regions_from_scene_graph(scene_graph: Mapping[str, Any]) -> list[Region]:
    entries = as_mapping(as_mapping(scene_graph, "scene_graph").get("regions"), "scene_graph.regions")
    regions = []
    fields = []
    for key, value in entries.items():
        field = join_field("scene_graph.regions", key)
        entry = as_mapping(value, field)
        region_id = entry.get("region_id", key)
        if isinstance(region_id, int) and not isinstance(region_id, bool):
            region_id = str(region_id)
        if not isinstance(region_id, str) or not region_id:
            msg = f"expected a region id, got {describe(region_id)}"
            raise InvalidSceneGraph(msg, field=join_field(field, "region_id"))
        name = entry.get("region_name", "")
        if not isinstance(name, str):
            msg = f"expected a string, got {describe(name)}"
            raise InvalidSceneGraph(msg, field=join_field(field, "region_name"))
        corners_field = join_field(field, "region_bbox")
        corners = [as_vector3(c, corners_field) for c in as_list(entry.get("region_bbox"), corners_field)]
        if not corners:
            msg = "a region box needs its corners"
            raise InvalidSceneGraph(msg, field=corners_field)
        low = [min(c[axis] for c in corners) for axis in range(3)]
        high = [max(c[axis] for c in corners) for axis in range(3)]
        center = [0.5 * (lo + hi) for lo, hi in zip(low, high, strict=True)]
        size = [hi - lo for lo, hi in zip(low, high, strict=True)]
        regions.append(
            build_region(
                field,
                {
                    "id": join_field(field, "region_id"),
                    "size": corners_field,
                    "name": join_field(field, "region_name"),
                },
                id=region_id,
                name=name,
                center=center,
                size=size,
            )
        )
        fields.append(join_field(field, "region_id"))
    check_unique(((r.id, f) for r, f in zip(regions, fields, strict=True)), "region id")
    return regions


def _regions_spanning(objects: list[SceneObject], rows: list[_Row]) -> list[Region]:
    """Without region files: one region per region_id, the box around its objects."""
    members: dict[str, list[tuple[SceneObject, _Row]]] = {}
    for obj, row in zip(objects, rows, strict=True):
        if obj.region_id is not None:
            members.setdefault(obj.region_id, []).append((obj, row))
    regions = []
    for region_id, group in members.items():
        center, size = bounding_box(obj for obj, _ in group)
        regions.append(
            build_region(
                group[0][1].field,
                {"id": join_field(group[0][1].field, "region_id")},
                id=region_id,
                name=f"region {region_id}",
                center=center,
                size=size,
            )
        )
    return regions
