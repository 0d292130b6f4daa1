"""What the belief says, in a few numbers: MAP voxel, top voxels, moments, entropy and mass per place.

With pi = softmax(lang + vis) over the N voxel centres c_i (fusion equation (2)):

    MAP              i* = argmax_i pi_i
    mean             mu = sum_i pi_i c_i
    covariance       Sigma = sum_i pi_i (c_i - mu)(c_i - mu)^T
    entropy          H = -sum_i pi_i log pi_i                             (nats)
    information gain IG = log N - H = KL(pi || uniform)                   (nats; 0 for the uniform prior)
    place mass       m(P) = sum_{i: c_i in P} pi_i

Mass per object: where a person would search. Each scene-graph object's *support place* is where a target
resting on it or kept in it would be, by the label classes of `app.grounding.box_relations` (its yawed
footprint, between two heights; `on_margin` is `ON_MARGIN_M` by default):

* a container (`is_container`: cabinet, drawer, nightstand, fridge, box, sink, ...): its whole box, plus
  `on_margin` above its top unless it is a part of furniture (nothing rests on a drawer);
* a seat or shelf (`internal_support_reach` > 0: bed, couch, chair, shelf, ...): its box from
  `INTERNAL_SUPPORT_MIN_HEIGHT` above its base, plus `on_margin` above its top;
* any other object: its top, from `ON_SINK_TOLERANCE` below the top surface (but not below
  `ON_MIN_BOTTOM_FRACTION` of its height) to `on_margin` above it, the heights at which the "on" relation
  puts a target's bottom (the space under a table is not the table's);
* parts that hold nothing (knobs, handles) and openings (doors, windows, curtains): no support place;
* structure, the room's shell (`is_room_structure`: floors, ceilings, walls and wall-like partitions): its
  box plus `on_margin` above its top, reported apart (`PosteriorSummary.structure`), never among the objects.

Each voxel counts towards one place only, the smallest support place (in voxels; ties: the first object of
the scene graph) that contains its centre, structure only where no object's does: the keys on a nightstand
count for the nightstand, not for the floor whose box and margin also cover its top, nor for the lamp beside
them; a voxel inside a drawer of a dresser counts for the drawer; the floor holds what lies on it and on no
object. So the objects' and structure's masses with `mass_elsewhere` (the mass in no such place) sum to one.
An object smaller than a voxel, whose support place holds no voxel centre, gets the voxel containing its
centre. A region's place is its box; regions overlap objects and each other, so their masses need not sum to
one.

Speed: two passes over the grid in cache-sized chunks. The first finds block maxima, and the top-k
search then looks only inside the blocks whose maximum can make the top k. The second writes
exp(s - max s) in float32 and accumulates the entropy term and, per (x, y) column, the mass and the
first two z moments (one small matrix product per chunk), from which the mean and covariance follow.
Place indices are computed once per (grid, scene graph) and cached. Grid sums finish in float64.

Places and memory: building an index paints every support place into one voxel array (largest first, so
that the smallest containing place owns a voxel), then lists each place's owned flat voxel indices while
all the lists together stay under `_INDEXED_VOXELS`, so that one gather and one segmented sum give those
places' masses; larger places are summed over their sub-box (with a mask of the voxels they own, where
another place owns some). A scene graph of a few huge boxes then costs the summary time in proportion to
their volume (which the service caps per session: `place_voxels`, `Settings.max_place_voxels`), never the
memory of its indices; the cache of place indices is bounded in bytes as well as in entries.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from app.belief.grid import VoxelGrid
from app.grounding.box_relations import (
    INTERNAL_SUPPORT_MIN_HEIGHT,
    ON_MIN_BOTTOM_FRACTION,
    ON_SINK_TOLERANCE,
    OPENINGS,
    PARTS,
    WALL_LIKE,
    internal_support_reach,
    is_ceiling,
    is_container,
    is_floor,
)
from app.scene_graph.model import SceneGraph, SceneObject
from app.vocabulary import in_classes

#: Height above an object's top surface that still counts as "on" it (metres): most things people leave
#: on furniture (bags, cups, laptops, books) are under 30 cm tall.
ON_MARGIN_M = 0.3
#: What a summary holds, as a number: summaries shared between processes (the Redis store) are keyed by it,
#: so that a replica never reads one made under another definition (2: support places and structure).
SUMMARY_FORMAT = 2
#: Most probable voxels a summary lists when nobody asks for another number.
DEFAULT_TOP_K = 5
#: Voxels per block in the top-k search; 1024 float32 values make one cheap SIMD row maximum.
_TOPK_BLOCK = 1024
#: Voxels per chunk of the two passes over the grid (256 kB of float32: stays in L2).
_CHUNK_VOXELS = 1 << 16
#: Log-weights are floored at max - 80 before exp (see `summarize`).
_EXP_FLOOR = -80.0
#: Largest log-weight exponentiated unshifted: e^40 * 40 * 1024 stays far inside float32's range.
_EXP_CEILING = 40.0
#: Place indices kept for (grid, scene graph, margin) triples; one per live session is plenty.
_PLACE_CACHE_SIZE = 64
#: Flat voxel indices one place index lists at most (4 bytes each): beyond, places are summed by sub-box.
_INDEXED_VOXELS = 1 << 20
#: Bytes of listed indices the place cache holds at most.
_PLACE_CACHE_BYTES = 64 << 20


@dataclass(frozen=True)
class VoxelMass:
    """One voxel of the posterior: flat index, centre (m) and probability."""

    index: int
    center: tuple[float, float, float]
    probability: float


@dataclass(frozen=True)
class PlaceMass:
    """Posterior mass inside one scene-graph object's place or region."""

    kind: Literal["object", "region"]
    id: str
    label: str
    mass: float

    def describe(self) -> str:
        if self.kind == "object":
            return f"{self.mass:.2f} on {self.label} {self.id}"
        return f"{self.mass:.2f} in {self.label or self.id}"


