"""Hydra / Spark-DSG scene graphs (the `spark_dsg` package), read into `SceneGraph`.

Two inputs:

- JSON, as ``DynamicSceneGraph.save("x.json")`` writes it ("SPARK_DSG_header", "nodes", "edges",
  "layer_keys"/"layer_ids", "layer_names", "metadata"). It is read here in pure Python, without the C++
  library, so every malformed field is reported by its path ("nodes.4.attributes.bounding_box.dimensions").
- Binary: ``DynamicSceneGraph.to_binary()`` bytes (what Hydra streams) or a ``.sparkdsg`` file. Only the
  C++ library reads that format, and it sizes vectors from the payload's length fields before checking
  them: setting one 4-byte length in a 1.4 kB graph made ``from_binary`` allocate 2 GB and take 3.4 s
  before failing, and larger lengths ask for tens of GB. So binary input is decoded in a child process
  with a capped address space and a timeout (`decode_spark_dsg_binary`), which re-saves the graph as
  JSON for the reader above; a crash, hang or memory blow-up of the decoder costs one child, never the
  service. The price is a process start per binary graph (0.15-0.25 s for a small graph on the 2-core
  development machine; 1.9 s for 20,000 objects).

Normalisation:

- OBJECTS layer (partition 0) -> objects: id = the node's NodeSymbol string ("O12"; ids whose category
  byte is not a letter print as the plain integer, because NodeSymbol.str() would print only the index
  and two such ids could collide). center/size = bounding_box.world_P_center/dimensions, yaw = heading of
  the box's world_R_center (0 for an axis-aligned box; for a full 3D rotation only its yaw is kept).
  label = attrs.name when set (and not merely the symbol), else the objects layer's labelspace name of
  attrs.semantic_label, else ``class_<semantic_label>``, else "unknown".
  attributes: dsg_node_id (the raw 64-bit id), box_type, semantic_label (when set), size_defaulted.
- Degenerate boxes: a box fitted to a few or coplanar points (a poster, a rug) can have a zero extent,
  and an object without a box has type INVALID. Rejecting a whole live map for one such object would
  help nobody, so each axis that is not > 0 becomes `DEGENERATE_EXTENT_M` (0.1 m), an object without a
  box gets a 0.1 m cube at its node position, and ``attributes["size_defaulted"] = True`` marks both.
  Non-finite numbers are still rejected.
- ROOMS layer -> regions: id = NodeSymbol string, name = attrs.name, else the rooms labelspace name,
  else the id. center/size from the bounding box when it is valid (all extents > 0; size = the sides of
  the axis-aligned box around the box turned by its yaw), else the box around the room's position and its
  children's positions, each extent at least 0.1 m.
- An object's region is the room found by walking up parent edges (object -> place -> room, or object ->
  room); a parent is the endpoint of an edge in a higher layer. The nearest room wins, the lowest id on
  ties; objects under no room get ``region_id=None``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import InvalidSceneGraph
from app.scene_graph.fields import (
    as_float,
    as_int,
    as_list,
    as_mapping,
    as_vector3,
    build_object,
    build_region,
    build_scene_graph,
    check_object_limit,
    describe,
    join_field,
)
from app.scene_graph.model import Region, SceneGraph, SceneObject, aabb_extents

# The Spark-DSG binary opens with a msgpack-style array tag (0xdd): the layer list, or the file header.
SPARK_DSG_ARRAY_TAG = 0xDD
DEGENERATE_EXTENT_M = 0.1
NO_SEMANTIC_LABEL = 2**32 - 1  # spark_dsg's SemanticNodeAttributes.NO_SEMANTIC_LABEL
# The header a .sparkdsg file starts with: the string "SPARK_DSG" as a 9-byte array.
SPARK_DSG_FILE_MAGIC = bytes([SPARK_DSG_ARRAY_TAG, 9, 0, 0, 0]) + b"SPARK_DSG"

BINARY_DECODE_TIMEOUT_S = 60.0
# Address space the decoder may add on top of what the interpreter and spark_dsg already use.
BINARY_DECODE_BASE_MEMORY = 1 << 30
BINARY_DECODE_MEMORY_PER_BYTE = 64

_DEFAULT_LAYERS = {"OBJECTS": (2, 0), "ROOMS": (4, 0)}
_SYMBOL_INDEX_BITS = 56
_MAX_NODE_ID = 2**64

# Runs in the child: decode the payload file with spark_dsg and save it as JSON. Exit codes: 0 done,
# 3 the library rejected the payload, 4 spark_dsg missing, 5 out of the memory allowance.
_DECODER_SCRIPT = r"""
import resource, sys
payload_path, json_path, allowance = sys.argv[1], sys.argv[2], int(sys.argv[3])
try:
    import spark_dsg
