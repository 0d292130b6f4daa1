"""The simulated world: a scene's objects voxelised on the belief's grid, and the floor a robot may use.

Each voxel holds the index of the object occupying it (into `SemanticVoxelWorld.objects`) or `FREE`.

Voxelisation. An object occupies the voxels whose centres lie in its axis-aligned box
[`SceneObject.min_corner`, `SceneObject.max_corner`] (the full box, not only its surface: a camera ray stops
at the first occupied voxel, which is a surface voxel anyway, and solid boxes make occlusion exact). Along an
axis where the box is thinner than a voxel and holds no centre, it takes the one voxel containing its centre,
so that every object inside the grid (a picture on a wall, a phone on a table) has at least one voxel. Where
boxes overlap, the smaller box (by volume) wins the shared voxels: a book on a table keeps its voxels when the
table's box reaches into it, and the target is never swallowed by the furniture it lies on. (The reverse
happens too: on the real layouts 0.1% (ScanNet) and 0.5% (AI2-THOR) of the target candidates lose every
voxel to smaller objects, a pen to the pencil in the same voxel; check `object_voxels` and skip those.)

Enclosed objects. Solid boxes bury what lies inside another object's box: books in a bookcase, a pillow on a
sofa (under the backrest's height), a picture inside a wall's box; on the real layouts 11-15% of the target
candidates would never be visible. Real furniture is open there, so every object without a free neighbour
voxel is opened, smallest first: the shortest straight tunnel of its box's cross-section, up or along x or
y (never down), from its box to the first voxel layer holding free space, is freed, provided it runs only
through larger objects (not the floor, not other contents). Objects that no such tunnel reaches stay hidden.

Floor. Real floor boxes are unreliable as solids (ScanNet's are up to 0.5 m thick around the true surface,
AI2-THOR's lie below it), so the walking surface height is estimated from what stands on it:

    floor_z = clip(Q_0.1({bottom z of every object that is not floor or ceiling}), floor_bottom, floor_top)

(the 10% quantile ignores the few boxes that poke below the floor; the clip to the floor boxes' z range
guards scenes with little furniture). Floor objects occupy only the one voxel layer just below floor_z
(centres in [floor_z - s, floor_z)) over their footprint. Scanned floors are partial (some scans have none,
or a fragment, or a carpet covering it), so the world adds a floor of its own (`SYNTHETIC_FLOOR_ID`) in that
layer under the xy extent of all objects, beneath the scene's floor objects: a camera looking down always
sees a floor.

Free floor. A floor cell (x, y) is free where the robot's body fits: it lies in the xy extent of the
objects, no voxel of its column between floor_z + step_height and floor_z + height is occupied within the
robot's radius, and it belongs to the largest 4-connected region of such cells (the room inside its walls,
every cell of it reachable).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_MAX_VOXELS, DEFAULT_VOXEL_SIZE_M, VoxelGrid
from app.errors import InvalidInput, NotFound
from app.grounding.box_relations import is_ceiling, is_floor
from app.scene_graph.model import SceneGraph, SceneObject

#: Owner code of a voxel no object occupies.
FREE = -1
#: The label observations give free voxels (the belief's vision update reads it as "not the target").
FREE_LABEL = "free"
#: Id of the floor the world lays under every scene (see the module docstring).
SYNTHETIC_FLOOR_ID = "__floor__"
#: Quantile of the objects' bottoms taken as the walking surface (see the module docstring).
FLOOR_QUANTILE = 0.1
#: (axis, sign) of the tunnels that open enclosed objects, preferred in this order at equal length.
OPENING_DIRECTIONS = ((2, 1), (0, -1), (0, 1), (1, -1), (1, 1))


@dataclass(frozen=True)
class RobotBody:
    """The robot's shape as the floor map needs it (metres): a vertical cylinder with a camera on top."""

    radius: float = 0.2
    height: float = 1.5
    # Obstacles lower than this above the floor (rugs, a scale, cables) can be driven over.
    step_height: float = 0.1
    camera_height: float = 1.2

    def __post_init__(self) -> None:
        values = {"radius": self.radius, "height": self.height, "step_height": self.step_height}
        for name, value in values.items():
            if not (math.isfinite(value) and value >= 0):
                msg = f"{name} must be a non-negative number of metres, got {value}"
                raise InvalidInput(msg, f"robot.{name}")
        if not self.step_height < self.height:
            msg = f"step_height {self.step_height} must be below the robot's height {self.height}"
            raise InvalidInput(msg, "robot.step_height")
        if not (math.isfinite(self.camera_height) and 0 < self.camera_height <= self.height):
            msg = f"camera_height must lie in (0, height={self.height}], got {self.camera_height}"
            raise InvalidInput(msg, "robot.camera_height")


