"""The Redis store's mirror: the last state of each session this process read in full or committed.

Each entry is named by its stamp, (version, the meta hash's updated_at bytes). An update computes from the
mirrored state and commits on the condition that the stored state still has that name; when another
replica wrote meanwhile the commit fails and the update reads. The mirror is never needed to be right: the
condition is checked in Redis, and a state is taken from the mirror only under its name.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from typing import Any

import msgpack
import numpy as np

from app.belief import fusion

#: A stored state's name: (version, the meta hash's updated_at bytes).
Stamp = tuple[int, bytes]
#: Hashes a commit writes, by part ("meta", "lang", "vis"): {field: value}.
PartWrites = dict[str, dict[str, Any]]


def n_blocks(n_voxels: int, block_voxels: int) -> int:
    return -(-n_voxels // block_voxels)


def layer_blocks(layer: np.ndarray, block_voxels: int) -> dict[str, bytes]:
    """A layer as stored: block number -> float32 bytes of `block_voxels` voxels."""
    b = block_voxels
    return {str(i): layer[i * b : (i + 1) * b].tobytes() for i in range(n_blocks(len(layer), b))}


def assemble_layer(blocks: dict[Any, bytes | None], n_voxels: int, block_voxels: int) -> np.ndarray:
    """Inverse of `layer_blocks` (absent blocks are zeros)."""
    layer = np.zeros(n_voxels, dtype=fusion.LAYER_DTYPE)
    for name, data in blocks.items():
        if data is not None:
            start = int(name) * block_voxels
            layer[start : start + len(data) // 4] = np.frombuffer(data, dtype="<f4")
    return layer


@dataclasses.dataclass(frozen=True)
class Mirrored:
    """A session's state as this store last read in full or committed it, named by `stamp`.

    Never changed in place (a summary on another thread may be reading it): an update makes a new one.
    `static` is decoded from the stored bytes, so it equals what a read of the meta hash gives.
    """

    stamp: Stamp
    static: dict[str, Any]
    look_alikes: np.ndarray
    block_voxels: int
    scene_graph_json: bytes
    lang: np.ndarray  # (N,) float32
    vis: np.ndarray  # (N,) float32

    @property
    def nbytes(self) -> int:
        return int(self.lang.nbytes + self.vis.nbytes)

    def after(self, writes: PartWrites, stamp: Stamp) -> Mirrored:
        """The state once a commit wrote `writes`."""
        layers = {"lang": self.lang, "vis": self.vis}
        for part, fields in writes.items():
            if part in layers and fields:
                layer, b = layers[part].copy(), self.block_voxels
                for name, data in fields.items():
                    start = int(name) * b
                    layer[start : start + len(data) // 4] = np.frombuffer(data, dtype="<f4")
                layers[part] = layer
        meta = writes.get("meta", {})
        sg = meta.get("sg", self.scene_graph_json)
        return Mirrored(
            stamp=stamp,
            static=msgpack.unpackb(meta["static"], raw=False) if "static" in meta else self.static,
            look_alikes=(
                np.frombuffer(meta["look_alikes"], dtype="<i8") if "look_alikes" in meta else self.look_alikes
            ),
            block_voxels=self.block_voxels,
            scene_graph_json=sg.encode() if isinstance(sg, str) else sg,
            lang=layers["lang"],
            vis=layers["vis"],
        )


class Mirror:
    """Sessions' last known states (`Mirrored`), the least recently used dropped beyond `max_bytes`."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, Mirrored] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, session_id: str, stamp: Stamp | None = None) -> Mirrored | None:
        """The session's entry (only if it is the state `stamp` names, when given)."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is None or (stamp is not None and entry.stamp != stamp):
                return None
            self._entries.move_to_end(session_id)
            return entry

    def put(self, session_id: str, entry: Mirrored) -> None:
        with self._lock:
            self._pop(session_id)
            if entry.nbytes > self.max_bytes:
                return
            self._entries[session_id] = entry
            self._bytes += entry.nbytes
            while self._bytes > self.max_bytes:
                self._pop(next(iter(self._entries)))

    def drop(self, session_id: str, stamp: Stamp | None = None) -> None:
        """Forget the session (only its entry named `stamp`, when given: a newer one stays)."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is not None and (stamp is None or entry.stamp == stamp):
                self._pop(session_id)

    def _pop(self, session_id: str) -> None:
        entry = self._entries.pop(session_id, None)
        if entry is not None:
            self._bytes -= entry.nbytes