except ImportError as exc:
    sys.stderr.write(f"spark_dsg is not installed: {exc}")
    sys.exit(4)
with open(payload_path, "rb") as fh:
    payload = fh.read()
# Capped only now: the interpreter and the imports above need memory that no payload controls.
with open("/proc/self/statm") as fh:
    in_use = int(fh.read().split()[0]) * resource.getpagesize()
hard = resource.getrlimit(resource.RLIMIT_AS)[1]
limit = in_use + allowance if hard == resource.RLIM_INFINITY else min(hard, in_use + allowance)
resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
try:
    if payload.startswith(bytes.fromhex(sys.argv[4])):
        graph = spark_dsg.DynamicSceneGraph.load(payload_path)
    else:
        graph = spark_dsg.DynamicSceneGraph.from_binary(payload)
    graph.save(json_path, include_mesh=False)
except MemoryError:
    sys.exit(5)
except Exception as exc:
    sys.stderr.write(f"{type(exc).__name__}: {exc}"[:500])
    sys.exit(3)
"""


@dataclass(frozen=True)
class _Node:
    index: int  # position in "nodes", for error paths
    node_id: int
    layer: int
    partition: int
    attributes: dict[str, Any]

    @property
    def field(self) -> str:
        return f"nodes.{self.index}"


@dataclass(frozen=True)
class _Box:
    center: list[float]
    dimensions: list[float]
    yaw: float
    box_type: str


def node_symbol(node_id: int) -> str:
    """Spark-DSG's printed node id: category letter + index ("O12"), else the plain integer."""
    category, index = node_id >> _SYMBOL_INDEX_BITS, node_id & ((1 << _SYMBOL_INDEX_BITS) - 1)
    letter = chr(category)
    return f"{letter}{index}" if letter.isascii() and letter.isalpha() else str(node_id)


def parse_spark_dsg_json(data: object, max_objects: int | None = None) -> SceneGraph:
    """Normalise the JSON that ``DynamicSceneGraph.save`` writes (see the module docstring)."""
    document = as_mapping(data, None)
    header = document.get("SPARK_DSG_header")
    if header is not None:
        as_mapping(header, "SPARK_DSG_header")
    objects_key = _layer_key(document, "OBJECTS")
    rooms_key = _layer_key(document, "ROOMS")
    nodes = _read_nodes(as_list(document.get("nodes"), "nodes"))
    parents = _read_parents(as_list(document.get("edges", []), "edges"), nodes)

    object_nodes = [n for n in nodes.values() if (n.layer, n.partition) == objects_key]
    check_object_limit(len(object_nodes), max_objects)
    room_nodes = [n for n in nodes.values() if (n.layer, n.partition) == rooms_key]
    object_labels = _labelspace(document, "OBJECTS", objects_key)
    room_labels = _labelspace(document, "ROOMS", rooms_key)

    children: dict[int, list[_Node]] = {}
    for child_id, parent_ids in parents.items():
        for parent_id in parent_ids:
            children.setdefault(parent_id, []).append(nodes[child_id])
    regions = [_room_region(room, children.get(room.node_id, []), room_labels) for room in room_nodes]
    room_ids = {room.node_id for room in room_nodes}
    objects = [
        _scene_object(node, _room_of(node.node_id, parents, room_ids), object_labels) for node in object_nodes
    ]
    return build_scene_graph(regions, objects)


def parse_spark_dsg_binary(
    payload: bytes, max_objects: int | None = None, *, timeout_s: float = BINARY_DECODE_TIMEOUT_S
) -> SceneGraph:
    """Normalise Spark-DSG binary (``to_binary()`` bytes or a ``.sparkdsg`` file's content)."""
    return parse_spark_dsg_json(decode_spark_dsg_binary(payload, timeout_s=timeout_s), max_objects)


