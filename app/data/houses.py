"""Maps a case is built on: one room, or a house of several rooms of one source.

A house joins HOUSE_MIN_ROOMS..HOUSE_MAX_ROOMS rooms the way a real house holds them: each room keeps its
layout (turned by a random quarter turn, so its boxes stay axis-aligned), rooms stand side by side in rows
on a floor at z = 0, separated by a gap of ROOM_GAP or touching (a shared wall, with probability
SHARED_WALL_PROBABILITY); with probability SECOND_FLOOR_PROBABILITY a house of three rooms or more puts
some of them on a second floor, FLOOR_HEIGHT above the first and always above its rooms' tops
(STOREY_CLEARANCE), so that no two rooms overlap. Every room is one `Region` (AI2-THOR and synthetic rooms
named by their type, ScanNet rooms "room 1", "room 2", ...: a name inferred from furniture would be wrong for
the scans of offices, classrooms and studios), every object's `region_id` names its room, and object ids are
prefixed by the room's index ("2:17") so that they stay unique. Relations are computed over the whole house
afterwards: its look-alikes (the chairs of every room), distances and z ranges are a real house's.

AI2-THOR houses take at most THOR_ROOM_LIMITS rooms of each type (one kitchen, one living room, ...); the
RoboTHOR apartments are whole apartments already and are not joined. ScanNet houses never hold two scans of
one room (`room_key`), and a house stops growing at HOUSE_MAX_OBJECTS objects.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.data.layouts import LayoutScene, room_key
from app.grounding.relations import Relation
from app.scene_graph.model import Region, SceneObject

HOUSE_MIN_ROOMS = 2
HOUSE_MAX_ROOMS = 6
HOUSE_MAX_OBJECTS = 250
SHARED_WALL_PROBABILITY = 0.3
ROOM_GAP = (0.05, 0.3)
# Row length of a floor's layout, as a multiple of the square root of its rooms' total footprint area.
ROW_LENGTH_FACTOR = (1.0, 1.6)
SECOND_FLOOR_PROBABILITY = 0.3
FLOOR_HEIGHT = (2.6, 3.4)
STOREY_CLEARANCE = 0.05
THOR_ROOM_LIMITS = {"kitchens": 1, "living_rooms": 1, "bedrooms": 3, "bathrooms": 2}


@dataclass
class MapLayout:
    """One map: its objects (clean boxes in the source frame), regions, and what is known about them."""

    source: str
    map_id: str
    scene_ids: tuple[str, ...]
    regions: list[Region]
    objects: list[SceneObject]
    # target id -> {anchor id: ON or IN}; None where on/in must come from the boxes (ScanNet).
    placements: dict[str, dict[str, Relation]] | None
    portable: frozenset[str]
    # object id -> the label as the source file writes it (AI2-THOR's CamelCase types).
    raw_labels: dict[str, str]
    # object id -> (scene id, object id in that scene): where each object comes from.
    origin: dict[str, tuple[str, str]]
    floors: int = 1

    @property
    def is_house(self) -> bool:
        return len(self.scene_ids) > 1


def room_map(scene: LayoutScene) -> MapLayout:
    """The map of one room, as the layout gives it (ids, frame and region unchanged)."""
    return MapLayout(
        source=scene.source,
        map_id=scene.scene_id,
        scene_ids=(scene.scene_id,),
        regions=[scene.region],
        objects=list(scene.objects),
        placements=scene.placements,
        portable=scene.portable,
        raw_labels=dict(scene.raw_labels),
        origin={o.id: (scene.scene_id, o.id) for o in scene.objects},
    )


def _quarter_turned(objects: Sequence[SceneObject], quarter_turns: int) -> tuple[np.ndarray, np.ndarray]:
    """Centres and sizes (N, 3) of the objects turned about z by quarter_turns x 90 degrees."""
    centres = np.array([o.center for o in objects], dtype=float)  # (N, 3)
    sizes = np.array([o.size for o in objects], dtype=float)  # (N, 3)
    for _ in range(quarter_turns % 4):
        centres[:, :2] = np.stack([-centres[:, 1], centres[:, 0]], axis=1)
        sizes[:, [0, 1]] = sizes[:, [1, 0]]
    return centres, sizes


def _row_layout(footprints: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Lower-left corners (R, 2) for rooms of footprint sizes (R, 2), in rows, without overlaps."""
    row_length = math.sqrt(float(np.sum(np.prod(footprints, axis=1)))) * rng.uniform(*ROW_LENGTH_FACTOR)
    corners = np.zeros_like(footprints)
    x = y = depth = 0.0

    def gap() -> float:
        return 0.0 if rng.random() < SHARED_WALL_PROBABILITY else float(rng.uniform(*ROOM_GAP))

    for k, (width, length) in enumerate(footprints.tolist()):
        if x > 0 and x + width > row_length:
            x, y, depth = 0.0, y + depth + gap(), 0.0
        corners[k] = (x, y)
        x += width + gap()
        depth = max(depth, length)
    return corners