@dataclass(frozen=True)
class PosteriorSummary:
    """The posterior's MAP voxel, top voxels, moments, entropy and mass per place (sorted, largest first).

    `objects`: the mass on each object's support place, `structure`: on the room's shell outside them (floors,
    walls, ceilings), `mass_elsewhere`: in neither (the three sum to one over all places; the lists hold the
    largest `max_places`); `regions`: in each region's box.
    """

    n_voxels: int
    map_voxel: VoxelMass
    top_voxels: tuple[VoxelMass, ...]
    mean: tuple[float, float, float]
    covariance: tuple[tuple[float, float, float], ...]
    entropy_nats: float
    information_gain_nats: float
    objects: tuple[PlaceMass, ...] = ()
    regions: tuple[PlaceMass, ...] = ()
    structure: tuple[PlaceMass, ...] = ()
    mass_elsewhere: float = 0.0
    version: int | None = None  # the belief version summarised, when a store knows it

    def describe(self, n: int = 3) -> str:
        """E.g. "0.62 on table 7, 0.30 on kitchen counter 2, 0.03 on chair 5"."""
        return ", ".join(place.describe() for place in self.objects[:n])

    @classmethod
    def from_dict(cls, data: dict[str, Any], version: int | None = None) -> PosteriorSummary:
        """The inverse of `to_dict` (which leaves the version out). A summary that an older replica shared
        (without `structure` and `mass_elsewhere`) reads with none and 0."""

        def voxel(v: dict[str, Any]) -> VoxelMass:
            x, y, z = v["center"]
            return VoxelMass(int(v["index"]), (float(x), float(y), float(z)), float(v["probability"]))

        def place(m: dict[str, Any]) -> PlaceMass:
            return PlaceMass(m["kind"], m["id"], m["label"], float(m["mass"]))

        mx, my, mz = data["mean"]
        return cls(
            n_voxels=int(data["n_voxels"]),
            map_voxel=voxel(data["map_voxel"]),
            top_voxels=tuple(voxel(v) for v in data["top_voxels"]),
            mean=(float(mx), float(my), float(mz)),
            covariance=tuple((float(r[0]), float(r[1]), float(r[2])) for r in data["covariance"]),
            entropy_nats=float(data["entropy_nats"]),
            information_gain_nats=float(data["information_gain_nats"]),
            objects=tuple(place(m) for m in data["objects"]),
            regions=tuple(place(m) for m in data["regions"]),
            structure=tuple(place(m) for m in data.get("structure", ())),
            mass_elsewhere=float(data.get("mass_elsewhere", 0.0)),
            version=version,
        )

    def to_dict(self) -> dict[str, Any]:
        def voxel(v: VoxelMass) -> dict[str, Any]:
            return {"index": v.index, "center": list(v.center), "probability": v.probability}

        def place(m: PlaceMass) -> dict[str, Any]:
            return {"kind": m.kind, "id": m.id, "label": m.label, "mass": m.mass}

        return {
            "n_voxels": self.n_voxels,
            "map_voxel": voxel(self.map_voxel),
            "top_voxels": [voxel(v) for v in self.top_voxels],
            "mean": list(self.mean),
            "covariance": [list(row) for row in self.covariance],
            "entropy_nats": self.entropy_nats,
            "information_gain_nats": self.information_gain_nats,
            "objects": [place(m) for m in self.objects],
            "regions": [place(m) for m in self.regions],
            "structure": [place(m) for m in self.structure],
            "mass_elsewhere": self.mass_elsewhere,
        }