def decode_spark_dsg_binary(payload: bytes, *, timeout_s: float = BINARY_DECODE_TIMEOUT_S) -> dict[str, Any]:
    """The graph in `payload` as Spark-DSG JSON, decoded by spark_dsg in a child process whose address
    space is capped (1 GiB + 64 bytes per payload byte beyond its start-up use) and which is killed after
    `timeout_s`; every way that can fail raises InvalidSceneGraph."""
    check_binary_prefix(payload)
    allowance = BINARY_DECODE_BASE_MEMORY + BINARY_DECODE_MEMORY_PER_BYTE * len(payload)
    # One BLAS thread is plenty for decoding and keeps the child's start-up footprint small.
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory(prefix="vlmap-dsg-") as tmp:
        # spark_dsg picks the reader from the file extension; .sparkdsg is the binary one.
        payload_path, json_path = Path(tmp) / "payload.sparkdsg", Path(tmp) / "graph.json"
        payload_path.write_bytes(payload)
        command = [
            sys.executable,
            "-I",  # isolated: no user site, no PYTHON* variables, no cwd on sys.path
            "-c",
            _DECODER_SCRIPT,
            str(payload_path),
            str(json_path),
            str(allowance),
            SPARK_DSG_FILE_MAGIC.hex(),
        ]
        try:
            child = subprocess.run(command, capture_output=True, timeout=timeout_s, env=env, check=False)
        except subprocess.TimeoutExpired as exc:
            msg = f"decoding the Spark-DSG binary took longer than {timeout_s:g} s"
            raise InvalidSceneGraph(msg) from exc
        except OSError as exc:
            msg = f"cannot start the Spark-DSG decoder: {exc}"
            raise InvalidSceneGraph(msg) from exc
        reason = child.stderr.decode("utf-8", "replace").strip()
        if child.returncode == 0:
            try:
                text = json_path.read_text(encoding="utf-8", errors="replace")
            except OSError as exc:
                msg = f"the Spark-DSG decoder wrote no graph: {exc}"
                raise InvalidSceneGraph(msg) from exc
        elif child.returncode == 3:
            msg = f"not a readable Spark-DSG binary graph: {reason}"
            raise InvalidSceneGraph(msg)
        elif child.returncode == 5:
            msg = f"decoding the Spark-DSG binary needed more than its memory allowance of {allowance} bytes"
            raise InvalidSceneGraph(msg)
        elif child.returncode < 0:
            msg = f"the Spark-DSG decoder crashed on this payload (signal {-child.returncode})"
            raise InvalidSceneGraph(msg)
        else:
            msg = f"the Spark-DSG decoder failed (exit {child.returncode}): {reason[-300:]}"
            raise InvalidSceneGraph(msg)
    try:
        return as_mapping(json.loads(text), None)
    except (ValueError, RecursionError) as exc:
        msg = f"the Spark-DSG decoder wrote unreadable JSON: {exc}"
        raise InvalidSceneGraph(msg) from exc


def check_binary_prefix(payload: bytes) -> None:
    """Cheap structural check of the opening array, so that arbitrary bytes never start a decoder.
    It is not the safety net (the child process is): deeper fields are only checked by spark_dsg."""
    if payload.startswith(SPARK_DSG_FILE_MAGIC):
        return
    if not payload:
        msg = "empty payload: neither JSON nor Spark-DSG binary"
        raise InvalidSceneGraph(msg)
    if payload[0] != SPARK_DSG_ARRAY_TAG or len(payload) < 5:
        msg = (
            f"neither JSON text nor Spark-DSG binary (which opens with byte 0x{SPARK_DSG_ARRAY_TAG:02x}); "
            f"starts with {payload[:8].hex(' ')}"
        )
        raise InvalidSceneGraph(msg)
    layer_count = int.from_bytes(payload[1:5], "little")
    # Every layer entry takes at least two bytes (a type tag and a value).
    if 2 * layer_count > len(payload) - 5:
        msg = f"truncated Spark-DSG binary: declares {layer_count} layers in {len(payload)} bytes"
        raise InvalidSceneGraph(msg)


def _layer_key(document: Mapping[str, Any], name: str) -> tuple[int, int]:
    """(layer, partition) of a named layer: layer_names holds {"layer", "partition"} (>= 1.1.1) or a
    bare layer number (1.1.0); older files use the default numbering."""
    if "layer_names" not in document:
        return _DEFAULT_LAYERS[name]
    names = as_mapping(document["layer_names"], "layer_names")
    if name not in names:
        return _DEFAULT_LAYERS[name]
    field = join_field("layer_names", name)
    value = names[name]
    if isinstance(value, dict):
        key = as_mapping(value, field)
        return as_int(key.get("layer"), join_field(field, "layer")), as_int(
            key.get("partition", 0), join_field(field, "partition")
        )
    return as_int(value, field), 0


