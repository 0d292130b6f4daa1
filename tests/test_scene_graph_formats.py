"""Scene-graph readers: region-grouped JSON, Spark-DSG JSON and binary, VLA-3D, detection and errors."""

from __future__ import annotations

import copy
import csv
import functools
import json
import math
import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.errors import InvalidSceneGraph, LimitExceeded
from app.scene_graph import hydra
from app.scene_graph.loader import (
    INTERNAL_ERROR_MESSAGE,
    SceneGraphFormat,
    detect_format,
    load_scene_graph_file,
    parse_scene_graph,
)
from app.scene_graph.model import SceneGraph
from app.scene_graph.region_grouped import parse_region_grouped, region_integer_ids, to_region_grouped
from app.scene_graph.vla3d import list_vla3d_scenes, load_vla3d_scene, parse_vla3d

RESOURCES = Path(__file__).parent / "resources" / "scene_graphs"
VLA3D_DIR = RESOURCES / "vla3d"
SCENE = "scene0010_01"


def paper_example() -> dict[str, Any]:
    return json.loads((RESOURCES / "region_grouped_paper_example.json").read_text(encoding="utf-8"))


def vla3d_payload() -> dict[str, Any]:
    return {
        "object_result_csv": (VLA3D_DIR / f"{SCENE}_object_result.csv").read_text(encoding="utf-8"),
        "region_result_csv": (VLA3D_DIR / f"{SCENE}_region_result.csv").read_text(encoding="utf-8"),
    }


def native_example() -> dict[str, Any]:
    return {
        "regions": [{"id": "r1", "name": "kitchen", "center": [0.0, 0.0, 1.0], "size": [4.0, 4.0, 2.0]}],
        "objects": [
            {
                "id": "a",
                "label": "table",
                "center": [0.0, 0.0, 0.4],
                "size": [1.0, 0.6, 0.8],
                "region_id": "r1",
            },
            {"id": "b", "label": "cup", "center": [0.1, 0.0, 0.85], "size": [0.1, 0.1, 0.1]},
        ],
    }


def raises_invalid(payload: Any, field: str | None, fmt: str | None = None) -> InvalidSceneGraph:
    with pytest.raises(InvalidSceneGraph) as info:
        parse_scene_graph(payload, fmt)
    assert info.value.field == field, str(info.value)
    return info.value


# --- a small Hydra graph, built with spark_dsg itself ------------------------------------------------------


def build_hydra_graph() -> Any:
    """Kitchen R0 (with a box) and bedroom R1 (no box) over places p0..p2 and objects O1..O4:
    O1 'mug' (named, yawed box) under p0 -> R0; O2 (labelspace 'table') under p1 -> R1; O3 (label 9,
    not in the labelspace, flat box) directly under R0; O4 (no box, no label) under nothing; plus an
    agent in layer 2, partition 'a', which is not an object."""
    import spark_dsg as dsg

    def vec(*values: float) -> np.ndarray:
        return np.array(values, dtype=np.float32)

    graph = dsg.DynamicSceneGraph()
    kitchen = dsg.RoomNodeAttributes()
    kitchen.name = "kitchen"
    kitchen.position = np.array([2.0, 1.0, 1.5])
    kitchen.bounding_box = dsg.BoundingBox(vec(4.0, 3.0, 2.5), vec(2.0, 1.0, 1.25))
    graph.add_node(dsg.DsgLayers.ROOMS, dsg.NodeSymbol("R", 0), kitchen)
    bedroom = dsg.RoomNodeAttributes()
    bedroom.semantic_label = 1
    bedroom.position = np.array([7.0, 1.0, 1.5])
    graph.add_node(dsg.DsgLayers.ROOMS, dsg.NodeSymbol("R", 1), bedroom)

    for index, (room, position) in enumerate(
        [(0, (1.5, 0.5, 0.5)), (1, (6.0, 0.0, 0.5)), (1, (8.5, 2.5, 1.0))]
    ):
        place = dsg.PlaceNodeAttributes()
        place.position = np.array(position)
        graph.add_node(dsg.DsgLayers.PLACES, dsg.NodeSymbol("p", index), place)
        graph.insert_edge(dsg.NodeSymbol("R", room), dsg.NodeSymbol("p", index))

    def add_object(index: int, name: str, label: int | None, box: Any, position: tuple[float, ...]) -> None:
        attrs = dsg.ObjectNodeAttributes()
        attrs.name = name
        if label is not None:
            attrs.semantic_label = label
        if box is not None:
            attrs.bounding_box = box
        attrs.position = np.array(position)
        graph.add_node(dsg.DsgLayers.OBJECTS, dsg.NodeSymbol("O", index), attrs)

    add_object(1, "mug", 3, dsg.BoundingBox(vec(0.1, 0.1, 0.12), vec(1.6, 0.4, 0.95), 0.5), (1.6, 0.4, 0.95))
    add_object(2, "", 7, dsg.BoundingBox(vec(1.2, 0.8, 0.75), vec(6.2, 0.3, 0.375)), (6.2, 0.3, 0.375))
    add_object(3, "", 9, dsg.BoundingBox(vec(0.5, 0.0, 0.3), vec(3.0, 2.5, 1.2)), (3.0, 2.5, 1.2))
    add_object(4, "", None, None, (10.0, 10.0, 0.0))
    graph.insert_edge(dsg.NodeSymbol("p", 0), dsg.NodeSymbol("O", 1))
    graph.insert_edge(dsg.NodeSymbol("p", 1), dsg.NodeSymbol("O", 2))
    graph.insert_edge(dsg.NodeSymbol("R", 0), dsg.NodeSymbol("O", 3))
    agent = dsg.AgentNodeAttributes()
    agent.position = np.array([0.0, 0.0, 0.0])
    graph.add_node(graph.get_layer_key(dsg.DsgLayers.OBJECTS).layer, dsg.NodeSymbol("a", 0), agent, ord("a"))

    graph.set_labelspace(dsg.Labelspace({3: "cup", 7: "table"}), dsg.DsgLayers.OBJECTS)
    graph.set_labelspace(dsg.Labelspace({1: "bedroom"}), dsg.DsgLayers.ROOMS)
    return graph


