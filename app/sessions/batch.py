"""One observation batch as the robot sent it, decoded (JSON or msgpack alike: `app.api.wire`), and the
msgpack body a client sends for one (`encode_msgpack_batch`, the encoder of `app.api.wire`'s format)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from app.belief.session import LabelNames
from app.errors import InvalidInput
from app.stores.base import pack_array


@dataclass(frozen=True)
class ObservationBatch:
    """One batch, decoded: exactly one of `voxels`/`points`, exactly one of `labels`/`p_target`."""

    stamp: float | None
    voxels: np.ndarray | None  # (N, 3) int64
    points: np.ndarray | None  # (N, 3) float64
    labels: np.ndarray | LabelNames | None  # (N,) int64 ids, or class names
    p_target: np.ndarray | None  # (N,) float64 in [0, 1]
    tp: float | None = None
    fp: float | None = None

    def __post_init__(self) -> None:
        if (self.voxels is None) == (self.points is None):
            msg = "give exactly one of voxels or points"
            raise InvalidInput(msg, field="voxels")
        if (self.labels is None) == (self.p_target is None):
            msg = "give exactly one of labels or p_target"
            raise InvalidInput(msg, field="labels")
        where = self.voxels if self.voxels is not None else self.points
        n = len(where)  # type: ignore[arg-type]
        values_field = "labels" if self.labels is not None else "p_target"
        values = self.labels if self.labels is not None else self.p_target
        if len(values) != n:  # type: ignore[arg-type]
            msg = f"{values_field} has {len(values)} entries for {n} voxels"  # type: ignore[arg-type]
            raise InvalidInput(msg, field=values_field)
        if self.points is not None and not np.all(np.isfinite(self.points)):
            msg = "points must be finite numbers"
            raise InvalidInput(msg, field="points")
        if self.p_target is not None and not (
            np.all(np.isfinite(self.p_target)) and np.all((self.p_target >= 0) & (self.p_target <= 1))
        ):
            msg = "p_target must hold probabilities in [0, 1]"
            raise InvalidInput(msg, field="p_target")
        for name, rate in (("tp", self.tp), ("fp", self.fp)):
            if rate is not None and not (0.0 < rate < 1.0):
                msg = f"{name} must lie strictly between 0 and 1"
                raise InvalidInput(msg, field=f"sensor_model.{name}")

    def __len__(self) -> int:
        return len(self.voxels if self.voxels is not None else self.points)  # type: ignore[arg-type]


def encode_msgpack_batch(
    *,
    voxels: np.ndarray | None = None,
    points: np.ndarray | None = None,
    labels: np.ndarray | list[str] | None = None,
    p_target: np.ndarray | None = None,
    stamp: float | None = None,
    tp: float | None = None,
    fp: float | None = None,
) -> bytes:
    """The msgpack body for a batch: int32 voxels or points, uint32 ids or names, or p_target. Points and
    p_target go at the precision given: float32 arrays (a sensor's) as float32, anything else as float64,
    so that the same numbers give the same belief as a JSON batch (a point rounded to float32 near a voxel
    face can fall in the neighbouring voxel)."""
    envelope: dict[str, Any] = {"stamp": stamp}
    if voxels is not None:
        envelope["voxels"] = pack_array(np.asarray(voxels, dtype=np.int32).reshape(-1, 3))
    if points is not None:
        envelope["points"] = pack_array(_floats(points).reshape(-1, 3))
    if labels is not None:
        arr = np.asarray(labels)
        envelope["labels"] = (
            [str(x) for x in arr] if arr.dtype.kind in "US" else pack_array(arr.astype(np.uint32))
        )
    if p_target is not None:
        envelope["p_target"] = pack_array(_floats(p_target))
    if tp is not None or fp is not None:
        envelope["sensor_model"] = {k: v for k, v in (("tp", tp), ("fp", fp)) if v is not None}
    packed: bytes = msgpack.packb(envelope, use_bin_type=True)
    return packed


def _floats(values: np.ndarray) -> np.ndarray:
    array = np.asarray(values)
    return array if array.dtype == np.float32 else array.astype(np.float64)
