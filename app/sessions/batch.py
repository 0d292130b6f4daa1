"""One observation batch as the robot sent it, decoded (JSON or msgpack alike: `app.api.wire`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.belief.session import LabelNames
from app.errors import InvalidInput


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
