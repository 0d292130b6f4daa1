"""Frames and reconstruction errors: the map a case shows is a moved, noisy, partial copy of the true layout.

Relations are computed once, from the clean boxes of the layout in its source frame, before any of this
(`app.data.build`). A rigid motion of the whole map leaves every relation true, so the truth of a moved
case is the truth of its layout; box noise and missing objects are what a real reconstruction does to a map
whose truth has not changed, so they are applied to the map only, never fed back into the relations. The
target's position is moved by the same motion without noise (it is where the object really is).

* Frame (`FrameMotion`): a turn about z by any yaw (continuous, or a multiple of 90 degrees), then a shift
  by any offset: x, y within +-`Shift.max_offset_xy`, z in `Shift.z_range` (the floor at any height).
  After a turn that is not a multiple of 90 degrees, a box is kept as a yawed box (`SceneObject.yaw`; its
  `half_extent` / `min_corner` bound the yawed box) or written as its axis-aligned bounding box with yaw 0,
  as a reconstruction in a non-aligned map frame would, chosen per case (`Shift.yawed_box_probability`).
  Regions, which have no yaw, are always written as the bounding box of the turned region.
* Box noise (`BoxNoise`), in the source frame before the motion: every centre coordinate moves by at most
  `center_jitter` (uniform), every side is scaled by a factor within 1 +- `size_noise` (uniform); both
  amplitudes are drawn per case from the `Shift`'s ranges.
* Missing objects: a fraction drawn per case from `Shift.drop_fraction` of the objects that are not the
  case's anchors is left out of the map.

Map coordinates are written to 0.1 mm (the precision of the source layouts), yaws to 1e-6 rad; the target's
box and the frame (`FrameMotion.to_json`) exactly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from app.scene_graph.model import Region, SceneObject

# Smallest side of a noisy box (metres): noise never flattens a box.
MIN_NOISY_SIZE = 0.01
COORD_DECIMALS = 4
YAW_DECIMALS = 6


@dataclass(frozen=True)
class Shift:
    """The distribution of frames and reconstruction errors of a split's cases."""

    continuous_yaw_probability: float
    yawed_box_probability: float
    max_offset_xy: float
    z_range: tuple[float, float]
    center_jitter: tuple[float, float]
    size_noise: tuple[float, float]
    drop_fraction: tuple[float, float]
    raw_label_probability: float


#: Training augmentations: every frame, light reconstruction errors ("a few cm", "5-10 %").
TRAIN_SHIFT = Shift(
    continuous_yaw_probability=0.6,
    yawed_box_probability=0.5,
    max_offset_xy=20.0,
    z_range=(-2.0, 5.0),
    center_jitter=(0.0, 0.05),
    size_noise=(0.05, 0.10),
    drop_fraction=(0.0, 0.2),
    raw_label_probability=0.25,
)
#: The calibration split: always a continuous yaw, heavier errors, raw labels more often.
CALIB_SHIFT = Shift(
    continuous_yaw_probability=1.0,
    yawed_box_probability=0.5,
    max_offset_xy=20.0,
    z_range=(-2.0, 5.0),
    center_jitter=(0.03, 0.08),
    size_noise=(0.10, 0.15),
    drop_fraction=(0.0, 0.2),
    raw_label_probability=0.5,
)


def without_yaw(shift: Shift) -> Shift:
    """The shift with quarter turns only (`--no-continuous-yaw`)."""
    return Shift(**{**shift.__dict__, "continuous_yaw_probability": 0.0})


def without_noise(shift: Shift) -> Shift:
    """The shift without box noise and missing objects (`--no-box-noise`)."""
    zero = (0.0, 0.0)
    return Shift(**{**shift.__dict__, "center_jitter": zero, "size_noise": zero, "drop_fraction": zero})


def without_raw_labels(shift: Shift) -> Shift:
    """The shift that keeps the layouts' own labels (`--no-raw-labels`)."""
    return Shift(**{**shift.__dict__, "raw_label_probability": 0.0})