@functools.cache
def hydra_json_text() -> str:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "graph.json"
        build_hydra_graph().save(str(path), include_mesh=False)
        return path.read_text(encoding="utf-8")


@functools.cache
def hydra_binary() -> bytes:
    return bytes(build_hydra_graph().to_binary())


def check_hydra_graph(sg: SceneGraph) -> None:
    """The normalised form of `build_hydra_graph`, field by field."""
    assert [o.id for o in sg.objects] == ["O1", "O2", "O3", "O4"]
    mug, table, flat, loose = sg.objects
    assert (mug.label, mug.region_id) == ("mug", "R0")  # the name wins over the labelspace's "cup"
    assert mug.center == pytest.approx([1.6, 0.4, 0.95], rel=1e-6)
    assert mug.size == pytest.approx([0.1, 0.1, 0.12], rel=1e-6)
    assert mug.yaw == pytest.approx(0.5, abs=1e-6)
    assert mug.attributes["box_type"] == "RAABB"
    assert mug.attributes["semantic_label"] == 3
    assert "size_defaulted" not in mug.attributes
    assert (table.label, table.region_id, table.yaw) == ("table", "R1", 0.0)  # place p1 -> bedroom
    assert table.size == pytest.approx([1.2, 0.8, 0.75], rel=1e-6)
    assert table.center == pytest.approx([6.2, 0.3, 0.375], rel=1e-6)
    assert (flat.label, flat.region_id) == ("class_9", "R0")  # object hangs directly off the room
    assert flat.size == pytest.approx([0.5, hydra.DEGENERATE_EXTENT_M, 0.3], rel=1e-6)
    assert flat.attributes["size_defaulted"] is True
    assert (loose.label, loose.region_id, loose.center) == ("unknown", None, [10.0, 10.0, 0.0])
    assert loose.size == [hydra.DEGENERATE_EXTENT_M] * 3
    assert loose.attributes["box_type"] == "INVALID"
    assert "semantic_label" not in loose.attributes

    kitchen, bedroom = sg.regions
    assert (kitchen.id, kitchen.name) == ("R0", "kitchen")
    assert kitchen.center == pytest.approx([2.0, 1.0, 1.25])
    assert kitchen.size == pytest.approx([4.0, 3.0, 2.5])
    # No box: the room position (7, 1, 1.5) and its places (6, 0, 0.5), (8.5, 2.5, 1) span it.
    assert (bedroom.id, bedroom.name) == ("R1", "bedroom")
    assert bedroom.center == pytest.approx([7.25, 1.25, 1.0])
    assert bedroom.size == pytest.approx([2.5, 2.5, 1.0])


def test_spark_dsg_json_written_by_spark_dsg(tmp_path: Path) -> None:
    text = hydra_json_text()
    assert "SPARK_DSG_header" in json.loads(text)
    assert detect_format(text) is SceneGraphFormat.SPARK_DSG_JSON
    check_hydra_graph(parse_scene_graph(text))
    path = tmp_path / "hydra.json"
    path.write_text(text, encoding="utf-8")
    check_hydra_graph(load_scene_graph_file(path))


def test_spark_dsg_json_without_header_or_partitions() -> None:
    """Files older than the header: no SPARK_DSG_header, no layer_names, no node partitions."""
    document = json.loads(hydra_json_text())
    del document["SPARK_DSG_header"], document["layer_names"]
    document["nodes"] = [n for n in document["nodes"] if n["partition"] == 0]  # drop the agent
    for node in document["nodes"]:
        del node["partition"]
    assert detect_format(document) is SceneGraphFormat.SPARK_DSG_JSON
    check_hydra_graph(parse_scene_graph(document))


