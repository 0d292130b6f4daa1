"""Synthetic rooms: a third source of layouts, drawn from broad furniture and room ranges.

A model trained on one source of maps learns that source's habits (AI2-THOR's small objects on counters,
ScanNet's partial scans of offices) as if they were what a relation means, and is overconfident on the
other source relation by relation (docs/models/lsm-calibration-experiments.md). These rooms follow neither:
their sizes, furniture counts, clutter and where things rest are drawn from wide ranges written from
common knowledge of furniture (no statistic of either dataset), so that the spread of a relation's
placements in training is wider than any one source's.

A room is a rectangle (floor at z = 0, axis-aligned boxes, like both real sources) of one type
(`ROOM_TYPES`): the floor, some of its walls, furniture on the floor (against a wall, free-standing, or
around a table), objects mounted on walls at any height, and small objects resting on furniture tops,
inside open furniture, or on the floor. Furniture footprints never overlap; a small object never
intersects another. On/in are left to the boxes, as for ScanNet. One room per line, in the scans' format
plus `room` (its type): `{"scene_id", "room", "up_axis", "units", "objects": [{"id", "label", "center",
"size"}]}`; `app.data.layouts.read_synthetic` reads it back.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from app.files import atomic_write

Range = tuple[float, float]
Placement = Literal["wall", "free", "mounted", "around"]

WALL_THICKNESS = 0.1
# Space kept between two floor footprints, and between a small object and the edge of what holds it.
FOOTPRINT_GAP = 0.05
EDGE_MARGIN = 0.02
PLACEMENT_TRIES = 40
# Where small objects rest: on a furniture top, inside open furniture, on the floor.
REST_WEIGHTS = {"top": 0.7, "inside": 0.15, "floor": 0.15}
# Each wall is kept with this probability (scans often miss some; AI2-THOR rooms often have none).
WALL_PROBABILITY = 0.6


@dataclass(frozen=True)
class Kind:
    """A kind of furniture or object: label, side ranges (along its wall, depth, height, metres), how it is
    placed, and whether things rest on it (`top`) or in it (`shelves`: its inside holds small objects)."""

    label: str
    width: Range
    depth: Range
    height: Range
    placement: Placement = "free"
    top: bool = False
    shelves: bool = False
    # Mounted objects: the height of their centre.
    mount_z: Range = (1.0, 1.8)


def _kinds(*kinds: Kind) -> dict[str, Kind]:
    return {k.label: k for k in kinds}


FURNITURE = _kinds(
    Kind("bed", (0.9, 2.0), (1.9, 2.2), (0.4, 0.7), "wall", top=True),
    Kind("nightstand", (0.4, 0.6), (0.35, 0.5), (0.45, 0.7), "wall", top=True),
    Kind("dresser", (0.8, 1.6), (0.4, 0.6), (0.7, 1.2), "wall", top=True),
    Kind("wardrobe", (0.8, 2.0), (0.5, 0.65), (1.8, 2.3), "wall", shelves=True),
    Kind("desk", (1.0, 1.8), (0.5, 0.8), (0.7, 0.78), "wall", top=True),
    Kind("table", (0.8, 2.4), (0.6, 1.2), (0.7, 0.78), "free", top=True),
    Kind("coffee table", (0.6, 1.3), (0.4, 0.8), (0.35, 0.5), "free", top=True),
    Kind("side table", (0.4, 0.6), (0.4, 0.6), (0.45, 0.65), "free", top=True),
    Kind("chair", (0.42, 0.6), (0.42, 0.6), (0.8, 1.05), "around"),
    Kind("office chair", (0.55, 0.7), (0.55, 0.7), (0.9, 1.2), "around"),
    Kind("stool", (0.3, 0.45), (0.3, 0.45), (0.45, 0.8), "around", top=True),
    Kind("sofa", (1.5, 2.6), (0.8, 1.0), (0.7, 0.95), "wall", shelves=True),
    Kind("armchair", (0.7, 1.0), (0.75, 1.0), (0.75, 1.0), "free", shelves=True),
    Kind("bookshelf", (0.6, 1.2), (0.25, 0.4), (1.0, 2.2), "wall", top=True, shelves=True),
    Kind("cabinet", (0.4, 1.2), (0.35, 0.6), (0.6, 1.0), "wall", top=True, shelves=True),
    Kind("kitchen counter", (1.2, 3.5), (0.6, 0.66), (0.86, 0.95), "wall", top=True),
    Kind("refrigerator", (0.6, 0.9), (0.6, 0.8), (1.5, 1.9), "wall", top=True),
    Kind("stove", (0.6, 0.76), (0.6, 0.66), (0.85, 0.95), "wall", top=True),
    Kind("toilet", (0.36, 0.45), (0.6, 0.75), (0.7, 0.85), "wall", top=True),
    Kind("bathtub", (1.4, 1.8), (0.7, 0.8), (0.5, 0.6), "wall", top=True),
    Kind("bathroom vanity", (0.6, 1.5), (0.45, 0.6), (0.8, 0.9), "wall", top=True),
    Kind("washing machine", (0.58, 0.62), (0.55, 0.65), (0.82, 0.88), "wall", top=True),
    Kind("tv stand", (1.0, 2.0), (0.35, 0.5), (0.4, 0.6), "wall", top=True),
    Kind("file cabinet", (0.4, 0.5), (0.5, 0.65), (0.7, 1.3), "wall", top=True),
    Kind("piano", (1.4, 1.55), (0.5, 0.65), (1.1, 1.3), "wall", top=True),
    Kind("lamp", (0.25, 0.5), (0.25, 0.5), (1.2, 1.8), "free"),
    Kind("plant", (0.3, 0.7), (0.3, 0.7), (0.4, 1.6), "free"),
    Kind("trash can", (0.25, 0.45), (0.25, 0.45), (0.3, 0.7), "free"),
    Kind("radiator", (0.6, 1.5), (0.08, 0.2), (0.5, 0.8), "wall", top=True),
    Kind("door", (0.75, 1.0), (0.05, 0.2), (1.95, 2.1), "wall"),
    Kind("whiteboard", (1.2, 2.4), (0.02, 0.1), (0.9, 1.2), "mounted", mount_z=(1.3, 1.7)),
    Kind("picture", (0.3, 1.2), (0.02, 0.06), (0.3, 0.9), "mounted", mount_z=(1.2, 1.9)),
    Kind("mirror", (0.4, 1.0), (0.02, 0.06), (0.5, 1.2), "mounted", mount_z=(1.2, 1.7)),
    Kind("window", (0.6, 2.0), (0.05, 0.25), (0.8, 1.6), "mounted", mount_z=(1.1, 1.8)),
    Kind("tv", (0.8, 1.6), (0.05, 0.15), (0.5, 0.95), "mounted", mount_z=(1.0, 1.7)),
    Kind("shelf", (0.5, 1.2), (0.18, 0.3), (0.03, 0.3), "mounted", top=True, mount_z=(0.9, 1.9)),
    Kind("clock", (0.2, 0.45), (0.03, 0.08), (0.2, 0.45), "mounted", mount_z=(1.6, 2.2)),
    Kind("coat rack", (0.4, 0.6), (0.4, 0.6), (1.6, 1.9), "free"),
)

SMALL_OBJECTS = _kinds(
    Kind("cup", (0.07, 0.1), (0.07, 0.1), (0.08, 0.14)),
    Kind("mug", (0.08, 0.12), (0.08, 0.1), (0.08, 0.12)),
    Kind("bottle", (0.06, 0.1), (0.06, 0.1), (0.18, 0.35)),
    Kind("book", (0.13, 0.25), (0.18, 0.3), (0.02, 0.06)),
    Kind("laptop", (0.3, 0.4), (0.2, 0.28), (0.02, 0.3)),
    Kind("keyboard", (0.35, 0.48), (0.12, 0.18), (0.02, 0.05)),
    Kind("monitor", (0.45, 0.7), (0.15, 0.25), (0.3, 0.5)),
    Kind("phone", (0.07, 0.09), (0.14, 0.17), (0.01, 0.02)),
    Kind("remote control", (0.04, 0.06), (0.15, 0.22), (0.02, 0.03)),
    Kind("bowl", (0.12, 0.25), (0.12, 0.25), (0.05, 0.12)),
    Kind("plate", (0.18, 0.3), (0.18, 0.3), (0.02, 0.04)),
    Kind("vase", (0.1, 0.25), (0.1, 0.25), (0.2, 0.5)),
    Kind("towel", (0.3, 0.6), (0.2, 0.4), (0.03, 0.15)),
    Kind("pillow", (0.35, 0.6), (0.35, 0.5), (0.1, 0.2)),
    Kind("shoes", (0.25, 0.35), (0.2, 0.3), (0.1, 0.15)),
    Kind("basket", (0.25, 0.5), (0.25, 0.4), (0.15, 0.4)),
    Kind("box", (0.15, 0.6), (0.15, 0.5), (0.1, 0.45)),
    Kind("backpack", (0.25, 0.35), (0.15, 0.25), (0.35, 0.5)),
    Kind("bag", (0.25, 0.5), (0.12, 0.25), (0.2, 0.45)),
    Kind("table lamp", (0.18, 0.4), (0.18, 0.4), (0.3, 0.65)),
    Kind("potted plant", (0.12, 0.3), (0.12, 0.3), (0.15, 0.5)),
    Kind("microwave", (0.45, 0.55), (0.3, 0.4), (0.26, 0.32)),
    Kind("toaster", (0.25, 0.3), (0.15, 0.2), (0.18, 0.22)),
    Kind("kettle", (0.15, 0.22), (0.15, 0.2), (0.2, 0.28)),
    Kind("paper towel roll", (0.12, 0.15), (0.12, 0.15), (0.25, 0.3)),
    Kind("soap dispenser", (0.06, 0.09), (0.06, 0.09), (0.15, 0.22)),
    Kind("toilet paper", (0.1, 0.12), (0.1, 0.12), (0.1, 0.12)),
    Kind("tissue box", (0.12, 0.25), (0.12, 0.14), (0.08, 0.14)),
    Kind("speaker", (0.12, 0.3), (0.12, 0.3), (0.15, 0.45)),
    Kind("alarm clock", (0.1, 0.2), (0.06, 0.1), (0.08, 0.15)),
    Kind("candle", (0.06, 0.12), (0.06, 0.12), (0.08, 0.25)),
    Kind("printer", (0.4, 0.55), (0.35, 0.5), (0.2, 0.35)),
    Kind("headphones", (0.15, 0.2), (0.08, 0.12), (0.18, 0.22)),
    Kind("tray", (0.3, 0.5), (0.25, 0.35), (0.02, 0.05)),
    Kind("game controller", (0.14, 0.17), (0.09, 0.11), (0.05, 0.07)),
    Kind("pot", (0.2, 0.32), (0.2, 0.32), (0.12, 0.25)),
    Kind("folder", (0.22, 0.33), (0.03, 0.3), (0.02, 0.3)),
)


@dataclass(frozen=True)
class RoomType:
    """A room type: footprint side ranges (metres), furniture counts (label -> (min, max)), the small
    objects it holds (labels) and their count range."""

    name: str
    sides: tuple[Range, Range]
    furniture: dict[str, tuple[int, int]]
    small: tuple[str, ...]
    clutter: tuple[int, int]


_KITCHEN_SMALL = (
    "cup",
    "mug",
    "bottle",
    "bowl",
    "plate",
    "kettle",
    "toaster",
    "microwave",
    "paper towel roll",
    "pot",
    "tray",
    "vase",
    "box",
)
_OFFICE_SMALL = (
    "cup",
    "mug",
    "bottle",
    "book",
    "laptop",
    "keyboard",
    "monitor",
    "phone",
    "printer",
    "folder",
    "headphones",
    "box",
    "backpack",
    "bag",
)
_LIVING_SMALL = (
    "cup",
    "mug",
    "book",
    "remote control",
    "vase",
    "pillow",
    "table lamp",
    "potted plant",
    "speaker",
    "game controller",
    "candle",
    "box",
    "basket",
    "bag",
    "tray",
)
_BEDROOM_SMALL = (
    "book",
    "pillow",
    "shoes",
    "table lamp",
    "alarm clock",
    "phone",
    "laptop",
    "bag",
    "backpack",
    "basket",
    "box",
    "towel",
    "cup",
)
_BATH_SMALL = ("towel", "soap dispenser", "toilet paper", "bottle", "basket", "tissue box", "candle", "cup")


ROOM_TYPES = (
    RoomType(
        "bedroom",
        ((2.8, 5.5), (2.8, 5.5)),
        {
            "bed": (1, 2),
            "nightstand": (0, 2),
            "dresser": (0, 1),
            "wardrobe": (0, 2),
            "desk": (0, 1),
            "chair": (0, 2),
            "lamp": (0, 1),
            "picture": (0, 3),
            "window": (0, 2),
            "door": (1, 2),
            "mirror": (0, 1),
            "trash can": (0, 1),
            "shelf": (0, 2),
            "radiator": (0, 1),
        },
        _BEDROOM_SMALL,
        (2, 18),
    ),
    RoomType(
        "living room",
        ((3.5, 8.0), (3.5, 7.0)),
        {
            "sofa": (1, 2),
            "armchair": (0, 3),
            "coffee table": (1, 2),
            "side table": (0, 3),
            "tv stand": (0, 1),
            "tv": (0, 1),
            "bookshelf": (0, 3),
            "lamp": (0, 3),
            "plant": (0, 4),
            "picture": (0, 4),
            "window": (0, 3),
            "door": (1, 2),
            "table": (0, 1),
            "chair": (0, 6),
            "piano": (0, 1),
            "cabinet": (0, 2),
            "shelf": (0, 3),
            "clock": (0, 1),
        },
        _LIVING_SMALL,
        (4, 30),
    ),
    RoomType(
        "kitchen",
        ((2.5, 6.0), (2.5, 5.0)),
        {
            "kitchen counter": (1, 3),
            "refrigerator": (1, 1),
            "stove": (0, 1),
            "cabinet": (0, 4),
            "table": (0, 1),
            "chair": (0, 4),
            "stool": (0, 3),
            "trash can": (1, 2),
            "window": (0, 2),
            "door": (1, 2),
            "shelf": (0, 2),
            "clock": (0, 1),
            "washing machine": (0, 1),
        },
        _KITCHEN_SMALL,
        (4, 28),
    ),
    RoomType(
        "office",
        ((2.5, 7.0), (2.5, 6.0)),
        {
            "desk": (1, 6),
            "office chair": (1, 6),
            "file cabinet": (0, 3),
            "bookshelf": (0, 3),
            "cabinet": (0, 2),
            "whiteboard": (0, 1),
            "trash can": (0, 3),
            "plant": (0, 2),
            "window": (0, 3),
            "door": (1, 2),
            "picture": (0, 2),
            "table": (0, 1),
            "chair": (0, 4),
            "coat rack": (0, 1),
            "shelf": (0, 3),
            "radiator": (0, 2),
        },
        _OFFICE_SMALL,
        (3, 30),
    ),
    RoomType(
        "conference room",
        ((4.0, 10.0), (3.5, 7.0)),
        {
            "table": (1, 3),
            "chair": (4, 16),
            "whiteboard": (0, 2),
            "tv": (0, 2),
            "cabinet": (0, 2),
            "trash can": (0, 2),
            "plant": (0, 2),
            "window": (0, 4),
            "door": (1, 2),
            "picture": (0, 2),
        },
        _OFFICE_SMALL,
        (0, 20),
    ),
    RoomType(
        "bathroom",
        ((1.6, 3.5), (1.8, 3.8)),
        {
            "toilet": (1, 1),
            "bathroom vanity": (1, 2),
            "bathtub": (0, 1),
            "mirror": (0, 2),
            "trash can": (0, 1),
            "cabinet": (0, 1),
            "door": (1, 1),
            "window": (0, 1),
            "shelf": (0, 2),
            "washing machine": (0, 1),
            "radiator": (0, 1),
        },
        _BATH_SMALL,
        (2, 14),
    ),
    RoomType(
        "dining room",
        ((3.0, 6.5), (3.0, 6.0)),
        {
            "table": (1, 2),
            "chair": (3, 10),
            "cabinet": (0, 2),
            "dresser": (0, 1),
            "picture": (0, 3),
            "window": (0, 3),
            "door": (1, 2),
            "plant": (0, 2),
            "lamp": (0, 2),
            "shelf": (0, 2),
        },
        _KITCHEN_SMALL + _LIVING_SMALL,
        (3, 26),
    ),
)


@dataclass
class _Box:
    label: str
    center: np.ndarray  # (3,)
    size: np.ndarray  # (3,)
    kind: Kind | None = None

    @property
    def lo(self) -> np.ndarray:
        return self.center - 0.5 * self.size

    @property
    def hi(self) -> np.ndarray:
        return self.center + 0.5 * self.size


def _overlaps(a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray, gap: float) -> bool:
    """Whether two boxes (any dimension) come closer than `gap` on every axis."""
    return bool(np.all(a_lo < b_hi + gap) and np.all(b_lo < a_hi + gap))


def _draw(rng: np.random.Generator, bounds: Range) -> float:
    return float(rng.uniform(*bounds))


class _Room:
    """One room being furnished: the floor's rectangle [0, sx] x [0, sy], what stands on it."""

    def __init__(self, rng: np.random.Generator, sx: float, sy: float, height: float) -> None:
        self.rng = rng
        self.sx, self.sy, self.height = sx, sy, height
        self.floor: list[_Box] = []  # furniture on the floor (footprints never overlap)
        self.mounted: list[_Box] = []
        self.small: list[_Box] = []

    def _footprint_free(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        return not any(_overlaps(lo[:2], hi[:2], b.lo[:2], b.hi[:2], FOOTPRINT_GAP) for b in self.floor)

    def _fits(self, center: np.ndarray, size: np.ndarray) -> bool:
        lo, hi = center - 0.5 * size, center + 0.5 * size
        inside = lo[0] >= 0 and lo[1] >= 0 and hi[0] <= self.sx and hi[1] <= self.sy
        return inside and self._footprint_free(lo, hi)

    def _against_wall(self, kind: Kind, width: float, depth: float, height: float, z: float) -> _Box | None:
        """A box with its back to a random wall (its width along the wall), at centre height z."""
        rng = self.rng
        for _ in range(PLACEMENT_TRIES):
            wall = int(rng.integers(4))
            along_x = wall in (0, 1)  # walls y = 0 and y = sy run along x
            size = np.array([width, depth, height]) if along_x else np.array([depth, width, height])
            length = self.sx if along_x else self.sy
            if width > length:
                continue
            t = rng.uniform(0.5 * width, length - 0.5 * width)
            off = 0.5 * depth + float(rng.uniform(0.0, 0.08))
            if wall == 0:
                xy = (t, off)
            elif wall == 1:
                xy = (t, self.sy - off)
            elif wall == 2:
                xy = (off, t)
            else:
                xy = (self.sx - off, t)
            center = np.array([xy[0], xy[1], z])
            if kind.placement == "mounted":
                box = _Box(kind.label, center, size, kind)
                clear = all(
                    not _overlaps(box.lo, box.hi, b.lo, b.hi, 0.02) for b in self.floor + self.mounted
                )
                if clear and box.hi[2] < self.height:
                    return box
            elif self._fits(center, size):
                return _Box(kind.label, center, size, kind)
        return None

    def _free(self, kind: Kind, size: np.ndarray) -> _Box | None:
        if np.any(size[:2] > [self.sx, self.sy]):
            return None
        for _ in range(PLACEMENT_TRIES):
            xy = self.rng.uniform(0.5 * size[:2], np.array([self.sx, self.sy]) - 0.5 * size[:2])
            center = np.array([xy[0], xy[1], 0.5 * size[2]])
            if self._fits(center, size):
                return _Box(kind.label, center, size, kind)
        return None

    def _around(self, kind: Kind, size: np.ndarray) -> _Box | None:
        """Beside a table or desk (any side, 0-0.35 m off its edge), else free-standing."""
        tables = [b for b in self.floor if b.label in ("table", "desk", "kitchen counter", "coffee table")]
        for _ in range(PLACEMENT_TRIES if tables else 0):
            table = tables[int(self.rng.integers(len(tables)))]
            axis = int(self.rng.integers(2))
            side = 1.0 if self.rng.random() < 0.5 else -1.0
            center = table.center.copy()
            center[axis] += side * (
                0.5 * table.size[axis] + 0.5 * size[axis] + float(self.rng.uniform(0.0, 0.35))
            )
            other = 1 - axis
            center[other] += float(self.rng.uniform(-0.5, 0.5)) * max(table.size[other] - size[other], 0.0)
            center[2] = 0.5 * size[2]
            if self._fits(center, size):
                return _Box(kind.label, center, size, kind)
        return self._free(kind, size)

    def furnish(self, kind: Kind) -> None:
        rng = self.rng
        width, depth, height = _draw(rng, kind.width), _draw(rng, kind.depth), _draw(rng, kind.height)
        box: _Box | None
        if kind.placement == "mounted":
            z = min(_draw(rng, kind.mount_z), self.height - 0.5 * height - 0.05)
            box = self._against_wall(kind, width, depth, height, z)
            if box is not None:
                self.mounted.append(box)
            return
        if kind.placement == "wall":
            box = self._against_wall(kind, width, depth, height, 0.5 * height)
        else:
            turn = rng.random() < 0.5
            size = np.array([depth, width, height]) if turn else np.array([width, depth, height])
            box = self._around(kind, size) if kind.placement == "around" else self._free(kind, size)
        if box is not None:
            self.floor.append(box)

    def _clear_of_small(self, box: _Box) -> bool:
        return all(not _overlaps(box.lo, box.hi, b.lo, b.hi, 0.0) for b in self.small)

    def place_small(self, kind: Kind) -> None:
        """On a furniture top, inside open furniture, or on the floor (`REST_WEIGHTS`), clear of others."""
        rng = self.rng
        size = np.array([_draw(rng, kind.width), _draw(rng, kind.depth), _draw(rng, kind.height)])
        if rng.random() < 0.5:
            size[:2] = size[1::-1]
        holders = {
            "top": [b for b in self.floor + self.mounted if b.kind is not None and b.kind.top],
            "inside": [b for b in self.floor if b.kind is not None and b.kind.shelves],
        }
        names, weights = zip(*REST_WEIGHTS.items(), strict=True)
        p = np.asarray(weights) / sum(weights)
        for _ in range(PLACEMENT_TRIES):
            rest = str(rng.choice(names, p=p))
            if rest == "floor":
                box = self._free(kind, size)
                if box is not None and self._clear_of_small(box):
                    self.small.append(box)
                    return
                continue
            options = holders[rest]
            if not options:
                continue
            holder = options[int(rng.integers(len(options)))]
            room = holder.size[:2] - size[:2] - 2 * EDGE_MARGIN
            if np.any(room < 0):
                continue
            xy = holder.lo[:2] + EDGE_MARGIN + 0.5 * size[:2] + rng.uniform(0.0, 1.0, 2) * room
            if rest == "top":
                z = holder.hi[2] + 0.5 * size[2]
            else:
                free = holder.size[2] - size[2] - 2 * EDGE_MARGIN
                if free < 0:
                    continue
                z = holder.lo[2] + EDGE_MARGIN + 0.5 * size[2] + float(rng.uniform(0.0, free))
            box = _Box(kind.label, np.array([xy[0], xy[1], z]), size, kind)
            if box.hi[2] < self.height and self._clear_of_small(box):
                self.small.append(box)
                return

    def shell(self) -> list[_Box]:
        """The floor slab and the walls kept (each with WALL_PROBABILITY)."""
        t, sx, sy, h = WALL_THICKNESS, self.sx, self.sy, self.height
        out = [_Box("floor", np.array([0.5 * sx, 0.5 * sy, -0.5 * t]), np.array([sx, sy, t]))]
        walls = (
            ((0.5 * sx, -0.5 * t), (sx, t)),
            ((0.5 * sx, sy + 0.5 * t), (sx, t)),
            ((-0.5 * t, 0.5 * sy), (t, sy)),
            ((sx + 0.5 * t, 0.5 * sy), (t, sy)),
        )
        for (cx, cy), (wx, wy) in walls:
            if self.rng.random() < WALL_PROBABILITY:
                out.append(_Box("wall", np.array([cx, cy, 0.5 * h]), np.array([wx, wy, h])))
        return out


def synthetic_room(rng: np.random.Generator, scene_id: str) -> dict[str, Any]:
    """One furnished room as a scans-format line (see the module docstring)."""
    room_type = ROOM_TYPES[int(rng.integers(len(ROOM_TYPES)))]
    (x_lo, x_hi), (y_lo, y_hi) = room_type.sides
    room = _Room(rng, _draw(rng, (x_lo, x_hi)), _draw(rng, (y_lo, y_hi)), _draw(rng, (2.4, 3.4)))
    # Big things first, so that what is placed later finds room around them.
    order = sorted(room_type.furniture.items(), key=lambda item: -FURNITURE[item[0]].width[1])
    for label, (lo, hi) in order:
        for _ in range(int(rng.integers(lo, hi + 1))):
            room.furnish(FURNITURE[label])
    for _ in range(int(rng.integers(room_type.clutter[0], room_type.clutter[1] + 1))):
        room.place_small(SMALL_OBJECTS[room_type.small[int(rng.integers(len(room_type.small)))]])
    boxes = room.shell() + room.floor + room.mounted + room.small
    objects = [
        {
            "id": str(k),
            "label": b.label,
            "center": np.round(b.center, 4).tolist(),
            "size": np.round(b.size, 4).tolist(),
        }
        for k, b in enumerate(boxes)
    ]
    return {"scene_id": scene_id, "room": room_type.name, "up_axis": "z", "units": "m", "objects": objects}


def synthetic_rooms(count: int, seed: int) -> Iterator[dict[str, Any]]:
    """`count` rooms, each drawn from its own seeded generator (room k is the same whatever `count`)."""
    for k in range(count):
        yield synthetic_room(np.random.default_rng([seed, k]), f"synthetic{k:05d}")


def write_synthetic_rooms(path: str | Path, count: int, seed: int) -> int:
    """Write `count` rooms (JSONL, replacing `path` once complete); returns how many objects they hold."""
    objects = 0
    with atomic_write(path) as fh:
        for room in synthetic_rooms(count, seed):
            objects += len(room["objects"])
            fh.write(json.dumps(room, separators=(",", ":")) + "\n")
    return objects