def estimate_floor_z(objects: Sequence[SceneObject]) -> float:
    """Height of the walking surface (see the module docstring)."""
    if not objects:
        msg = "a world needs at least one object"
        raise InvalidInput(msg, "objects")
    bottoms = [float(o.min_corner[2]) for o in objects if not (is_floor(o.label) or is_ceiling(o.label))]
    floors = [o for o in objects if is_floor(o.label)]
    if not bottoms:
        return min(float(o.min_corner[2]) for o in objects)
    z = float(np.quantile(bottoms, FLOOR_QUANTILE))
    if floors:
        low = min(float(o.min_corner[2]) for o in floors)
        high = max(float(o.max_corner[2]) for o in floors)
        z = min(max(z, low), high)
    return z


def box_index_ranges(grid: VoxelGrid, low: np.ndarray, high: np.ndarray) -> tuple[slice, slice, slice] | None:
    """Voxel index ranges of a box: the voxels whose centres it holds, or along an axis where it holds none,
    the voxel containing its centre. None if the box misses the grid."""
    ranges = list(grid.box_slices(low, high))
    for axis, rng in enumerate(ranges):
        if rng.stop > rng.start:
            continue
        if high[axis] < grid.min_corner[axis] or low[axis] > grid.max_corner[axis]:
            return None
        middle = 0.5 * (low[axis] + high[axis])
        k = int(np.clip(np.floor((middle - grid.origin[axis]) / grid.voxel_size), 0, grid.shape[axis] - 1))
        ranges[axis] = slice(k, k + 1)
    return ranges[0], ranges[1], ranges[2]


def voxelize(
    grid: VoxelGrid, objects: Sequence[SceneObject], floor_layer: int, open_enclosed: bool = True
) -> np.ndarray:
    """Owner array (nx, ny, nz) int32: the index of the object in each voxel, FREE where none.

    Floor objects fill their footprint in layer `floor_layer` only, in the order given; the others fill their
    boxes, larger boxes first, so that smaller ones overwrite them where they overlap. With `open_enclosed`,
    enclosed objects are then opened, smallest first (see the module docstring).
    """
    owner = np.full(grid.shape, FREE, dtype=np.int32)
    volumes = np.array([float(np.prod(o.max_corner - o.min_corner)) for o in objects])
    floors = [i for i, o in enumerate(objects) if is_floor(o.label)]
    solids = sorted(set(range(len(objects))) - set(floors), key=lambda i: (-volumes[i], i))
    ranges: dict[int, tuple[slice, slice, slice]] = {}
    for index in floors + solids:
        obj = objects[index]
        box = box_index_ranges(grid, obj.min_corner, obj.max_corner)
        if box is None:
            continue
        if index in floors:
            box = (box[0], box[1], slice(floor_layer, floor_layer + 1))
        owner[box] = index
        ranges[index] = box
    if open_enclosed:
        # Tunnels may cut through larger objects only; never through the floor.
        carvable_volume = volumes.copy()
        carvable_volume[floors] = 0.0
        for index in sorted(ranges.keys() - set(floors), key=lambda i: (volumes[i], i)):
            if _is_enclosed(owner, ranges[index], index):
                _open(owner, ranges[index], volumes[index], carvable_volume)
    return owner


def _is_enclosed(owner: np.ndarray, box: tuple[slice, slice, slice], index: int) -> bool:
    """Whether the object has voxels and none of them has a free 6-neighbour inside the grid."""
    around = tuple(slice(max(r.start - 1, 0), r.stop + 1) for r in box)
    block = owner[around]
    mine = block == index
    if not mine.any():
        return False
    near = np.zeros_like(mine)
    near[1:] |= mine[:-1]
    near[:-1] |= mine[1:]
    near[:, 1:] |= mine[:, :-1]
    near[:, :-1] |= mine[:, 1:]
    near[:, :, 1:] |= mine[:, :, :-1]
    near[:, :, :-1] |= mine[:, :, 1:]
    return not np.any(near & (block == FREE))