def is_room_structure(label: str) -> bool:
    """Floors, ceilings, walls and wall-like partitions (`app.grounding.box_relations`' classes): the room's
    shell, whose mass the summary reports apart from the objects'."""
    return is_floor(label) or is_ceiling(label) or in_classes(label, WALL_LIKE)


def support_heights(obj: SceneObject, on_margin: float = ON_MARGIN_M) -> tuple[float, float] | None:
    """(bottom, top) heights (m) of an object's support place (see the module docstring), None for an object
    nothing rests on or in."""
    half_height = 0.5 * float(obj.size[2])
    bottom, top = float(obj.center[2]) - half_height, float(obj.center[2]) + half_height
    label = obj.label
    if is_room_structure(label):
        return bottom, top + on_margin
    holds_on_top = not (in_classes(label, PARTS) or in_classes(label, OPENINGS))
    on_top = max(top - ON_SINK_TOLERANCE, bottom + ON_MIN_BOTTOM_FRACTION * (top - bottom))
    if is_container(label):
        low = bottom
    elif internal_support_reach(label) > 0:
        low = min(bottom + INTERNAL_SUPPORT_MIN_HEIGHT, on_top)
    elif holds_on_top:
        low = on_top
    else:
        return None
    return low, top + on_margin if holds_on_top else top


@dataclass(frozen=True)
class _Place:
    """A place as voxel index ranges, with a mask over that sub-box when the place is a yawed box or shares
    voxels with places that own them."""

    kind: Literal["object", "region"]
    id: str
    label: str
    slices: tuple[slice, slice, slice]
    # (bx, by, bz) bool, True where the voxel centre lies in the place (and, for a support place, the voxel is
    # its own); a yawed box's footprint repeated along z is a broadcast view (z stride 0)
    mask: np.ndarray | None = None


@dataclass(frozen=True)
class PlaceIndex:
    """Every object's places and every region's on one grid (build once, reuse for every summary).

    `objects`: each object's box grown by `on_margin` on top, in scene-graph order (what the belief's
    look-alike filter reads, with no margin). `supports`: each object's support place in the same order, its
    voxels the ones it owns; `structure[i]` says whether the i-th object is room structure.
    `support_voxels[support_bounds[j]:support_bounds[j + 1]]` are the flat voxel indices owned by the j-th
    support of `indexed`: one gather and one segmented sum give those masses (a sum per place cost ~15 us
    each in Python). The other supports (`summed`), too large to list, are summed over their sub-boxes.
    """

    objects: tuple[_Place, ...] = field(default=())
    regions: tuple[_Place, ...] = field(default=())
    supports: tuple[_Place, ...] = field(default=())
    structure: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    support_voxels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    support_bounds: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    indexed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # positions in supports
    summed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        masks = [place.mask for place in self.supports if _owns_mask(place.mask)]
        return int(self.support_voxels.nbytes) + sum(int(mask.nbytes) for mask in masks if mask is not None)


def _owns_mask(mask: np.ndarray | None) -> bool:
    """Whether a place's mask is an array of its own (not a footprint broadcast along z)."""
    return mask is not None and mask.strides[2] != 0


