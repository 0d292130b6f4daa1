"""The native scene graph: objects with labels and boxes, grouped into regions (metres, z up).

Every accepted input format (region-grouped JSON, Spark-DSG, VLA-3D) is normalised into `SceneGraph`.
Validation errors name the offending field so that the API can answer 422 with a precise message.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3, description="x, y, z in metres")]
#: A box's sides: the validators below refuse a side that is not positive; the schema says so too.
Size3 = Annotated[Vec3, Field(json_schema_extra={"items": {"type": "number", "exclusiveMinimum": 0}})]

#: Objects and regions one scene graph may hold at most, whatever the service's configured limits (which lie
#: below): the validator refuses a longer list before reading its items, so the work a body can ask for stays
#: bounded. Lists stop at their first bad item (fail_fast) so that an error is not made per item either.
MAX_OBJECTS_CEILING = 20_000
MAX_REGIONS_CEILING = 20_000


def _id_text(value: Any) -> Any:
    """Integer ids (ScanNet's and Hydra's objects have them) read as their decimal text."""
    return str(value) if isinstance(value, int) and not isinstance(value, bool) else value


Id = Annotated[
    str,
    BeforeValidator(_id_text),
    Field(min_length=1, max_length=128, description="1-128 characters; an integer is read as its text."),
]


def _check_finite(name: str, values: list[float]) -> list[float]:
    if not all(math.isfinite(v) for v in values):
        msg = f"{name} must hold finite numbers (no NaN or infinity), got {values}"
        raise ValueError(msg)
    return values


def _check_positive(name: str, values: list[float]) -> list[float]:
    if not all(v > 0 for v in values):
        msg = f"{name} must be strictly positive in every axis, got {values}"
        raise ValueError(msg)
    return values


class Region(BaseModel):
    """A room or other region of the map, as an axis-aligned box."""

    model_config = ConfigDict(extra="forbid")

    id: Id
    name: str = Field(default="", max_length=256)
    center: Vec3
    size: Size3

    @field_validator("center")
    @classmethod
    def _center_finite(cls, v: list[float]) -> list[float]:
        return _check_finite("center", v)

    @field_validator("size")
    @classmethod
    def _size_positive(cls, v: list[float]) -> list[float]:
        return _check_positive("size", _check_finite("size", v))


class SceneObject(BaseModel):
    """One mapped object: a labelled box, rotated by `yaw` (radians, about +z) around its centre."""

    model_config = ConfigDict(extra="forbid")

    id: Id
    label: str = Field(min_length=1, max_length=256)
    center: Vec3
    size: Size3
    yaw: float = 0.0
    region_id: Id | None = None
    attributes: dict[str, Any] = Field(default_factory=dict)

    @field_validator("center")
    @classmethod
    def _center_finite(cls, v: list[float]) -> list[float]:
        return _check_finite("center", v)

    @field_validator("size")
    @classmethod
    def _size_positive(cls, v: list[float]) -> list[float]:
        return _check_positive("size", _check_finite("size", v))

    @field_validator("yaw")
    @classmethod
    def _yaw_finite(cls, v: float) -> float:
        return _check_finite("yaw", [v])[0]

    @property
    def min_corner(self) -> np.ndarray:
        """Lower corner of the axis-aligned box that bounds the (possibly rotated) object."""
        low: np.ndarray = np.asarray(self.center) - self.half_extent
        return low

    @property
    def max_corner(self) -> np.ndarray:
        """Upper corner of the axis-aligned box that bounds the (possibly rotated) object."""
        high: np.ndarray = np.asarray(self.center) + self.half_extent
        return high

    @property
    def half_extent(self) -> np.ndarray:
        """Half sizes of the axis-aligned bounding box of the yawed box."""
        half: np.ndarray = 0.5 * aabb_extents(np.array([self.size]), np.array([self.yaw]))[0]
        return half


def aabb_extents(dims: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Sides (M, 3) of the axis-aligned boxes of boxes with sides `dims` (M, 3) turned by `yaws` (M,)."""
    cos, sin = np.abs(np.cos(yaws)), np.abs(np.sin(yaws))
    return np.stack(
        [cos * dims[:, 0] + sin * dims[:, 1], sin * dims[:, 0] + cos * dims[:, 1], dims[:, 2]], axis=1
    )


def object_corners(objects: Sequence[SceneObject]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (N, 3) of the axis-aligned boxes that bound the objects' yawed boxes: every
    object's `min_corner` and `max_corner` at once (the per-object properties cost microseconds each, and
    a request reads a map's boxes several times)."""
    if not objects:
        return np.zeros((0, 3)), np.zeros((0, 3))
    centers = np.array([o.center for o in objects], dtype=np.float64)  # (N, 3)
    dims = np.array([o.size for o in objects], dtype=np.float64)
    half = 0.5 * aabb_extents(dims, np.array([o.yaw for o in objects], dtype=np.float64))
    return centers - half, centers + half


class SceneGraph(BaseModel):
    """Objects and regions of one map; ids are unique and every object's region exists."""

    model_config = ConfigDict(extra="forbid")

    frame_id: str = Field(default="map", max_length=128)
    regions: list[Region] = Field(default_factory=list, max_length=MAX_REGIONS_CEILING, fail_fast=True)
    objects: list[SceneObject] = Field(default_factory=list, max_length=MAX_OBJECTS_CEILING, fail_fast=True)

    @model_validator(mode="after")
    def _check_references(self) -> SceneGraph:
        region_ids = [r.id for r in self.regions]
        dup_regions = _duplicates(region_ids)
        if dup_regions:
            msg = f"regions: duplicate region ids {dup_regions}"
            raise ValueError(msg)
        dup_objects = _duplicates([o.id for o in self.objects])
        if dup_objects:
            msg = f"objects: duplicate object ids {dup_objects}"
            raise ValueError(msg)
        known = set(region_ids)
        for index, obj in enumerate(self.objects):
            if obj.region_id is not None and obj.region_id not in known:
                msg = f"objects[{index}].region_id: unknown region id {obj.region_id!r}"
                raise ValueError(msg)
        return self

    def object(self, object_id: str) -> SceneObject:
        """The object with this id; KeyError if absent."""
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise KeyError(object_id)

    def region(self, region_id: str) -> Region:
        """The region with this id; KeyError if absent."""
        for reg in self.regions:
            if reg.id == region_id:
                return reg
        raise KeyError(region_id)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (min, max) corners over all objects and regions; a unit box at the origin if empty."""
        if not self.objects and not self.regions:
            return np.full(3, -0.5), np.full(3, 0.5)
        low, high = object_corners(self.objects)
        if self.regions:
            centers = np.array([r.center for r in self.regions], dtype=np.float64)
            half = 0.5 * np.array([r.size for r in self.regions], dtype=np.float64)
            low, high = np.concatenate([low, centers - half]), np.concatenate([high, centers + half])
        return low.min(axis=0), high.max(axis=0)


def _duplicates(ids: list[str]) -> list[str]:
    seen: set[str] = set()
    dups: list[str] = []
    for i in ids:
        if i in seen and i not in dups:
            dups.append(i)
        seen.add(i)
    return dups