@dataclass(frozen=True)
class FrameMotion:
    """Turn about z by `yaw` (radians), then shift by `offset`; boxes stay yawed or become their AABB."""

    yaw: float
    offset: tuple[float, float, float]
    yawed_boxes: bool

    @property
    def quarter_turns(self) -> int | None:
        """The yaw as a number of quarter turns, when it is one (boxes then stay exactly axis-aligned)."""
        k = self.yaw / (0.5 * math.pi)
        return round(k) % 4 if abs(k - round(k)) < 1e-9 else None

    def points(self, p: np.ndarray) -> np.ndarray:
        """Moved points (..., 3)."""
        p = np.asarray(p, dtype=float)
        quarters = self.quarter_turns
        if quarters is not None:
            x, y = p[..., 0], p[..., 1]
            for _ in range(quarters):
                x, y = -y, x
        else:
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            x, y = c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1]
        moved: np.ndarray = np.stack([x, y, p[..., 2]], axis=-1) + np.asarray(self.offset)
        return moved

    def boxes(
        self, centres: np.ndarray, sizes: np.ndarray, yaws: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moved boxes: centres (N, 3), sizes (N, 3), yaws (N,)."""
        moved = self.points(centres)
        quarters = self.quarter_turns
        if quarters is not None and not np.any(yaws):
            turned = sizes[:, [1, 0, 2]] if quarters % 2 else sizes
            return moved, turned.copy(), np.zeros(len(sizes))
        new_yaws = yaws + self.yaw
        if self.yawed_boxes:
            return moved, sizes.copy(), (new_yaws + math.pi) % (2.0 * math.pi) - math.pi
        c, s = np.abs(np.cos(new_yaws)), np.abs(np.sin(new_yaws))
        aabb = np.stack(
            [c * sizes[:, 0] + s * sizes[:, 1], s * sizes[:, 0] + c * sizes[:, 1], sizes[:, 2]], 1
        )
        return moved, aabb, np.zeros(len(sizes))

    def region(self, region: Region) -> Region:
        """The region's box moved, as the bounding box of the turned box (regions have no yaw)."""
        as_box = FrameMotion(self.yaw, self.offset, yawed_boxes=False)
        centre, size, _ = as_box.boxes(np.array([region.center]), np.array([region.size]), np.zeros(1))
        return region.model_copy(update={"center": _rounded(centre[0]), "size": _rounded(size[0])})

    def to_json(self) -> dict[str, object]:
        """The motion, exactly (so that a case's frame can be replayed on its layout)."""
        return {
            "yaw": self.yaw,
            "offset": list(self.offset),
            "boxes": "yawed" if self.yawed_boxes else "aabb",
        }


IDENTITY = FrameMotion(0.0, (0.0, 0.0, 0.0), yawed_boxes=False)


@dataclass(frozen=True)
class BoxNoise:
    """Per-box reconstruction error: centre jitter (metres, per axis) and relative size error (per side)."""

    center_jitter: float
    size_noise: float

    def apply(
        self, centres: np.ndarray, sizes: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noisy centres and sizes (N, 3) of the boxes (N, 3)."""
        jitter = rng.uniform(-self.center_jitter, self.center_jitter, size=centres.shape)
        scale = 1.0 + rng.uniform(-self.size_noise, self.size_noise, size=sizes.shape)
        return centres + jitter, np.maximum(sizes * scale, MIN_NOISY_SIZE)

    def to_json(self) -> dict[str, float]:
        return {"center_jitter": round(self.center_jitter, 4), "size_noise": round(self.size_noise, 4)}


NO_NOISE = BoxNoise(0.0, 0.0)


def random_motion(shift: Shift, rng: np.random.Generator) -> FrameMotion:
    """A frame drawn from the shift: continuous yaw or quarter turns, offset, floor height, box mode."""
    if rng.random() < shift.continuous_yaw_probability:
        yaw = float(rng.uniform(-math.pi, math.pi))
    else:
        yaw = 0.5 * math.pi * int(rng.integers(-1, 3))
    xy = rng.uniform(-shift.max_offset_xy, shift.max_offset_xy, size=2)
    z = float(rng.uniform(*shift.z_range))
    yawed = bool(rng.random() < shift.yawed_box_probability)
    return FrameMotion(yaw, (float(xy[0]), float(xy[1]), z), yawed_boxes=yawed)


def random_noise(shift: Shift, rng: np.random.Generator) -> BoxNoise:
    return BoxNoise(float(rng.uniform(*shift.center_jitter)), float(rng.uniform(*shift.size_noise)))


def _rounded(values: np.ndarray) -> list[float]:
    return [round(float(v), COORD_DECIMALS) for v in values]


def observed_objects(
    objects: Sequence[SceneObject],
    *,
    motion: FrameMotion,
    noise: BoxNoise,
    drop_fraction: float,
    keep: frozenset[str],
    labels: Mapping[str, str],
    rng: np.random.Generator,
) -> tuple[list[SceneObject], int]:
    """The objects as the case's map shows them, and how many were left out.

    A `drop_fraction` share (rounded down) of the objects not in `keep` (the case's anchors) is left out;
    the rest get box noise, then the motion; `labels` renames objects by id (a raw label vocabulary).
    """
    droppable = [k for k, o in enumerate(objects) if o.id not in keep]
    n_drop = math.floor(drop_fraction * len(droppable))
    dropped = set(rng.choice(droppable, size=n_drop, replace=False).tolist()) if n_drop else set()
    kept = [o for k, o in enumerate(objects) if k not in dropped]
    centres = np.array([o.center for o in kept], dtype=float).reshape(-1, 3)  # (N, 3)
    sizes = np.array([o.size for o in kept], dtype=float).reshape(-1, 3)  # (N, 3)
    yaws = np.array([o.yaw for o in kept], dtype=float)  # (N,)
    if noise.center_jitter or noise.size_noise:
        centres, sizes = noise.apply(centres, sizes, rng)
    centres, sizes, yaws = motion.boxes(centres, sizes, yaws)
    out = [
        SceneObject.model_construct(
            id=o.id,
            label=labels.get(o.id, o.label),
            center=c,
            size=s,
            yaw=w,
            region_id=o.region_id,
            attributes=o.attributes,
        )
        for o, c, s, w in zip(
            kept,
            np.round(centres, COORD_DECIMALS).tolist(),
            np.round(sizes, COORD_DECIMALS).tolist(),
            np.round(yaws, YAW_DECIMALS).tolist(),
            strict=True,
        )
    ]
    return out, n_drop