def join_rooms(scenes: Sequence[LayoutScene], map_id: str, rng: np.random.Generator) -> MapLayout:
    """One house of the given rooms (at least two, of one source), laid out as the module docstring says."""
    if len(scenes) < 2 or len({s.source for s in scenes}) != 1:
        msg = "a house joins two rooms or more of one source"
        raise ValueError(msg)
    rooms = []
    for scene in scenes:
        centres, sizes = _quarter_turned(scene.objects, int(rng.integers(4)))
        lo = np.min(centres - 0.5 * sizes, axis=0)
        hi = np.max(centres + 0.5 * sizes, axis=0)
        rooms.append((scene, centres - lo, sizes, hi - lo))  # room corner at the origin, floor at z = 0
    upstairs = np.zeros(len(rooms), dtype=bool)
    if len(rooms) >= 3 and rng.random() < SECOND_FLOOR_PROBABILITY:
        upstairs[rng.permutation(len(rooms))[: int(rng.integers(1, len(rooms) // 2 + 1))]] = True
    ground_top = max(
        float(extent[2]) for (_, _, _, extent), up in zip(rooms, upstairs, strict=True) if not up
    )
    lowest = max(FLOOR_HEIGHT[0], ground_top + STOREY_CLEARANCE)
    if lowest > FLOOR_HEIGHT[1]:
        upstairs[:] = False  # the first floor's rooms are too tall for a second floor above them
    floor_z = float(rng.uniform(lowest, FLOOR_HEIGHT[1])) if upstairs.any() else 0.0
    offsets = np.zeros((len(rooms), 3))
    for storey in (False, True):
        members = np.flatnonzero(upstairs == storey)
        if members.size:
            footprints = np.array([rooms[k][3][:2] for k in members.tolist()])
            offsets[members, :2] = _row_layout(footprints, rng)
            offsets[members, 2] = floor_z if storey else 0.0
    regions, objects = [], []
    placements: dict[str, dict[str, Relation]] | None = None if scenes[0].placements is None else {}
    portable: set[str] = set()
    raw_labels: dict[str, str] = {}
    origin: dict[str, tuple[str, str]] = {}
    for k, ((scene, centres, sizes, extent), offset) in enumerate(zip(rooms, offsets, strict=True)):
        region_id = str(k)
        name = scene.region.name if scene.room_type else f"room {k + 1}"
        regions.append(
            Region(id=region_id, name=name, center=(offset + 0.5 * extent).tolist(), size=extent.tolist())
        )
        ids = {o.id: f"{k}:{o.id}" for o in scene.objects}
        # Coordinates to 0.1 mm, the layouts' precision: the relations are computed on exactly these boxes.
        for o, c, s in zip(scene.objects, np.round(centres + offset, 4), sizes, strict=True):
            update = {"id": ids[o.id], "center": c.tolist(), "size": s.tolist(), "region_id": region_id}
            objects.append(o.model_copy(update=update))
            origin[ids[o.id]] = (scene.scene_id, o.id)
        if placements is not None and scene.placements is not None:
            for target, found in scene.placements.items():
                placements[ids[target]] = {ids[a]: r for a, r in found.items() if a in ids}
        portable |= {ids[i] for i in scene.portable}
        raw_labels |= {ids[i]: label for i, label in scene.raw_labels.items()}
    return MapLayout(
        source=scenes[0].source,
        map_id=map_id,
        scene_ids=tuple(s.scene_id for s in scenes),
        regions=regions,
        objects=objects,
        placements=placements,
        portable=frozenset(portable),
        raw_labels=raw_labels,
        origin=origin,
        floors=2 if upstairs.any() else 1,
    )


def draw_houses(pool: Sequence[LayoutScene], count: int, rng: np.random.Generator) -> list[list[LayoutScene]]:
    """`count` houses' rooms drawn from `pool`: per house one source (in proportion to its rooms there),
    HOUSE_MIN_ROOMS..HOUSE_MAX_ROOMS rooms in random order, within the limits of the module docstring."""
    by_source: dict[str, list[LayoutScene]] = {}
    for scene in sorted(pool, key=lambda s: (s.source, s.scene_id)):
        if scene.source == "ai2thor" and scene.room_type not in THOR_ROOM_LIMITS:
            continue
        by_source.setdefault(scene.source, []).append(scene)
    sources = [s for s, rooms in sorted(by_source.items()) if len(rooms) >= HOUSE_MIN_ROOMS]
    if not sources or count <= 0:
        return []
    weights = np.array([len(by_source[s]) for s in sources], dtype=float)
    houses = []
    for _ in range(count):
        source = sources[int(rng.choice(len(sources), p=weights / weights.sum()))]
        rooms = by_source[source]
        wanted = int(rng.integers(HOUSE_MIN_ROOMS, HOUSE_MAX_ROOMS + 1))
        chosen: list[LayoutScene] = []
        keys: set[str] = set()
        types: Counter[str] = Counter()
        n_objects = 0
        for k in rng.permutation(len(rooms)).tolist():
            scene = rooms[k]
            key, kind = room_key(scene.source, scene.scene_id), scene.room_type
            if key in keys or (source == "ai2thor" and types[kind] >= THOR_ROOM_LIMITS[kind]):
                continue
            if n_objects + len(scene.objects) > HOUSE_MAX_OBJECTS and len(chosen) >= HOUSE_MIN_ROOMS:
                break
            chosen.append(scene)
            keys.add(key)
            types[kind] += 1
            n_objects += len(scene.objects)
            if len(chosen) == wanted:
                break
        if len(chosen) >= HOUSE_MIN_ROOMS:
            houses.append(chosen)
    return houses