def _read_nodes(records: list[Any]) -> dict[int, _Node]:
    nodes: dict[int, _Node] = {}
    for index, record in enumerate(records):
        field = f"nodes.{index}"
        node = as_mapping(record, field)
        node_id = _node_id(node.get("id"), join_field(field, "id"))
        if node_id in nodes:
            msg = f"duplicate node id {node_symbol(node_id)}"
            raise InvalidSceneGraph(msg, field=join_field(field, "id"))
        layer = as_int(node.get("layer"), join_field(field, "layer"))
        if "partition" in node:
            partition = as_int(node["partition"], join_field(field, "partition"))
        else:
            # Before 1.1.0 dynamic (agent) nodes carried a timestamp and their symbol's category was the
            # partition; everything else was partition 0.
            partition = node_id >> _SYMBOL_INDEX_BITS if "timestamp" in node else 0
        attributes = as_mapping(node.get("attributes"), join_field(field, "attributes"))
        nodes[node_id] = _Node(index, node_id, layer, partition, attributes)
    return nodes


def _read_parents(records: list[Any], nodes: Mapping[int, _Node]) -> dict[int, list[int]]:
    """Child node id -> parent node ids (the endpoints of its edges in higher layers)."""
    parents: dict[int, list[int]] = {}
    for index, record in enumerate(records):
        field = f"edges.{index}"
        edge = as_mapping(record, field)
        source = _node_id(edge.get("source"), join_field(field, "source"))
        target = _node_id(edge.get("target"), join_field(field, "target"))
        # spark_dsg itself skips edges whose endpoints are missing; so do we.
        if source not in nodes or target not in nodes:
            continue
        low, high = sorted((nodes[source], nodes[target]), key=lambda n: n.layer)
        if low.layer < high.layer:
            parents.setdefault(low.node_id, []).append(high.node_id)
    return parents


def _room_of(node_id: int, parents: Mapping[int, list[int]], room_ids: set[int]) -> int | None:
    """The nearest room above a node (fewest parent steps, then lowest id). Parents always sit in a
    higher layer, so the walk ends after at most as many steps as there are layers."""
    frontier = set(parents.get(node_id, ()))
    seen = set(frontier)
    while frontier:
        rooms = frontier & room_ids
        if rooms:
            return min(rooms)
        frontier = {p for n in frontier for p in parents.get(n, ()) if p not in seen}
        seen |= frontier
    return None


def _labelspace(document: Mapping[str, Any], layer_name: str, layer_key: tuple[int, int]) -> dict[int, str]:
    """Semantic label -> name for one layer. spark_dsg stores a labelspace in metadata.labelspaces under
    the layer's name ("OBJECTS") when set by name, else under "_l<layer>p<partition>"; both are read."""
    metadata = document.get("metadata")
    if not isinstance(metadata, dict) or "labelspaces" not in metadata:
        return {}
    labelspaces = as_mapping(metadata["labelspaces"], "metadata.labelspaces")
    for key in (layer_name, f"_l{layer_key[0]}p{layer_key[1]}"):
        if key in labelspaces:
            break
    else:
        return {}
    field = join_field("metadata.labelspaces", key)
    names: dict[int, str] = {}
    for index, pair in enumerate(as_list(labelspaces[key], field)):
        if not (isinstance(pair, list) and len(pair) == 2 and isinstance(pair[1], str)):
            msg = f"expected a [label, name] pair, got {describe(pair)}"
            raise InvalidSceneGraph(msg, field=join_field(field, index))
        names[as_int(pair[0], join_field(field, index, 0))] = pair[1]
    return names


def _scene_object(node: _Node, room_id: int | None, labels: Mapping[int, str]) -> SceneObject:
    field = join_field(node.field, "attributes")
    attrs = node.attributes
    symbol = node_symbol(node.node_id)
    box = _read_box(attrs.get("bounding_box"), join_field(field, "bounding_box"))
    attributes: dict[str, Any] = {"dsg_node_id": node.node_id, "box_type": box.box_type if box else "INVALID"}
    if box is None:
        center, yaw = as_vector3(attrs.get("position"), join_field(field, "position")), 0.0
        size = [DEGENERATE_EXTENT_M] * 3
        attributes["size_defaulted"] = True
    else:
        center, yaw = box.center, box.yaw
        size = [d if d > 0 else DEGENERATE_EXTENT_M for d in box.dimensions]
        if size != box.dimensions:
            attributes["size_defaulted"] = True
    semantic_label = _semantic_label(attrs, field)
    if semantic_label is not None:
        attributes["semantic_label"] = semantic_label

    name = attrs.get("name")
    if isinstance(name, str) and name and name != symbol:
        label = name
    elif semantic_label is not None:
        label = labels.get(semantic_label, f"class_{semantic_label}")
    else:
        label = "unknown"
    return build_object(
        node.field,
        {"label": join_field(field, "name"), "id": join_field(node.field, "id")},
        id=symbol,
        label=label,
        center=center,
        size=size,
        yaw=yaw,
        region_id=node_symbol(room_id) if room_id is not None else None,
        attributes=attributes,
    )