def test_spark_dsg_oriented_room_box_becomes_its_axis_aligned_extents(tmp_path: Path) -> None:
    """A 10 m x 2 m corridor whose box is turned 90 degrees about +z spans 2 m in x and 10 m in y; its local
    sides taken as world extents would leave its own table (2 m along y from its centre) outside it."""
    import spark_dsg as dsg

    graph = dsg.DynamicSceneGraph()
    corridor = dsg.RoomNodeAttributes()
    corridor.name = "corridor"
    corridor.position = np.array([0.0, 0.0, 1.5])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    dims, center = np.array([10.0, 2.0, 3.0], dtype=np.float32), np.array([0.0, 0.0, 1.5], dtype=np.float32)
    corridor.bounding_box = dsg.BoundingBox(dsg.BoundingBoxType.OBB, dims, center, turn)
    graph.add_node(dsg.DsgLayers.ROOMS, dsg.NodeSymbol("R", 0), corridor)
    table = dsg.ObjectNodeAttributes()
    table.name = "table"
    table.position = np.array([0.0, 2.0, 0.4])
    table.bounding_box = dsg.BoundingBox(np.array([1.0, 0.6, 0.8], dtype=np.float32), table.position)
    graph.add_node(dsg.DsgLayers.OBJECTS, dsg.NodeSymbol("O", 1), table)
    graph.insert_edge(dsg.NodeSymbol("R", 0), dsg.NodeSymbol("O", 1))
    path = tmp_path / "corridor.json"
    graph.save(str(path), include_mesh=False)

    sg = parse_scene_graph(path.read_text(encoding="utf-8"))
    (region,), (obj,) = sg.regions, sg.objects
    assert region.center == pytest.approx([0.0, 0.0, 1.5])
    assert region.size == pytest.approx([2.0, 10.0, 3.0], abs=1e-6)
    assert obj.region_id == region.id
    assert all(abs(c - m) <= s / 2 for c, m, s in zip(obj.center, region.center, region.size, strict=True))


def test_spark_dsg_binary_from_to_binary_and_sparkdsg_file(tmp_path: Path) -> None:
    payload = hydra_binary()
    assert detect_format(payload) is SceneGraphFormat.SPARK_DSG_BINARY
    from_bytes = parse_scene_graph(payload)
    check_hydra_graph(from_bytes)
    assert from_bytes == parse_scene_graph(hydra_json_text())
    path = tmp_path / "hydra.sparkdsg"
    build_hydra_graph().save(str(path), include_mesh=False)
    assert path.read_bytes().startswith(hydra.SPARK_DSG_FILE_MAGIC)
    assert load_scene_graph_file(path) == from_bytes


@pytest.mark.parametrize("category", ["O", "p", "R", "a", "Z"])
def test_node_symbol_matches_spark_dsg(category: str) -> None:
    import spark_dsg as dsg

    symbol = dsg.NodeSymbol(category, 4242)
    assert hydra.node_symbol(symbol.value) == symbol.str()
    # Non-letter categories print as the whole integer (spark_dsg would print just the index).
    assert hydra.node_symbol(17) == "17"
    assert hydra.node_symbol((1 << 56) | 17) == str((1 << 56) | 17)


def test_spark_dsg_json_errors() -> None:
    document = json.loads(hydra_json_text())
    index = next(i for i, n in enumerate(document["nodes"]) if n["attributes"].get("name") == "mug")
    broken = copy.deepcopy(document)
    broken["nodes"][index]["attributes"]["bounding_box"]["world_P_center"][1] = math.nan
    raises_invalid(broken, f"nodes.{index}.attributes.bounding_box.world_P_center")
    broken = copy.deepcopy(document)
    broken["nodes"][index]["attributes"]["bounding_box"]["dimensions"] = [0.1, math.inf, 0.1]
    raises_invalid(broken, f"nodes.{index}.attributes.bounding_box.dimensions")
    broken = copy.deepcopy(document)
    broken["nodes"].append(copy.deepcopy(broken["nodes"][index]))
    raises_invalid(broken, f"nodes.{len(broken['nodes']) - 1}.id")
    broken = copy.deepcopy(document)
    broken["nodes"] = {"not": "a list"}
    raises_invalid(broken, "nodes")
    broken = copy.deepcopy(document)
    broken["edges"][0]["source"] = "R0"
    raises_invalid(broken, "edges.0.source")