def _open(
    owner: np.ndarray, box: tuple[slice, slice, slice], volume: float, carvable_volume: np.ndarray
) -> None:
    """Free the shortest straight tunnel (box cross-section, one of `OPENING_DIRECTIONS`) from the box to a
    layer holding free space, if one exists that runs only through larger objects."""
    best: np.ndarray | None = None
    for axis, sign in OPENING_DIRECTIONS:
        index = list(box)
        face = box[axis]
        index[axis] = slice(face.stop, None) if sign > 0 else slice(0, face.start)
        slab = np.moveaxis(owner[tuple(index)], axis, 0)  # (L, ., .) view, layers outward from the face
        if sign < 0:
            slab = slab[::-1]
        reaches = np.flatnonzero((slab == FREE).any(axis=(1, 2)))
        if len(reaches) == 0 or reaches[0] == 0:
            continue
        tunnel = slab[: reaches[0]]
        if (best is None or len(tunnel) < len(best)) and np.all(carvable_volume[tunnel] > volume):
            best = tunnel
    if best is not None:
        best[...] = FREE


def _disk_offsets(radius_cells: float) -> np.ndarray:
    """Structuring element: the cells (i, j) whose square comes closer than `radius_cells` to the centre
    cell's centre, i.e. hypot(max(|i| - 1/2, 0), max(|j| - 1/2, 0)) < radius_cells."""
    reach = math.ceil(radius_cells + 0.5)
    i, j = np.mgrid[-reach : reach + 1, -reach : reach + 1]
    gap = np.hypot(np.maximum(np.abs(i) - 0.5, 0.0), np.maximum(np.abs(j) - 0.5, 0.0))
    disk: np.ndarray = (gap < radius_cells) | ((i == 0) & (j == 0))
    return disk


