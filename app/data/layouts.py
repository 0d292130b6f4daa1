"""Layouts read for the case builder and the simulator: ScanNet scans, AI2-THOR rooms and synthetic rooms,
normalised.

* ScanNet (`scannet_train_scenes.jsonl`): axis-aligned boxes and labels; on/in will come from the boxes.
* AI2-THOR (`ai2thor_scenes.jsonl`): CamelCase object types become words ("DiningTable" -> "dining table",
  the type kept as the raw label); `parent_receptacles` give the real on/in placements, mapped to "on" or
  "in" by receptacle type (`THOR_RECEPTACLE_RELATION`). "On the floor" placements are dropped (the floor is
  never an anchor). A parent id missing from the scene falls back to its base object when the id names a
  part ("Sink|...|SinkBasin" -> "Sink|..."), else the placement is skipped; both are counted in the notes.
* Synthetic rooms (`vlmap data synth`, `app.data.synthetic`): the scans' format, each named by its type.

Which objects a case may ask about: `is_grounding_target` (any object but the room's shell, the builder's
default) or `is_target_candidate` (small or medium movable-looking objects: the simulator's searches and the
builder's `--small-targets-only`).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import InvalidInput
from app.grounding.box_relations import is_room_shell, is_structure, label_set
from app.grounding.relations import Relation
from app.scene_graph.model import Region, SceneObject

# Boxes thinner than this (two AI2-THOR objects have a zero side) are widened to it.
MIN_SIZE = 0.01
# Targets are small or medium: footprint sides and height at most these (metres).
TARGET_MAX_SIDE = 1.5
TARGET_MAX_HEIGHT = 2.0
# A ScanNet object counts as portable ("I left my ...") when no side exceeds this.
PORTABLE_MAX_SIDE = 0.6

# Built-in fixtures and parts of furniture: real objects, and fine anchors, but not what people look for.
FIXTURES = label_set(
    "kitchen cabinets, kitchen cabinet, cabinet, cabinets, bathroom cabinet, counter, kitchen counter, "
    "countertop, bathroom vanity, shower, bathtub, bathtub basin, sink, sink basin, toilet, radiator, "
    "whiteboard, blackboard, bulletin board, board, closet, wardrobe closet, refrigerator, fridge, "
    "stove, oven, range hood, dishwasher, shower curtain rod, closet rod, fireplace, drawer, shelf, "
    "stove burner, stove knob, faucet, shower head, towel holder, hand towel holder, "
    "toilet paper hanger, light switch, bathroom stall, mailboxes, water heater, washing machine, "
    "clothes dryer, bar, ledge, windowsill"
)

# How an AI2-THOR receptacle holds what it carries. Types absent from the table default to "on".
_THOR_CONTAINING = (
    "Fridge Cabinet Drawer Microwave Box GarbageCan BathtubBasin SinkBasin Safe LaundryHamper Pot Pan Bowl "
    "Cup Mug Kettle CoffeeMachine Toaster"
)
_THOR_SUPPORTING = (
    "CounterTop DiningTable CoffeeTable SideTable Desk Shelf ShelvingUnit Dresser Bed Sofa ArmChair Chair "
    "Stool Ottoman Footstool TVStand Toilet TowelHolder HandTowelHolder ToiletPaperHanger StoveBurner Plate "
    "DogBed Sink Bathtub"
)
THOR_RECEPTACLE_RELATION: dict[str, Relation] = {
    **dict.fromkeys(_THOR_CONTAINING.split(" "), Relation.IN),
    **dict.fromkeys(_THOR_SUPPORTING.split(" "), Relation.ON),
}
THOR_ROOM_NAMES = {
    "kitchens": "kitchen",
    "living_rooms": "living room",
    "bedrooms": "bedroom",
    "bathrooms": "bathroom",
    "robothor": "apartment",
}
# Compound words that CamelCase splitting would tear apart.
_THOR_LABEL_OVERRIDES = {
    "CounterTop": "countertop",
    "BasketBall": "basketball",
    "KeyChain": "keychain",
    "TableTopDecor": "tabletop decor",
    "ArmChair": "armchair",
}
_CAMEL_WORD = re.compile(r"[A-Z]+(?![a-z])|[A-Z][a-z]*|[a-z]+|\d+")
_SCANNET_ROOM = re.compile(r"^(scene\d{4})_\d{2}$")


def split_camel_case(object_type: str) -> str:
    """An AI2-THOR object type as words: "DiningTable" -> "dining table", "TVStand" -> "tv stand"."""
    if object_type in _THOR_LABEL_OVERRIDES:
        return _THOR_LABEL_OVERRIDES[object_type]
    return " ".join(w.lower() for w in _CAMEL_WORD.findall(object_type))


def thor_placement_relation(receptacle_type: str) -> Relation:
    """IN for receptacles that enclose (Fridge, Drawer, SinkBasin, ...), ON for those that support."""
    return THOR_RECEPTACLE_RELATION.get(receptacle_type, Relation.ON)


def room_key(source: str, scene_id: str) -> str:
    """The physical room of a scene: rescans "scene0010_00" and "scene0010_01" share "scannet/scene0010"."""
    match = _SCANNET_ROOM.match(scene_id) if source == "scannet" else None
    return f"{source}/{match.group(1) if match else scene_id}"


def is_grounding_target(label: str) -> bool:
    """Anything a person may ask about: every object but floors, ceilings, walls and generic labels (doors,
    windows, tables and beds as well as the small movable things)."""
    return not is_room_shell(label)


def is_target_candidate(label: str, size: Sequence[float]) -> bool:
    """Small or medium, movable-looking objects: no structure, no fixture, not too big."""
    text = label.strip().lower()
    if is_structure(text) or text in FIXTURES:
        return False
    return max(size[0], size[1]) <= TARGET_MAX_SIDE and size[2] <= TARGET_MAX_HEIGHT


@dataclass
class LayoutScene:
    """One real layout, normalised: objects in one region, known placements, the simulator's candidate
    targets (`is_target_candidate`)."""

    source: str
    scene_id: str
    region: Region
    objects: list[SceneObject]
    # target id -> {anchor id: ON or IN}; None where on/in must come from the boxes (ScanNet).
    placements: dict[str, dict[str, Relation]] | None
    portable: frozenset[str]
    targets: list[str]
    notes: Counter[str] = field(default_factory=Counter)
    # The source's room type ("kitchens"; "" for ScanNet) and, where it differs from `label`, the label as the
    # source file writes it (AI2-THOR's CamelCase types), by object id.
    room_type: str = ""
    raw_labels: dict[str, str] = field(default_factory=dict)


def _box_values(raw: dict[str, Any], where: str) -> tuple[list[float], list[float]]:
    try:
        center = [float(v) for v in raw["center"]]
        size = [max(float(v), MIN_SIZE) for v in raw["size"]]
    except (KeyError, TypeError, ValueError) as exc:
        msg = f"object without a usable center/size: {exc}"
        raise InvalidInput(msg, where) from exc
    if len(center) != 3 or len(size) != 3:
        msg = "center and size need three values"
        raise InvalidInput(msg, where)
    return center, size


def _extent_region(name: str, objects: Sequence[SceneObject]) -> Region:
    lo = np.min([o.min_corner for o in objects], axis=0)
    hi = np.max([o.max_corner for o in objects], axis=0)
    return Region(id="0", name=name, center=(0.5 * (lo + hi)).tolist(), size=(hi - lo).tolist())


def _read_jsonl(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    with path.open(encoding="utf-8") as fh:
        for number, line in enumerate(fh, start=1):
            if line.strip():
                yield number, json.loads(line)


def _read_boxes(path: str | Path, source: str) -> list[LayoutScene]:
    """Scenes of boxes and labels only (the scans' format); on/in will come from the boxes. A line's `room`,
    where given, names its region and type."""
    scenes = []
    for number, raw in _read_jsonl(Path(path)):
        objects = []
        for k, o in enumerate(raw["objects"]):
            center, size = _box_values(o, f"{path}:{number}:objects[{k}]")
            label = str(o["label"]).strip().lower()
            objects.append(SceneObject(id=str(o["id"]), label=label, center=center, size=size, region_id="0"))
        if not objects:
            continue
        portable = frozenset(
            o.id for o in objects if max(o.size) <= PORTABLE_MAX_SIDE and not is_structure(o.label)
        )
        room = str(raw.get("room", ""))
        scenes.append(
            LayoutScene(
                source=source,
                scene_id=str(raw["scene_id"]),
                region=_extent_region(room or "room", objects),
                objects=objects,
                placements=None,
                portable=portable,
                targets=[o.id for o in objects if is_target_candidate(o.label, o.size)],
                room_type=room,
            )
        )
    return scenes


def read_scannet(path: str | Path) -> list[LayoutScene]:
    """ScanNet scenes (`scannet_train_scenes.jsonl`): boxes only; on/in will come from the boxes."""
    return _read_boxes(path, "scannet")


def read_synthetic(path: str | Path) -> list[LayoutScene]:
    """Synthetic rooms (`vlmap data synth`, `app.data.synthetic`): boxes only, each region named by its room
    type; on/in will come from the boxes."""
    return _read_boxes(path, "synthetic")


def _thor_placements(
    raw_objects: list[dict[str, Any]], notes: Counter[str]
) -> dict[str, dict[str, Relation]]:
    types = {str(o["id"]): str(o["label"]) for o in raw_objects}
    placements: dict[str, dict[str, Relation]] = {}
    for o in raw_objects:
        found: dict[str, Relation] = {}
        for parent in o.get("parent_receptacles") or []:
            parent = str(parent)
            part = parent.rsplit("|", 1)[-1]
            if parent in types:
                anchor, kind = parent, types[parent]
            elif parent.count("|") >= 4 and part.isalpha() and parent.rsplit("|", 1)[0] in types:
                # "Sink|x|y|z|SinkBasin" without its basin object: the sink itself, held the basin's way.
                anchor, kind = parent.rsplit("|", 1)[0], part
                notes["placement_parent_resolved_to_base"] += 1
            else:
                notes["placement_parent_missing"] += 1
                continue
            if types[anchor] == "Floor":
                notes["placement_on_floor_dropped"] += 1
                continue
            found[anchor] = thor_placement_relation(kind)
        if found:
            placements[str(o["id"])] = found
    return placements


def read_ai2thor(path: str | Path) -> list[LayoutScene]:
    """AI2-THOR rooms (`ai2thor_scenes.jsonl`): CamelCase types become words; parents give on/in."""
    scenes = []
    for number, raw in _read_jsonl(Path(path)):
        room_type = str(raw.get("room_type", ""))
        notes: Counter[str] = Counter()
        objects = []
        for k, o in enumerate(raw["objects"]):
            center, size = _box_values(o, f"{path}:{number}:objects[{k}]")
            label = split_camel_case(str(o["label"]))
            objects.append(SceneObject(id=str(o["id"]), label=label, center=center, size=size, region_id="0"))
        if not objects:
            continue
        region_name = THOR_ROOM_NAMES.get(room_type, room_type.replace("_", " ").rstrip("s") or "room")
        scenes.append(
            LayoutScene(
                source="ai2thor",
                scene_id=str(raw["scene_id"]),
                region=_extent_region(region_name, objects),
                objects=objects,
                placements=_thor_placements(raw["objects"], notes),
                portable=frozenset(str(o["id"]) for o in raw["objects"] if o.get("pickupable")),
                targets=[o.id for o in objects if is_target_candidate(o.label, o.size)],
                notes=notes,
                room_type=room_type,
                raw_labels={str(o["id"]): str(o["label"]) for o in raw["objects"]},
            )
        )
    return scenes