def _object_aabb(obj: Any, on_margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """(centre, half sizes in the object's frame, half sizes of the map-frame bounding box, cos, sin) of an
    object's place."""
    center, half = object_place_box(np.asarray(obj.center), np.asarray(obj.size), on_margin)
    return (center, half, *_yawed_aabb(half, obj.yaw))


def _yawed_aabb(half: np.ndarray, yaw: float) -> tuple[np.ndarray, float, float]:
    """Half sizes of the map-frame bounding box of a box with these half sizes turned by `yaw`, cos, sin."""
    cos, sin = math.cos(yaw), math.sin(yaw)
    aabb_half = np.array(
        [abs(cos) * half[0] + abs(sin) * half[1], abs(sin) * half[0] + abs(cos) * half[1], half[2]]
    )
    return aabb_half, cos, sin


def place_voxels(grid: VoxelGrid, scene_graph: SceneGraph, on_margin: float = ON_MARGIN_M) -> int:
    """The voxels of every object's place (its map-frame bounding box: an upper bound for a yawed one; each
    support place lies inside it) and of every region, summed: what building a place index reads of the grid
    beyond a few passes, and a summary at most. Cheap: no voxel is listed."""
    total = 0
    for obj in scene_graph.objects:
        center, _, aabb_half, _, _ = _object_aabb(obj, on_margin)
        total += _place_size(grid.box_slices(center - aabb_half, center + aabb_half), None)
    for reg in scene_graph.regions:
        half = 0.5 * np.asarray(reg.size)
        total += _place_size(
            grid.box_slices(np.asarray(reg.center) - half, np.asarray(reg.center) + half), None
        )
    return total


def object_place_box(center: np.ndarray, size: np.ndarray, on_margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half sizes (object frame) of an object's place: its box with `on_margin` added on top."""
    half = 0.5 * np.asarray(size, dtype=np.float64)
    center = np.asarray(center, dtype=np.float64) + np.array([0.0, 0.0, 0.5 * on_margin])
    return center, half + np.array([0.0, 0.0, 0.5 * on_margin])


def _box_place(
    grid: VoxelGrid, obj: SceneObject, center: np.ndarray, half: np.ndarray, *, fallback: bool
) -> _Place:
    """The voxels whose centres lie in a box of the object's yaw (centre, half sizes in its frame); with
    `fallback`, the voxel containing the object's centre when there are none."""
    aabb_half, cos, sin = _yawed_aabb(half, obj.yaw)
    slices = grid.box_slices(center - aabb_half, center + aabb_half)
    mask = None
    if abs(math.sin(2.0 * obj.yaw)) > 1e-9:  # not a multiple of 90 degrees: the box is not its own AABB
        xs, ys = (grid.axis_centers(a)[s] - center[a] for a, s in ((0, slices[0]), (1, slices[1])))
        local_x = cos * xs[:, None] + sin * ys[None, :]  # (bx, by): rotate map offsets into the object frame
        local_y = -sin * xs[:, None] + cos * ys[None, :]
        inside_xy = (np.abs(local_x) <= half[0]) & (np.abs(local_y) <= half[1])
        nz = slices[2].stop - slices[2].start
        mask = np.broadcast_to(inside_xy[:, :, None], (*inside_xy.shape, nz))
    if fallback and _place_size(slices, mask) == 0:
        flat, inside = grid.locate(np.asarray(obj.center)[None, :])
        if inside[0]:
            i, j, k = grid.flat_to_ijk(flat)[0]
            slices, mask = (slice(i, i + 1), slice(j, j + 1), slice(k, k + 1)), None
    return _Place("object", obj.id, obj.label, slices, mask)


_NOWHERE = (slice(0, 0), slice(0, 0), slice(0, 0))


def _support_place(grid: VoxelGrid, obj: SceneObject, on_margin: float) -> _Place:
    heights = support_heights(obj, on_margin)
    if heights is None:
        return _Place("object", obj.id, obj.label, _NOWHERE)
    low, high = heights
    center = np.array([obj.center[0], obj.center[1], 0.5 * (low + high)], dtype=np.float64)
    half = np.array([0.5 * obj.size[0], 0.5 * obj.size[1], 0.5 * (high - low)], dtype=np.float64)
    return _box_place(grid, obj, center, half, fallback=True)


def build_place_index(grid: VoxelGrid, scene_graph: SceneGraph, on_margin: float = ON_MARGIN_M) -> PlaceIndex:
    """Each object's box + `on_margin` and support place (yaw respected), each support's own voxels (the
    smallest containing place's, structure last), and each region's box."""
    objects = []
    for obj in scene_graph.objects:
        center, half = object_place_box(np.asarray(obj.center), np.asarray(obj.size), on_margin)
        objects.append(_box_place(grid, obj, center, half, fallback=True))
    regions = []
    for reg in scene_graph.regions:
        half = 0.5 * np.asarray(reg.size)
        slices = grid.box_slices(np.asarray(reg.center) - half, np.asarray(reg.center) + half)
        regions.append(_Place("region", reg.id, reg.name, slices))
    supports = [_support_place(grid, obj, on_margin) for obj in scene_graph.objects]
    structure = np.array([is_room_structure(obj.label) for obj in scene_graph.objects], dtype=bool)
    sizes = [_place_size(place.slices, place.mask) for place in supports]
    # Paint the places into one array, the last painted owning a voxel: structure first, then the objects,
    # each group largest first (of equal sizes, the first object last).
    order = sorted(range(len(supports)), key=lambda i: (not structure[i], -sizes[i], -i))
    code_type = np.int16 if len(supports) < 2**15 else np.int32
    owner = np.full(grid.shape, -1, dtype=code_type)
    for position in order:
        place = supports[position]
        if sizes[position] == 0:
            continue
        if place.mask is None:
            owner[place.slices] = position
        else:
            np.copyto(owner[place.slices], np.asarray(position, dtype=code_type), where=place.mask)
    flat_owner = owner.reshape(-1)
    owned_flat = np.flatnonzero(flat_owner >= 0)
    codes = flat_owner[owned_flat]
    counts = np.bincount(codes, minlength=len(supports)) if len(supports) else np.zeros(0, dtype=np.int64)
    # List the supports' owned voxels, in scene-graph order, while they fit the budget; sum the rest by box.
    listed = np.zeros(len(supports), dtype=bool)
    budget = _INDEXED_VOXELS
    for position, count in enumerate(counts.tolist()):
        if count <= budget:
            listed[position] = True
            budget -= count
    keep = listed[codes]
    kept_flat, kept_codes = owned_flat[keep], codes[keep]
    by_place = np.argsort(kept_codes, kind="stable")
    index_type = np.int32 if grid.n_voxels < 2**31 else np.int64
    support_voxels = kept_flat[by_place].astype(index_type)
    support_bounds = np.cumsum([0, *counts[listed].tolist()]).astype(np.int64)
    summed = np.flatnonzero(~listed)
    for position in summed.tolist():
        place = supports[position]
        owned = owner[place.slices] == position
        whole = place.mask if place.mask is not None else True
        if not np.array_equal(owned, np.broadcast_to(whole, owned.shape)):  # others own some of its voxels
            supports[position] = _Place(place.kind, place.id, place.label, place.slices, owned)
    return PlaceIndex(
        tuple(objects),
        tuple(regions),
        tuple(supports),
        structure,
        support_voxels,
        support_bounds,
        np.flatnonzero(listed),
        summed,
    )


def _place_size(slices: tuple[slice, slice, slice], mask: np.ndarray | None) -> int:
    if mask is not None:
        return int(mask.sum())
    return math.prod(max(0, s.stop - s.start) for s in slices)


_place_cache: OrderedDict[tuple[VoxelGrid, str, float], PlaceIndex] = OrderedDict()
_place_cache_lock = threading.Lock()


def json_fingerprint(scene_graph_json: bytes) -> str:
    """A digest of a scene graph's `model_dump_json()` bytes (two equal graphs share cached place indices)."""
    return hashlib.blake2b(scene_graph_json, digest_size=16).hexdigest()


def scene_graph_fingerprint(scene_graph: SceneGraph) -> str:
    """`json_fingerprint` of the scene graph (dumping a 60-object one takes ~0.3 ms)."""
    return json_fingerprint(scene_graph.model_dump_json().encode())


def cached_place_index(
    grid: VoxelGrid, scene_graph: SceneGraph, on_margin: float = ON_MARGIN_M, fingerprint: str | None = None
) -> PlaceIndex:
    """`build_place_index`, memoised on (grid, scene-graph content, margin) for the last few graphs.
    `fingerprint`: the graph's `scene_graph_fingerprint` when the caller has it (e.g. from stored JSON)."""
    key = (grid, fingerprint or scene_graph_fingerprint(scene_graph), float(on_margin))
    with _place_cache_lock:
        index = _place_cache.get(key)
        if index is not None:
            _place_cache.move_to_end(key)
            return index
    index = build_place_index(grid, scene_graph, on_margin)
    with _place_cache_lock:
        _place_cache[key] = index
        held = sum(entry.nbytes for entry in _place_cache.values())
        while len(_place_cache) > _PLACE_CACHE_SIZE or (held > _PLACE_CACHE_BYTES and len(_place_cache) > 1):
            held -= _place_cache.popitem(last=False)[1].nbytes
    return index


def _column_chunks(grid: VoxelGrid) -> list[tuple[int, int]]:
    """(start, stop) flat ranges of whole (x, y) columns of voxels, small enough to stay in cache."""
    nx, ny, nz = grid.shape
    rows = max(1, _CHUNK_VOXELS // nz)
    return [(r * nz, min(r + rows, nx * ny) * nz) for r in range(0, nx * ny, rows)]


def column_mass(grid: VoxelGrid, lang: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """The belief seen from above: softmax(lang + vis) summed over z in each (x, y) column of voxels, (nx, ny)
    float32 summing to one (what a dashboard draws as a heat map: nx * ny values instead of N)."""
    nx, ny, nz = grid.shape
    chunks = _column_chunks(grid)
    scratch = np.empty(min(grid.n_voxels, chunks[0][1]), dtype=np.float32)
    peak = -math.inf
    for start, stop in chunks:
        s = np.add(lang[start:stop], vis[start:stop], out=scratch[: stop - start])
        peak = max(peak, float(s.max()))
    cols = np.empty(nx * ny, dtype=np.float64)
    for start, stop in chunks:
        s = np.add(lang[start:stop], vis[start:stop], out=scratch[: stop - start])
        s -= peak
        np.maximum(s, _EXP_FLOOR, out=s)  # as in `summarize`: float32 exp slows down on underflow
        np.exp(s, out=s)
        cols[start // nz : stop // nz] = s.reshape(-1, nz).sum(axis=1, dtype=np.float64)
    cols /= cols.sum()
    return cols.reshape(nx, ny).astype(np.float32)


def summarize(
    grid: VoxelGrid,
    lang: np.ndarray,
    vis: np.ndarray,
    scene_graph: SceneGraph | None = None,
    *,
    top_k: int = DEFAULT_TOP_K,
    max_places: int = 10,
    on_margin: float = ON_MARGIN_M,
    scene_fingerprint: str | None = None,
) -> PosteriorSummary:
    """Summarise softmax(lang + vis) on `grid` (see the module docstring); places need `scene_graph`
    (`scene_fingerprint`: its `scene_graph_fingerprint`, if known)."""
    n = grid.n_voxels
    nx, ny, nz = grid.shape
    # s = lang + vis is recomputed per chunk rather than stored, which saves a full-size array and two passes
    # over it.
    chunks = _column_chunks(grid)
    scratch = np.empty(min(n, chunks[0][1]), dtype=np.float32)

    def log_weights(start: int, stop: int) -> np.ndarray:
        out = scratch[: stop - start]
        np.add(lang[start:stop], vis[start:stop], out=out)
        return out

    # Pass 1: block maxima (and the global minimum), then the top k inside the few blocks that can hold them.
    block_starts, block_max = [], []
    low = math.inf
    for start, stop in chunks:
        s = log_weights(start, stop)
        low = min(low, float(s.min()))
        full = len(s) - len(s) % _TOPK_BLOCK
        block_starts.append(np.arange(start, start + len(s), _TOPK_BLOCK))
        block_max.append(s[:full].reshape(-1, _TOPK_BLOCK).max(axis=1))
        if full < len(s):
            block_max.append(s[full:].max(keepdims=True))
    starts = np.concatenate(block_starts)
    stops = np.append(starts[1:], n)
    top_idx = _top_k_indices(np.concatenate(block_max), starts, stops, lang, vis, min(max(top_k, 1), n))
    peak = np.add(lang[top_idx[0]], vis[top_idx[0]], dtype=np.float32)

    # Pass 2: p = exp(s - shift), sum_i p_i (s_i - shift) for the entropy, and column moments about the MAP
    # voxel (small offsets keep float32 products accurate):
    # cols[i, j] = (sum_k p_ijk, sum_k p_ijk dz_k, sum_k p_ijk dz_k^2).
    # Any shift gives the same posterior. The layers' clamps normally keep every s inside [-80, 40], where
    # float32 exp is exact to rounding, neither underflows nor overflows (nor do the block sums below):
    # then shift = 0 and the pass skips two full-size operations. Otherwise shift = peak (p <= 1) and s is
    # floored at peak - 80, since exp slows down ~10x on float32 underflow and e^-80 relative to the MAP
    # voxel is far below anything the summary reports.
    shift = 0.0 if (low >= _EXP_FLOOR and peak <= _EXP_CEILING) else float(peak)
    floor = low - shift < _EXP_FLOOR
    anchor = grid.centers(top_idx[:1])[0]
    xs, ys, zs = (grid.axis_centers(a) - anchor[a] for a in range(3))
    z_powers = np.stack([np.ones(nz), zs, zs * zs], axis=1).astype(np.float32)  # (nz, 3)
    p = np.empty(n, dtype=np.float32)  # (N,) unnormalised posterior
    cols32 = np.empty((nx * ny, 3), dtype=np.float32)
    p_dot_s = 0.0
    for start, stop in chunks:
        s = log_weights(start, stop)
        if shift:
            s -= shift
        if floor:
            np.maximum(s, _EXP_FLOOR, out=s)
        chunk = p[start:stop]
        np.exp(s, out=chunk)
        p_dot_s += _blocked_dot(chunk, s)
        # Per-chunk products stay small enough that BLAS does not spawn threads (a loss on a busy machine).
        np.matmul(chunk.reshape(-1, nz), z_powers, out=cols32[start // nz : stop // nz])
    cols = cols32.astype(np.float64).reshape(nx, ny, 3)
    z_total = cols[..., 0].sum()
    px, py = cols[..., 0].sum(axis=1), cols[..., 0].sum(axis=0)  # (nx,), (ny,)
    e_x, e_y, e_z = xs @ px / z_total, ys @ py / z_total, cols[..., 1].sum() / z_total
    e_xx, e_yy, e_zz = (xs * xs) @ px / z_total, (ys * ys) @ py / z_total, cols[..., 2].sum() / z_total
    e_xy = xs @ cols[..., 0] @ ys / z_total
    e_xz = xs @ cols[..., 1].sum(axis=1) / z_total
    e_yz = ys @ cols[..., 1].sum(axis=0) / z_total
    second = np.array([[e_xx, e_xy, e_xz], [e_xy, e_yy, e_yz], [e_xz, e_yz, e_zz]])
    first = np.array([e_x, e_y, e_z])
    covariance = second - np.outer(first, first)
    mean = first + anchor

    entropy = math.log(z_total) - p_dot_s / z_total
    centers = grid.centers(top_idx)
    top = tuple(
        VoxelMass(int(i), (float(c[0]), float(c[1]), float(c[2])), float(p[i] / z_total))
        for i, c in zip(top_idx, centers, strict=True)
    )
    objects: tuple[PlaceMass, ...] = ()
    regions: tuple[PlaceMass, ...] = ()
    structure: tuple[PlaceMass, ...] = ()
    elsewhere = 1.0
    if scene_graph is not None:
        index = cached_place_index(grid, scene_graph, on_margin, scene_fingerprint)
        p3 = p.reshape(nx, ny, nz)
        weights = np.zeros(len(index.supports))
        weights[index.indexed] = _segment_sums(p, index.support_voxels, index.support_bounds)
        weights[index.summed] = [_place_weight(index.supports[i], p3) for i in index.summed.tolist()]
        shell = index.structure.tolist()
        objects = _ranked(index.supports, weights, z_total, [not s for s in shell])
        structure = _ranked(index.supports, weights, z_total, shell)
        regions = _ranked(index.regions, [_place_weight(place, p3) for place in index.regions], z_total)
        objects, structure, regions = objects[:max_places], structure[:max_places], regions[:max_places]
        elsewhere = max(0.0, 1.0 - float(weights.sum() / z_total))  # each voxel is in one place at most
    return PosteriorSummary(
        n_voxels=n,
        map_voxel=top[0],
        top_voxels=top,
        mean=(float(mean[0]), float(mean[1]), float(mean[2])),
        covariance=tuple((float(r[0]), float(r[1]), float(r[2])) for r in covariance),
        entropy_nats=float(entropy),
        information_gain_nats=float(math.log(n) - entropy),
        objects=objects,
        regions=regions,
        structure=structure,
        mass_elsewhere=elsewhere,
    )


def _place_weight(place: _Place, p3: np.ndarray) -> float:
    block = p3[place.slices]
    if place.mask is None:
        return float(block.sum(dtype=np.float64))
    if _owns_mask(place.mask):
        return float(block[place.mask].sum(dtype=np.float64))
    # A yawed place's mask is its footprint repeated along z: sum the columns, then mask the footprint.
    return float(block.sum(axis=2, dtype=np.float64)[place.mask[:, :, 0]].sum())


def _segment_sums(p: np.ndarray, flat: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """sum of p[flat[bounds[i]:bounds[i + 1]]] for each i, in float64 (0 for an empty segment)."""
    out = np.zeros(len(bounds) - 1)
    starts = bounds[:-1]
    filled = bounds[1:] > starts
    if np.any(filled):  # reduceat sums from each start to the next one given: skip the empty segments
        out[filled] = np.add.reduceat(p[flat].astype(np.float64), starts[filled])
    return out


def _ranked(
    places: tuple[_Place, ...],
    weights: Sequence[float] | np.ndarray,
    total: float,
    chosen: Sequence[bool] | None = None,
) -> tuple[PlaceMass, ...]:
    """The places' masses (of those `chosen`, when given), largest first."""
    masses = [
        PlaceMass(place.kind, place.id, place.label, float(weight / total))
        for place, weight, keep in zip(places, weights, chosen or [True] * len(places), strict=True)
        if keep
    ]
    masses.sort(key=lambda m: (-m.mass, m.id))
    return tuple(masses)


def _blocked_dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum_i a_i b_i for float32 vectors: float32 dot products of 1024-blocks, summed in float64."""
    main = len(a) - len(a) % _TOPK_BLOCK
    blocks = np.vecdot(a[:main].reshape(-1, _TOPK_BLOCK), b[:main].reshape(-1, _TOPK_BLOCK))
    return float(blocks.sum(dtype=np.float64) + np.dot(a[main:].astype(np.float64), b[main:]))


def _top_k_indices(
    block_max: np.ndarray,
    starts: np.ndarray,
    stops: np.ndarray,
    lang: np.ndarray,
    vis: np.ndarray,
    k: int,
) -> np.ndarray:
    """Flat indices of the k largest lang + vis, largest first (ties at the k-th value broken arbitrarily).

    Blocks [starts[b], stops[b]) have maxima block_max[b]; let t be the k-th largest. Every voxel outside
    the blocks whose maximum exceeds t, and outside k blocks whose maximum equals t, is <= t, while those
    blocks hold at least k voxels >= t; so the top k of those few blocks are the top k overall.
    """
    if k < len(block_max):
        threshold = np.partition(block_max, len(block_max) - k)[len(block_max) - k]
        chosen = np.concatenate(
            [np.flatnonzero(block_max > threshold), np.flatnonzero(block_max == threshold)[:k]]
        )
    else:
        chosen = np.arange(len(block_max))
    candidates = np.concatenate([np.arange(starts[b], stops[b]) for b in chosen])
    values = np.add(lang[candidates], vis[candidates], dtype=np.float32)
    if k < len(candidates):
        best = np.argpartition(values, len(values) - k)[len(values) - k :]
        candidates, values = candidates[best], values[best]
    return candidates[np.lexsort((candidates, -values))]
