"""Targets moved to another resting place in their room before their relations are computed.

A source's layouts place small things where that source puts them (AI2-THOR's mugs on counters, ScanNet's
bags on chairs), and a model trained on one source learns that habit as if it were what "near the table"
means. A person's object can rest anywhere it physically can. So a share of the training targets
(`BuildConfig.relocate_fraction`) is first put down somewhere else in its own region: on the floor, or on
the top of a piece of furniture wide enough to hold it, at a uniform place on that surface, never inside
another object. The builder then lists the moved target's true relations from the boxes as for any target,
so the utterance stays true of where the target is; only where it rests follows no source's habit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.data.layouts import PORTABLE_MAX_SIDE
from app.grounding.box_relations import (
    FLOOR_CEILING,
    OPENINGS,
    PARTS,
    WALL_LIKE,
    WALL_MOUNTED,
    Box,
    is_room_shell,
    volume_overlap,
)
from app.scene_graph.model import Region, SceneObject
from app.vocabulary import in_classes

# How often the floor is drawn rather than a furniture top (when the room has a top wide enough).
FLOOR_PROBABILITY = 0.3
# Tops higher than this above the floor hold nothing a person would leave there (shelves' tops, wardrobes).
SUPPORT_MAX_HEIGHT = 2.0
# What holds nothing on top, whatever its box says.
NOT_SUPPORTS = WALL_LIKE | OPENINGS | PARTS | WALL_MOUNTED
# A place is rejected when more than this share of the target's box lies inside another object's box.
MAX_OVERLAP = 0.05
TRIES = 20


def _overlap_share(box: Box, others: Box) -> float:
    """The largest share of `box` (one box) that lies inside any one of `others` (N boxes)."""
    if len(others.lo) == 0:
        return 0.0
    return float(np.max(volume_overlap(box, others)) / np.prod(box.size))


def floor_height(objects: Sequence[SceneObject]) -> float:
    """The floor under a region's objects: the lowest bottom of its furniture (shell boxes have thickness)."""
    bottoms = [float(o.min_corner[2]) for o in objects if not is_room_shell(o.label)]
    if not bottoms:
        bottoms = [float(o.min_corner[2]) for o in objects]
    return min(bottoms)


def relocated(
    target: SceneObject,
    others: Sequence[SceneObject],
    region: Region | None,
    rng: np.random.Generator,
) -> SceneObject | None:
    """The target resting at a random place of its region (`others` exclude it), or None where no place
    was found in TRIES draws or the target is not portable (a side over PORTABLE_MAX_SIDE: a door, a table).
    The floor is the region's box footprint at `floor_height`; a furniture top is
    any non-shell object of the region under SUPPORT_MAX_HEIGHT whose footprint holds the target's."""
    local = [o for o in others if region is None or o.region_id in (None, region.id)]
    if not local or max(target.size) > PORTABLE_MAX_SIDE:
        return None
    half = target.half_extent
    floor = floor_height(local)
    if region is not None:
        lo_xy = np.asarray(region.center[:2]) - np.asarray(region.size[:2]) / 2
        hi_xy = np.asarray(region.center[:2]) + np.asarray(region.size[:2]) / 2
    else:
        around = Box.of(local)
        lo_xy, hi_xy = around.lo.min(axis=0)[:2], around.hi.max(axis=0)[:2]
    # Floors and ceilings are slabs the target may touch; walls and furniture it may not enter.
    solid = [o for o in local if not in_classes(o.label, FLOOR_CEILING)]
    solid_boxes = Box.of(solid)
    solid_low, solid_high = solid_boxes.lo, solid_boxes.hi
    supports = [
        k
        for k, o in enumerate(solid)
        if not is_room_shell(o.label)
        and not in_classes(o.label, NOT_SUPPORTS)
        and float(solid_high[k, 2]) - floor <= SUPPORT_MAX_HEIGHT
        and np.all(solid_high[k, :2] - solid_low[k, :2] >= 2 * half[:2])
    ]
    for _ in range(TRIES):
        keep = np.ones(len(solid), dtype=bool)
        if not supports or rng.random() < FLOOR_PROBABILITY:
            area_lo, area_hi, base = lo_xy, hi_xy, floor
        else:
            k = supports[int(rng.integers(len(supports)))]
            area_lo, area_hi, base = solid_low[k, :2], solid_high[k, :2], float(solid_high[k, 2])
            keep[k] = False  # the target rests on it
        if np.any(area_hi - area_lo - 2 * half[:2] < 1e-6):
            continue
        xy = rng.uniform(area_lo + half[:2], area_hi - half[:2])
        centre = np.array([xy[0], xy[1], base + half[2]])
        if _overlap_share(Box(centre - half, centre + half), solid_boxes.take(keep)) > MAX_OVERLAP:
            continue
        return target.model_copy(update={"center": [float(v) for v in centre]})
    return None