def test_spark_dsg_binary_corrupt_and_truncated() -> None:
    payload = hydra_binary()
    for cut in (1, 5, 40, len(payload) // 2):
        error = raises_invalid(payload[:cut], None)
        assert "Spark-DSG" in str(error)
    error = raises_invalid(b"\xdd" + bytes(range(40)), None)
    assert "Spark-DSG" in str(error)


def test_binary_memory_bomb_is_contained() -> None:
    """One length field set to 2**26 makes spark_dsg resize a vector of strings to 2 GB before it
    notices the payload is short; the capped child turns that into an error instead."""
    payload = bytearray(hydra_binary())
    layer_count = struct.unpack_from("<I", payload, 1)[0]
    names_offset = 5 + 19 * layer_count  # a layer key: array tag+length, tagged int64, tagged uint32
    assert payload[names_offset] == 0xDD  # the list of attribute type names starts here
    struct.pack_into("<I", payload, names_offset + 1, 1 << 26)
    error = raises_invalid(bytes(payload), None)
    assert "memory allowance" in str(error)


def test_binary_decoder_crash_and_hang_are_contained(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hydra, "_DECODER_SCRIPT", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)")
    with pytest.raises(InvalidSceneGraph, match="crashed"):
        hydra.parse_spark_dsg_binary(hydra_binary())
    monkeypatch.setattr(hydra, "_DECODER_SCRIPT", "import time; time.sleep(30)")
    with pytest.raises(InvalidSceneGraph, match="longer than"):
        hydra.parse_spark_dsg_binary(hydra_binary(), timeout_s=0.5)


# --- region-grouped -------------------------------------------------------------------------------------


def test_region_grouped_paper_example() -> None:
    example = paper_example()
    assert detect_format(example) is SceneGraphFormat.REGION_GROUPED
    sg = parse_scene_graph(json.dumps(example))
    assert [(r.id, r.name) for r in sg.regions] == [("0", "Office"), ("1", "Lobby")]
    assert [o.id for o in sg.objects] == [str(i) for i in range(9)]
    for region_name, region in example.items():
        for key, entry in region["objects"].items():
            obj = sg.object(key)
            assert obj.label == entry["semantics"]
            assert obj.attributes == {"raw_label": entry["raw_label"]}
            assert obj.center == entry["center"]
            assert obj.region_id == str(region["region_id"])
            # Derived size: a cube with the given volume.
            assert obj.size == pytest.approx([entry["volume"] ** (1 / 3)] * 3)
            assert math.prod(obj.size) == pytest.approx(entry["volume"])
        # The region box is the box around its objects' cubes (computed here the slow way).
        region = next(r for r in sg.regions if r.name == region_name)
        cubes = [(e["center"], e["volume"] ** (1 / 3)) for e in region_objects(example, region_name)]
        low = [min(c[a] - s / 2 for c, s in cubes) for a in range(3)]
        high = [max(c[a] + s / 2 for c, s in cubes) for a in range(3)]
        assert region.center == pytest.approx([(lo + hi) / 2 for lo, hi in zip(low, high, strict=True)])
        assert region.size == pytest.approx([hi - lo for lo, hi in zip(low, high, strict=True)])


def region_objects(example: dict[str, Any], name: str) -> list[dict[str, Any]]:
    return list(example[name]["objects"].values())


def test_region_grouped_size_yaw_extra_keys_and_unassigned() -> None:
    data = {
        "Kitchen": {
            "objects": {
                "k": {
                    "semantics": "table",
                    "center": [1, 2, 0.4],
                    "size": [2, 1, 0.8],
                    "yaw": 0.3,
                    "color": "red",
                },
                "x": {"raw_label": "old lamp", "center": [0, 0, 1], "volume": 0.008, "object_id": 12},
            },
            "region_id": 5,
        },
        "Unassigned": {
            "objects": {"u": {"semantics": "box", "center": [9, 9, 0], "volume": 1.0}},
            "region_id": -1,
        },
        "Empty": {"objects": {}, "region_id": 6},
    }
    sg = parse_region_grouped(data)
    assert [r.id for r in sg.regions] == ["5"]  # "Empty" has no geometry and is dropped
    table, lamp, box = sg.objects
    assert (table.id, table.size, table.yaw, table.attributes) == ("k", [2, 1, 0.8], 0.3, {"color": "red"})
    assert (lamp.id, lamp.label, lamp.attributes["raw_label"]) == ("12", "old lamp", "old lamp")
    assert lamp.size == pytest.approx([0.2, 0.2, 0.2])
    assert (box.id, box.region_id) == ("u", None)


def test_to_region_grouped_round_trip_and_integer_ids() -> None:
    sg = SceneGraph.model_validate(
        {
            "regions": [
                {"id": "3", "name": "Office", "center": [0, 0, 1], "size": [4, 4, 2]},
                {"id": "kitchen", "name": "Office", "center": [5, 0, 1], "size": [3, 3, 2]},
                {"id": "007", "name": "", "center": [9, 0, 1], "size": [2, 2, 2]},
            ],
            "objects": [
                {
                    "id": "d",
                    "label": "desk",
                    "center": [0, 0, 0.4],
                    "size": [1.5, 0.8, 0.8],
                    "yaw": 0.2,
                    "region_id": "3",
                    "attributes": {"raw_label": "wooden desk"},
                },
                {
                    "id": "f",
                    "label": "fridge",
                    "center": [5, 0, 0.9],
                    "size": [0.7, 0.7, 1.8],
                    "region_id": "kitchen",
                },
                {"id": "c", "label": "cup", "center": [20, 0, 0], "size": [0.1, 0.1, 0.1]},
            ],
        }
    )
    assert region_integer_ids(sg) == {"3": 3, "kitchen": 4, "007": 5}
    grouped = to_region_grouped(sg)
    assert list(grouped) == ["Office", "Office (2)", "region 007", "Unassigned"]
    assert [g["region_id"] for g in grouped.values()] == [3, 4, 5, -1]
    assert grouped["Office"]["objects"]["d"] == {
        "semantics": "desk",
        "raw_label": "wooden desk",
        "center": [0, 0, 0.4],
        "volume": pytest.approx(1.5 * 0.8 * 0.8),
        "object_id": "d",
    }
    assert grouped["region 007"]["objects"] == {}
    assert grouped["Unassigned"]["objects"]["c"]["raw_label"] == "cup"

    back = parse_scene_graph(json.dumps(to_region_grouped(sg, include_geometry=True)))
    for original in sg.objects:
        restored = back.object(original.id)
        assert (restored.label, restored.center, restored.size) == (
            original.label,
            original.center,
            original.size,
        )
        assert restored.yaw == pytest.approx(original.yaw)
        expected_region = (
            None if original.region_id is None else str(region_integer_ids(sg)[original.region_id])
        )
        assert restored.region_id == expected_region


# --- VLA-3D -------------------------------------------------------------------------------------------


def csv_rows(name: str) -> list[dict[str, str]]:
    with (VLA3D_DIR / name).open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def test_vla3d_example_scene_field_by_field() -> None:
    sg = load_vla3d_scene(VLA3D_DIR)
    graph_json = json.loads((VLA3D_DIR / f"{SCENE}_scene_graph.json").read_text(encoding="utf-8"))
    expected_ids = {o["object_id"] for r in graph_json["regions"].values() for o in r["objects"]}
    assert len(sg.objects) == 59
    assert {o.id for o in sg.objects} == expected_ids

    (region,) = sg.regions
    (region_row,) = csv_rows(f"{SCENE}_region_result.csv")
    assert (region.id, region.name) == ("0", "Office")
    assert region.center == [float(region_row[f"region_bbox_c{a}"]) for a in "xyz"]
    assert region.size == pytest.approx([float(region_row[f"region_bbox_{a}length"]) for a in "xyz"])

    rows = {row["object_id"]: row for row in csv_rows(f"{SCENE}_object_result.csv")}
    for obj in sg.objects:
        row = rows[obj.id]
        assert obj.label == row["nyu_label"]
        assert obj.center == [float(row[f"object_bbox_c{a}"]) for a in "xyz"]
        assert obj.size == [float(row[f"object_bbox_{a}length"]) for a in "xyz"]
        assert obj.yaw == float(row["object_bbox_heading"])
        assert obj.region_id == "0"
        assert obj.attributes["raw_label"] == row["raw_label"]
        assert obj.attributes["nyu40_label"] == row["nyu40_label"]
    bin_18 = sg.object("18")
    assert (bin_18.label, bin_18.attributes["raw_label"]) == ("garbage bin", "trash can")
    assert bin_18.attributes["colors"][0] == {
        "name": "navy",
        "rgb": [25, 25, 112],
        "fraction": pytest.approx(0.5328185328185329),
        "average_distance": pytest.approx(12.002155770570225),
    }
    assert sg.object("35").attributes["colors"] == [  # a short row: colours 2 and 3 missing
        {
            "name": "brown",
            "rgb": [139, 69, 19],
            "fraction": pytest.approx(0.9965457685664939),
            "average_distance": pytest.approx(12.634410998461547),
        }
    ]
    assert sg.object("2").attributes["front_heading"] == pytest.approx(-0.7057644886752646)
    assert sg.object("0").attributes["front_heading"] is None


def test_vla3d_unknown_objects_and_region_fallbacks() -> None:
    payload = vla3d_payload()
    with_unknown = parse_vla3d(
        payload["object_result_csv"], payload["region_result_csv"], include_unknown=True
    )
    assert len(with_unknown.objects) == 61
    assert with_unknown.object("55").label == "unknown"

    graph_json = json.loads((VLA3D_DIR / f"{SCENE}_scene_graph.json").read_text(encoding="utf-8"))
    from_graph = parse_vla3d(payload["object_result_csv"], scene_graph=graph_json)
    (region,) = from_graph.regions
    corners = graph_json["regions"]["0"]["region_bbox"]
    assert (region.id, region.name) == ("0", "Office")
    assert region.center == pytest.approx(
        [(min(c[a] for c in corners) + max(c[a] for c in corners)) / 2 for a in range(3)]
    )
    assert region.size == pytest.approx(
        [max(c[a] for c in corners) - min(c[a] for c in corners) for a in range(3)]
    )

    spanning = parse_vla3d(payload["object_result_csv"])
    (region,) = spanning.regions
    low, high = spanning.bounds()  # only objects lie inside the region, so they span the same box
    assert (region.id, region.name) == ("0", "region 0")
    assert region.center == pytest.approx(list((low + high) / 2))
    assert region.size == pytest.approx(list(high - low))


def test_vla3d_folders_files_and_detection(tmp_path: Path) -> None:
    root = tmp_path / "VLA-3D"
    shutil.copytree(VLA3D_DIR, root / "Scannet" / SCENE)
    other = root / "Matterport" / "house_1"
    other.mkdir(parents=True)
    (other / "house_1_object_result.csv").write_text(
        "object_id,region_id,raw_label,nyu_label,object_bbox_cx,object_bbox_cy,object_bbox_cz,"
        "object_bbox_xlength,object_bbox_ylength,object_bbox_zlength,object_bbox_heading\n"
        "7,_,sofa,sofa,1,2,0.4,2,1,0.8,0.5\n",
        encoding="utf-8",
    )
    assert list_vla3d_scenes(root) == ["house_1", SCENE]
    house = load_vla3d_scene(root, "house_1")
    assert (house.regions, house.object("7").region_id, house.object("7").yaw) == ([], None, 0.5)
    assert len(load_vla3d_scene(root, SCENE).objects) == 59
    with pytest.raises(InvalidSceneGraph, match="2 VLA-3D scenes"):
        load_vla3d_scene(root)
    with pytest.raises(InvalidSceneGraph, match="exactly one"):
        load_vla3d_scene(root, "scene9999_00")
    for path in (root / "Scannet" / SCENE, root / "Scannet" / SCENE / f"{SCENE}_scene_graph.json"):
        assert len(load_scene_graph_file(path).objects) == 59
    payload = vla3d_payload()
    assert detect_format(payload) is SceneGraphFormat.VLA3D
    assert parse_scene_graph(json.dumps(payload).encode()) == load_vla3d_scene(VLA3D_DIR)


def test_vla3d_scene_graph_json_is_read_only_without_the_region_csv(tmp_path: Path) -> None:
    scene = tmp_path / SCENE
    shutil.copytree(VLA3D_DIR, scene)
    graph_json = scene / f"{SCENE}_scene_graph.json"
    graph_json.write_text("{not json", encoding="utf-8")
    assert load_vla3d_scene(scene) == load_vla3d_scene(VLA3D_DIR)
    (scene / f"{SCENE}_region_result.csv").unlink()
    with pytest.raises(InvalidSceneGraph, match="not valid JSON"):
        load_vla3d_scene(scene)


# --- detection, native, and the error paths of every format -------------------------------------------


def test_detection_of_each_format() -> None:
    assert detect_format(native_example()) is SceneGraphFormat.NATIVE
    assert detect_format(json.dumps(native_example()).encode()) is SceneGraphFormat.NATIVE
    assert detect_format(paper_example()) is SceneGraphFormat.REGION_GROUPED
    assert detect_format({"objects": {"objects": {}, "region_id": 0}}) is SceneGraphFormat.REGION_GROUPED
    assert detect_format(vla3d_payload()) is SceneGraphFormat.VLA3D
    assert detect_format(b"\x00\x01binary") is SceneGraphFormat.SPARK_DSG_BINARY
    sg = parse_scene_graph(native_example())
    assert sg == SceneGraph.model_validate(native_example())
    with pytest.raises(InvalidSceneGraph, match="unrecognised"):
        detect_format({"rooms": []})
    # An explicit format is taken at its word.
    raises_invalid(paper_example(), "Lobby", fmt="vla3d")
    raises_invalid(paper_example(), "format", fmt="hydra")


def test_a_native_graph_needs_none_of_its_optional_fields() -> None:
    """ "objects" is optional in a native graph (the spec says so), so its other fields mark it too."""
    regions_only = {"frame_id": "map", "regions": [native_example()["regions"][0]]}
    for graph in (regions_only, {"frame_id": "odom"}, {"regions": []}):
        assert detect_format(graph) is SceneGraphFormat.NATIVE
        assert parse_scene_graph(graph) == SceneGraph.model_validate(graph)
    # Region-grouped maps whose rooms bear those names hold dicts, never a list or a string.
    assert detect_format({"regions": {"objects": {}, "region_id": 0}}) is SceneGraphFormat.REGION_GROUPED
    assert detect_format({"frame_id": {"objects": {}, "region_id": 0}}) is SceneGraphFormat.REGION_GROUPED


def with_change(base: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A deep copy of `base` with the value at dotted `path` replaced (or deleted when value is ...)."""
    data = copy.deepcopy(base)
    *parents, last = path.split(".")
    node: Any = data
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    key: Any = int(last) if isinstance(node, list) else last
    if value is ...:
        del node[key]
    else:
        node[key] = value
    return data


def csv_with(text: str, row: int, column: str, value: str) -> str:
    lines = text.splitlines()
    header = lines[0].split(",")
    cells = lines[row + 1].split(",")
    cells[header.index(column)] = value
    lines[row + 1] = ",".join(cells)
    return "\n".join(lines) + "\n"


def vla3d_with(row: int, column: str, value: str) -> dict[str, Any]:
    payload = vla3d_payload()
    payload["object_result_csv"] = csv_with(payload["object_result_csv"], row, column, value)
    return payload


ERROR_CASES = {
    "native NaN center": (with_change(native_example(), "objects.1.center.2", math.nan), "objects.1.center"),
    "native inf size": (with_change(native_example(), "objects.0.size.0", math.inf), "objects.0.size"),
    "native zero size": (with_change(native_example(), "objects.0.size.1", 0.0), "objects.0.size"),
    "native negative size": (with_change(native_example(), "objects.1.size.2", -0.1), "objects.1.size"),
    "native string size": (with_change(native_example(), "objects.1.size", "big"), "objects.1.size"),
    "native duplicate ids": (with_change(native_example(), "objects.1.id", "a"), "objects"),
    "native unknown region": (
        with_change(native_example(), "objects.1.region_id", "r9"),
        "objects.1.region_id",
    ),
    "native label type": (with_change(native_example(), "objects.0.label", 7), "objects.0.label"),
    "grouped zero volume": (
        with_change(paper_example(), "Office.objects.2.volume", 0.0),
        "Office.objects.2.volume",
    ),
    "grouped negative volume": (
        with_change(paper_example(), "Lobby.objects.7.volume", -1.0),
        "Lobby.objects.7.volume",
    ),
    "grouped NaN volume": (
        with_change(paper_example(), "Lobby.objects.8.volume", math.nan),
        "Lobby.objects.8.volume",
    ),
    "grouped inf center": (
        with_change(paper_example(), "Office.objects.3.center.0", -math.inf),
        "Office.objects.3.center",
    ),
    "grouped zero size": (
        with_change(paper_example(), "Office.objects.4.size", [1.0, 0.0, 1.0]),
        "Office.objects.4.size",
    ),
    "grouped center type": (
        with_change(paper_example(), "Office.objects.0.center", "here"),
        "Office.objects.0.center",
    ),
    "grouped missing volume": (
        with_change(paper_example(), "Office.objects.1.volume", ...),
        "Office.objects.1.volume",
    ),
    "grouped duplicate object id": (
        with_change(paper_example(), "Lobby.objects.6.object_id", "2"),
        "Lobby.objects.6.object_id",
    ),
    "grouped duplicate region id": (with_change(paper_example(), "Lobby.region_id", 0), "Lobby.region_id"),
    "grouped region id type": (with_change(paper_example(), "Lobby.region_id", "one"), "Lobby.region_id"),
    "grouped objects type": (with_change(paper_example(), "Lobby.objects", [1, 2]), "Lobby.objects"),
    "vla3d negative length": (
        vla3d_with(3, "object_bbox_ylength", "-0.2"),
        "object_result_csv.3.object_bbox_ylength",
    ),
    "vla3d zero length": (
        vla3d_with(0, "object_bbox_zlength", "0"),
        "object_result_csv.0.object_bbox_zlength",
    ),
    "vla3d nan center": (vla3d_with(5, "object_bbox_cx", "nan"), "object_result_csv.5.object_bbox_cx"),
    "vla3d text center": (vla3d_with(5, "object_bbox_cy", "left"), "object_result_csv.5.object_bbox_cy"),
    "vla3d missing center": (vla3d_with(2, "object_bbox_cz", "_"), "object_result_csv.2.object_bbox_cz"),
    "vla3d duplicate id": (vla3d_with(4, "object_id", "1"), "object_result_csv.4.object_id"),
    "vla3d unknown region": (vla3d_with(6, "region_id", "3"), "object_result_csv.6.region_id"),
    "vla3d region zero length": (
        {
            **vla3d_payload(),
            "region_result_csv": csv_with(
                vla3d_payload()["region_result_csv"], 0, "region_bbox_xlength", "0"
            ),
        },
        "region_result_csv.0.region_bbox_xlength",
    ),
    "vla3d missing column": (
        {
            "object_result_csv": vla3d_payload()["object_result_csv"].replace(
                "object_bbox_cy,", "object_bbox_y,", 1
            )
        },
        "object_result_csv.object_bbox_cy",
    ),
    "vla3d csv type": ({"object_result_csv": 12}, "object_result_csv"),
    "vla3d extra key": ({**vla3d_payload(), "statements": {}}, "statements"),
}


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_invalid_inputs_name_the_field(case: str) -> None:
    payload, field = ERROR_CASES[case]
    error = raises_invalid(payload, field)
    assert str(error).startswith(f"{field}: ")


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        "   ",
        "not json",
        "{'single': 'quotes'}",
        "[1, 2]",
        "[" * 100_000,
        b"\xff\xfe\x00garbage",
        "1" * 5000,
    ],
    ids=["empty bytes", "blank", "text", "python repr", "array", "deep nesting", "non-utf8", "huge number"],
)
def test_non_json_payloads(payload: str | bytes) -> None:
    raises_invalid(payload, None)


def test_max_objects_for_every_format() -> None:
    cases: list[tuple[dict[str, Any] | str | bytes, int]] = [
        (native_example(), 2),
        (paper_example(), 9),
        (vla3d_payload(), 59),
        (hydra_json_text(), 4),
        (hydra_binary(), 4),
    ]
    for payload, count in cases:
        assert len(parse_scene_graph(payload, max_objects=count).objects) == count
        with pytest.raises(LimitExceeded) as info:
            parse_scene_graph(payload, max_objects=count - 1)
        assert info.value.limit_name == "max_objects"


# --- fuzzing: any input gives a SceneGraph, InvalidSceneGraph or LimitExceeded --------------------------

JSON_LEAVES = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
)
JSON_VALUES = st.recursive(
    JSON_LEAVES,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


def small_vla3d_payload() -> dict[str, Any]:
    lines = vla3d_payload()["object_result_csv"].splitlines()
    return {**vla3d_payload(), "object_result_csv": "\n".join(lines[:4]) + "\n"}


def small_spark_json() -> dict[str, Any]:
    return json.loads(hydra_json_text())


def paths_in(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    paths = [prefix]
    if isinstance(value, dict):
        for key, child in value.items():
            paths.extend(paths_in(child, (*prefix, key)))
    elif isinstance(value, list):
        for index, child in enumerate(value):
            paths.extend(paths_in(child, (*prefix, index)))
    return paths


@st.composite
def mutated_documents(draw: st.DrawFn) -> dict[str, Any]:
    """A valid document of some format with 1-3 sub-values replaced by arbitrary JSON or deleted."""
    document = copy.deepcopy(
        draw(st.sampled_from([native_example(), paper_example(), small_vla3d_payload(), small_spark_json()]))
    )
    for _ in range(draw(st.integers(1, 3))):
        paths = paths_in(document)[1:]
        if not paths:  # everything was deleted
            break
        path = draw(st.sampled_from(paths))
        parent: Any = document
        for part in path[:-1]:
            parent = parent[part]
        if draw(st.booleans()) and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = draw(JSON_VALUES)
    return document


@st.composite
def mutated_bytes(draw: st.DrawFn) -> bytes:
    """Valid JSON text or Spark-DSG binary with bytes overwritten, inserted or cut off."""
    base = draw(
        st.sampled_from(
            [
                json.dumps(paper_example()).encode(),
                json.dumps(small_vla3d_payload()).encode(),
                hydra_binary(),
            ]
        )
    )
    data = bytearray(base)
    for _ in range(draw(st.integers(1, 4))):
        position = draw(st.integers(0, len(data) - 1))
        action = draw(st.sampled_from(["overwrite", "insert", "truncate"]))
        if action == "overwrite":
            data[position] = draw(st.integers(0, 255))
        elif action == "insert":
            data[position:position] = draw(st.binary(min_size=1, max_size=4))
        else:
            del data[max(position, 1) :]
    return bytes(data)


@settings(max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    payload=st.one_of(
        st.binary(max_size=200),
        st.text(max_size=200),
        JSON_VALUES.map(json.dumps),
        mutated_documents(),
        mutated_bytes(),
    )
)
def test_fuzz_only_scene_graphs_or_domain_errors(payload: Any) -> None:
    try:
        result = parse_scene_graph(payload, max_objects=10)
    except LimitExceeded as exc:
        assert exc.limit_name == "max_objects"
    except InvalidSceneGraph as exc:
        assert INTERNAL_ERROR_MESSAGE not in str(exc), "a reader raised something unexpected"
    else:
        assert isinstance(result, SceneGraph)
        assert len(result.objects) <= 10  # the limit holds for what is returned, not only for what raises
