"""The voxel grid the VL-Map belief lives on: an axis-aligned lattice of cubes in the scene graph's frame.

The workspace is cut into N non-overlapping voxels indexed by i in [N] (the reference's "voxel
representation"). The target's position is a categorical variable over those voxels: exactly one voxel
holds it, and the belief is a probability vector of length N.

Voxel (i, j, k) covers [origin + (i, j, k) s, origin + (i + 1, j + 1, k + 1) s) with s the voxel size,
its centre is origin + (i + 1/2, j + 1/2, k + 1/2) s, and its flat index is (i * ny + j) * nz + k
(C order, z fastest), so a (N,) layer reshapes to (nx, ny, nz) without a copy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.errors import InvalidInput, LimitExceeded
from app.scene_graph.model import SceneGraph

#: Hydra's default voxel size for indoor scenes (metres).
DEFAULT_VOXEL_SIZE_M = 0.1
#: Free space kept around the scene graph's extent, so that a target beside a wall still has voxels (metres).
DEFAULT_MARGIN_M = 0.5
#: Largest grid `VoxelGrid.around` builds: 16 M voxels are 128 MB of float32 layers per session.
DEFAULT_MAX_VOXELS = 16_000_000


@dataclass(frozen=True)
class VoxelGrid:
    """Axis-aligned voxel lattice: `origin` is the min corner, `shape` the voxel count per axis."""

    origin: tuple[float, float, float]
    shape: tuple[int, int, int]
    voxel_size: float = DEFAULT_VOXEL_SIZE_M

    def __post_init__(self) -> None:
        if len(self.origin) != 3 or not all(math.isfinite(v) for v in self.origin):
            msg = f"grid origin must be three finite numbers, got {self.origin}"
            raise InvalidInput(msg, "grid.origin")
        if len(self.shape) != 3 or not all(int(n) == n and n >= 1 for n in self.shape):
            msg = f"grid shape must be three positive integers, got {self.shape}"
            raise InvalidInput(msg, "grid.shape")
        if not (math.isfinite(self.voxel_size) and self.voxel_size > 0):
            msg = f"voxel size must be a positive number of metres, got {self.voxel_size}"
            raise InvalidInput(msg, "grid.voxel_size")
        # Normalise numpy scalars and lists so that equal grids hash equal (summary caches key on grids).
        object.__setattr__(self, "origin", tuple(float(v) for v in self.origin))
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))
        object.__setattr__(self, "voxel_size", float(self.voxel_size))

    @classmethod
    def around(
        cls,
        scene_graph: SceneGraph,
        voxel_size: float = DEFAULT_VOXEL_SIZE_M,
        margin: float = DEFAULT_MARGIN_M,
        max_voxels: int = DEFAULT_MAX_VOXELS,
    ) -> VoxelGrid:
        """The grid covering the scene graph's extent (`SceneGraph.bounds()`) grown by `margin` on every side.

        The corners snap outward to multiples of `voxel_size`, so grids of overlapping scenes share one
        lattice (as Hydra's global voxel map does).
        """
        if not (math.isfinite(voxel_size) and voxel_size > 0):
            msg = f"voxel size must be a positive number of metres, got {voxel_size}"
            raise InvalidInput(msg, "voxel_size")
        if not (math.isfinite(margin) and margin >= 0):
            msg = f"margin must be a non-negative number of metres, got {margin}"
            raise InvalidInput(msg, "margin")
        low, high = scene_graph.bounds()
        first = np.floor((low - margin) / voxel_size)
        last = np.ceil((high + margin) / voxel_size)
        shape = np.maximum(last - first, 1).astype(np.int64)
        n_voxels = math.prod(int(n) for n in shape)  # Python ints: a huge extent must not wrap around
        if n_voxels > max_voxels:
            msg = (
                f"the scene's extent {np.round(high - low, 2).tolist()} m at {voxel_size} m voxels needs "
                f"{n_voxels:,} voxels, more than the limit {max_voxels:,}; use larger voxels"
            )
            raise LimitExceeded(msg, "max_grid_voxels")
        return cls(origin=tuple(first * voxel_size), shape=tuple(shape), voxel_size=voxel_size)

    @property
    def n_voxels(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    @property
    def voxel_volume(self) -> float:
        """V = s^3 (m^3)."""
        return self.voxel_size**3

    @property
    def min_corner(self) -> np.ndarray:
        return np.asarray(self.origin)

    @property
    def max_corner(self) -> np.ndarray:
        return np.asarray(self.origin) + np.asarray(self.shape) * self.voxel_size

    def axis_centers(self, axis: int) -> np.ndarray:
        """Centre coordinates of the voxels along one axis, shape (shape[axis],)."""
        return self.origin[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_size

    def flat_to_ijk(self, flat_idx: np.ndarray) -> np.ndarray:
        """(M,) flat indices -> (M, 3) integer voxel coordinates."""
        return np.stack(np.unravel_index(np.asarray(flat_idx), self.shape), axis=-1)

    def ijk_to_flat(self, ijk: np.ndarray) -> np.ndarray:
        """(M, 3) integer voxel coordinates (inside the grid) -> (M,) flat indices."""
        ijk = np.asarray(ijk)
        return np.ravel_multi_index((ijk[..., 0], ijk[..., 1], ijk[..., 2]), self.shape)

    def centers(self, flat_idx: np.ndarray | None = None) -> np.ndarray:
        """Voxel centres, shape (M, 3) for the given flat indices, or (N, 3) for the whole grid."""
        if flat_idx is None:
            flat_idx = np.arange(self.n_voxels)
        ijk = self.flat_to_ijk(flat_idx)  # (M, 3)
        return np.asarray(self.origin) + (ijk + 0.5) * self.voxel_size

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) points -> ((M,) flat indices, (M,) inside mask); points outside or non-finite get -1."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)  # (M, 3)
        with np.errstate(invalid="ignore"):
            scaled = np.floor((pts - np.asarray(self.origin)) / self.voxel_size)  # (M, 3), NaN stays NaN
            inside = np.all((scaled >= 0) & (scaled < np.asarray(self.shape)), axis=1)  # NaN compares False
        ijk = np.where(inside[:, None], scaled, 0).astype(np.int64)
        flat = np.where(inside, self.ijk_to_flat(ijk), -1)
        return flat, inside

    def box_slices(self, low: np.ndarray, high: np.ndarray) -> tuple[slice, slice, slice]:
        """Index ranges of the voxels whose centres lie in the closed box [low, high] (possibly empty)."""
        # origin + (i + 1/2) s in [low, high]  <=>  (low - origin)/s - 1/2 <= i <= (high - origin)/s - 1/2
        origin, shape = np.asarray(self.origin), np.asarray(self.shape)
        # Clipped while still floats: a box far beyond the grid would overflow int64 (and select nothing).
        first = np.clip(np.ceil((np.asarray(low) - origin) / self.voxel_size - 0.5), 0, shape).astype(
            np.int64
        )
        last = np.clip(np.floor((np.asarray(high) - origin) / self.voxel_size - 0.5), -1, shape).astype(
            np.int64
        )
        stop = np.clip(last + 1, first, shape)
        return (
            slice(int(first[0]), int(stop[0])),
            slice(int(first[1]), int(stop[1])),
            slice(int(first[2]), int(stop[2])),
        )

    def to_dict(self) -> dict[str, Any]:
        return {"origin": list(self.origin), "shape": list(self.shape), "voxel_size": self.voxel_size}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VoxelGrid:
        return cls(origin=tuple(data["origin"]), shape=tuple(data["shape"]), voxel_size=data["voxel_size"])