class SemanticVoxelWorld:
    """Which object occupies each voxel of a grid, and where on the floor a robot may stand."""

    def __init__(
        self,
        grid: VoxelGrid,
        objects: Sequence[SceneObject],
        *,
        robot: RobotBody | None = None,
        floor_z: float | None = None,
        open_enclosed: bool = True,
    ) -> None:
        objects = list(objects)
        floor_z = estimate_floor_z(objects) if floor_z is None else float(floor_z)
        floor = _floor_under(objects, floor_z, grid.voxel_size)
        objects.insert(0, floor)  # painted first: the scene's floor objects overwrite it
        self.grid = grid
        self.objects: tuple[SceneObject, ...] = tuple(objects)
        self.robot = robot or RobotBody()
        self.floor_z = floor_z
        s, z0 = grid.voxel_size, grid.origin[2]
        # The layer whose centre z0 + (k + 1/2) s lies in [floor_z - s, floor_z).
        self.floor_layer = int(np.clip(math.ceil((floor_z - z0) / s - 1.5), 0, grid.shape[2] - 1))
        self._index = {o.id: i for i, o in enumerate(self.objects)}
        self.owner = voxelize(grid, self.objects, self.floor_layer, open_enclosed)  # (nx, ny, nz) int32
        # Cells under the objects' xy extent (the synthetic floor's footprint).
        self._floor_area = np.zeros(grid.shape[:2], dtype=bool)  # (nx, ny)
        extent = box_index_ranges(grid, floor.min_corner, floor.max_corner)
        if extent is not None:
            self._floor_area[extent[:2]] = True
        self.labels: tuple[str, ...] = tuple(o.label for o in self.objects)
        # Label lookup for owner codes: FREE = -1 picks the last entry.
        self._label_table = np.array([*self.labels, FREE_LABEL])

    @classmethod
    def from_scene(
        cls,
        scene: SceneGraph,
        grid: VoxelGrid | None = None,
        *,
        voxel_size: float = DEFAULT_VOXEL_SIZE_M,
        margin: float = DEFAULT_MARGIN_M,
        max_voxels: int = DEFAULT_MAX_VOXELS,
        robot: RobotBody | None = None,
        floor_z: float | None = None,
    ) -> SemanticVoxelWorld:
        """The world of a full scene (target included) on `grid`, by default `VoxelGrid.around(scene)`.

        Pass the belief session's grid to make observed flat indices valid for the service as they are.
        """
        if grid is None:
            grid = VoxelGrid.around(scene, voxel_size=voxel_size, margin=margin, max_voxels=max_voxels)
        return cls(grid, scene.objects, robot=robot, floor_z=floor_z)

    # --- objects -----------------------------------------------------------------------------------------

    def index_of(self, object_id: str) -> int:
        """Owner code of an object; NotFound if the world has no such object."""
        try:
            return self._index[object_id]
        except KeyError:
            msg = f"the world has no object {object_id!r}"
            raise NotFound(msg) from None

    def object_voxels(self, object_id: str) -> np.ndarray:
        """(K,) flat indices of the voxels the object occupies (after overlaps were resolved)."""
        return np.flatnonzero(self.owner.ravel() == self.index_of(object_id))

    def labels_of(self, owner_codes: np.ndarray) -> np.ndarray:
        """(M,) true labels of owner codes; FREE_LABEL for FREE."""
        labels: np.ndarray = self._label_table[np.asarray(owner_codes)]
        return labels

    @property
    def occupied(self) -> np.ndarray:
        """(nx, ny, nz) bool."""
        occupied: np.ndarray = self.owner != FREE
        return occupied

    # --- floor -------------------------------------------------------------------------------------------

    @property
    def camera_z(self) -> float:
        return self.floor_z + self.robot.camera_height

    @cached_property
    def free_floor(self) -> np.ndarray:
        """(nx, ny) bool: cells where the robot may stand (see the module docstring)."""
        from scipy import ndimage

        low, high = self.grid.min_corner.copy(), self.grid.max_corner.copy()
        low[2], high[2] = self.floor_z + self.robot.step_height, self.floor_z + self.robot.height
        band = self.grid.box_slices(low, high)[2]
        obstacle = np.any(self.owner[:, :, band] >= 0, axis=2)  # (nx, ny)
        if self.robot.radius > 0:
            disk = _disk_offsets(self.robot.radius / self.grid.voxel_size)
            obstacle = ndimage.binary_dilation(obstacle, structure=disk)
        free: np.ndarray = self._floor_area & ~obstacle
        regions, n_regions = ndimage.label(free)  # 4-connected
        if n_regions > 1:
            sizes = np.bincount(regions.ravel())[1:]
            free = regions == 1 + int(np.argmax(sizes))
        return free

    @property
    def free_floor_area(self) -> float:
        """Area of the free floor (m^2): too little of it makes a scene a poor place to explore."""
        return float(np.count_nonzero(self.free_floor)) * self.grid.voxel_size**2

    def free_floor_points(self) -> np.ndarray:
        """(K, 2) xy centres of the free floor cells, in flat (x-major) order."""
        i, j = np.nonzero(self.free_floor)
        s = self.grid.voxel_size
        return np.stack([self.grid.origin[0] + (i + 0.5) * s, self.grid.origin[1] + (j + 0.5) * s], axis=1)

    def is_free_floor(self, xy: np.ndarray) -> np.ndarray:
        """(M,) bool: whether each of (M, 2) floor points lies in a free floor cell."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((pts - np.asarray(self.grid.origin[:2])) / self.grid.voxel_size)
        inside = np.all((ij >= 0) & (ij < np.asarray(self.grid.shape[:2])), axis=1)
        ij = np.where(inside[:, None], ij, 0).astype(np.int64)
        free: np.ndarray = inside & self.free_floor[ij[:, 0], ij[:, 1]]
        return free

    def segment_is_free(self, start: np.ndarray, end: np.ndarray) -> bool:
        """Whether the straight floor segment start -> end (xy) runs over free floor only (sampled at s/4)."""
        a, b = np.asarray(start, dtype=np.float64)[:2], np.asarray(end, dtype=np.float64)[:2]
        n = max(2, math.ceil(4.0 * float(np.linalg.norm(b - a)) / self.grid.voxel_size) + 1)
        fractions = np.linspace(0.0, 1.0, n)[:, None]
        return bool(np.all(self.is_free_floor(a + fractions * (b - a))))


def _floor_under(objects: Sequence[SceneObject], floor_z: float, voxel_size: float) -> SceneObject:
    """A one-voxel floor slab under the xy extent of the objects."""
    low = np.min([o.min_corner for o in objects], axis=0)
    high = np.max([o.max_corner for o in objects], axis=0)
    center = [0.5 * (low[0] + high[0]), 0.5 * (low[1] + high[1]), floor_z - 0.5 * voxel_size]
    size = [max(high[0] - low[0], voxel_size), max(high[1] - low[1], voxel_size), voxel_size]
    return SceneObject(id=SYNTHETIC_FLOOR_ID, label="floor", center=center, size=size)