def _room_region(room: _Node, children: list[_Node], labels: Mapping[int, str]) -> Region:
    field = join_field(room.field, "attributes")
    attrs = room.attributes
    symbol = node_symbol(room.node_id)
    box = _read_box(attrs.get("bounding_box"), join_field(field, "bounding_box"))
    if box is not None and all(d > 0 for d in box.dimensions):
        # Regions are axis-aligned and a room's box may be oriented: its local sides are not world extents.
        center = box.center
        size = aabb_extents(np.array([box.dimensions]), np.array([box.yaw]))[0].tolist()
    else:
        points = [as_vector3(attrs.get("position"), join_field(field, "position"))]
        for child in children:
            if "position" in child.attributes:
                position_field = join_field(child.field, "attributes", "position")
                points.append(as_vector3(child.attributes["position"], position_field))
        low = [min(p[axis] for p in points) for axis in range(3)]
        high = [max(p[axis] for p in points) for axis in range(3)]
        center = [0.5 * (lo + hi) for lo, hi in zip(low, high, strict=True)]
        size = [max(hi - lo, DEGENERATE_EXTENT_M) for lo, hi in zip(low, high, strict=True)]

    name = attrs.get("name")
    semantic_label = _semantic_label(attrs, field)
    if isinstance(name, str) and name:
        region_name = name
    elif semantic_label is not None and semantic_label in labels:
        region_name = labels[semantic_label]
    else:
        region_name = symbol
    return build_region(
        room.field,
        {"name": join_field(field, "name"), "id": join_field(room.field, "id")},
        id=symbol,
        name=region_name,
        center=center,
        size=size,
    )


def _read_box(value: object, field: str) -> _Box | None:
    """A bounding box, or None when absent or of type INVALID. Dimensions may be <= 0 (see module doc)."""
    if value is None:
        return None
    box = as_mapping(value, field)
    box_type = box.get("type")
    # Named types since 1.0.3; older files wrote the enum number (0 = INVALID).
    if box_type in (None, "INVALID", 0):
        return None
    if isinstance(box_type, bool) or not isinstance(box_type, str | int):
        msg = f"expected a box type name, got {describe(box_type)}"
        raise InvalidSceneGraph(msg, field=join_field(field, "type"))
    if "dimensions" in box:
        dimensions = as_vector3(box["dimensions"], join_field(field, "dimensions"))
        center = as_vector3(box.get("world_P_center"), join_field(field, "world_P_center"))
    elif "min" in box and "max" in box:  # before 1.0.3: corners instead of dimensions
        low = as_vector3(box["min"], join_field(field, "min"))
        high = as_vector3(box["max"], join_field(field, "max"))
        dimensions = [hi - lo for lo, hi in zip(low, high, strict=True)]
        midpoint = [0.5 * (lo + hi) for lo, hi in zip(low, high, strict=True)]
        center = as_vector3(box.get("world_P_center", midpoint), join_field(field, "world_P_center"))
    else:
        msg = "a bounding box needs 'dimensions' (or legacy 'min' and 'max')"
        raise InvalidSceneGraph(msg, field=field)
    yaw = _yaw(box.get("world_R_center"), join_field(field, "world_R_center"))
    return _Box(center, dimensions, yaw, str(box_type))


def _yaw(value: object, field: str) -> float:
    """Heading about +z of a quaternion {w, x, y, z}: atan2(2(wz + xy), w² + x² - y² - z²).

    This form needs no normalisation (numerator and denominator scale alike); identity when absent."""
    if value is None:
        return 0.0
    quaternion = as_mapping(value, field)
    w, x, y, z = (as_float(quaternion.get(k), join_field(field, k)) for k in ("w", "x", "y", "z"))
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def _semantic_label(attrs: Mapping[str, Any], field: str) -> int | None:
    value = attrs.get("semantic_label")
    if value is None:
        return None
    label = as_int(value, join_field(field, "semantic_label"))
    return None if label == NO_SEMANTIC_LABEL else label


def _node_id(value: object, field: str) -> int:
    node_id = as_int(value, field)
    if not 0 <= node_id < _MAX_NODE_ID:
        msg = f"node ids are unsigned 64-bit integers, got {describe(node_id)}"
        raise InvalidSceneGraph(msg, field=field)
    return node_id
