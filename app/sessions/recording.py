"""A session's recording: a bounded log of frames, one per belief version, that `GET .../recording`
answers as JSON and `GET .../recording.mcap` as an MCAP file (`app.foxglove.messages` converts both).

A frame (`Frame.to_json`) holds the version, its time, what caused it (the event's `cause`), the posterior
summary of that version with its `RECORD_TOP_K` most probable voxels (the belief snapshot: the whole grid is
not kept), and, when the version came from one, the utterance's hypotheses and mixture, or the scene graph
(the session's first frame holds its scene graph too). An utterance that was not fused gets a frame without
a summary, at the version it left unchanged.

Cost: the summary of the new version is what the update's answer carries anyway (its top 5 are the top 100's
first five, so one pass over the grid serves both); a batch sent with `summary=false` is recorded off the
request path, in the background, so that a sensor-rate stream pays nothing more per batch. A recorder reads
the session just after its update: when another update of the session lands in between (two writers at
once, or a background record behind the next batch), the frame shows the later version and the one in
between has none. One writer at a time, with summaries, gets exactly one frame per version.

Bounds and decimation (`app.stores.recording.thin`): a session keeps at most `Settings.recording_frames`
frames (256 by default, about 6 kB each); past it, one level of frames is halved at a time (a frame's level
counts the thinnings it survived, so that frames of level l lie 2^l arrivals apart), never the first frame,
the newest or the frames of utterances and scene graphs (marked `KEEP`), so that a long session keeps its
whole span at a resolution that halves with age while its recent frames stay at full rate; should those
frames alone pass twice the limit, the oldest frames go. The stores keep the log beside the session and drop
it with the session (`SessionStore.record`): the memory store in process memory (not in
its write-ahead log: a restart starts the recording again), the Redis store in one list per session written
after the update's commit (so a process killed in between leaves that version without a frame; no exactness
per version is promised anyway).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack

from app.grounding.sensor import Grounding
from app.scene_graph.model import SceneGraph
from app.stores.recording import KEEP, THIN

#: Voxels of each snapshot (the summary's top voxels; the API's largest top_k).
RECORD_TOP_K = 100


@dataclass(frozen=True)
class Frame:
    """One frame of a recording (module docstring); `summary` is None for an utterance that was not fused."""

    version: int
    at: float
    cause: dict[str, Any]
    target_label: str
    summary: dict[str, Any] | None
    utterance: dict[str, Any] | None = None  # {"text", "fused", "reason", "hypotheses", "mixture"}
    scene_graph: dict[str, Any] | None = None

    @property
    def keep(self) -> bool:
        """Never thinned: an utterance's frame, and a frame carrying a scene graph (the first, or a
        replacement: the only frame that holds the graph that later frames are about)."""
        return (
            self.utterance is not None or self.scene_graph is not None or self.cause.get("kind") == "created"
        )

    def pack(self) -> bytes:
        fields = [self.version, self.at, self.cause, self.target_label, self.summary]
        packed: bytes = msgpack.packb([*fields, self.utterance, self.scene_graph], use_bin_type=True)
        return (KEEP if self.keep else THIN) + packed

    @classmethod
    def unpack(cls, data: bytes) -> Frame:
        return cls(*msgpack.unpackb(data[1:], raw=False))

    def to_json(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "at": self.at,
            "cause": self.cause,
            "target_label": self.target_label or None,
            "summary": self.summary,
            "utterance": self.utterance,
            "scene_graph": self.scene_graph,
        }


def utterance_part(text: str, fused: bool, reason: str | None, grounding: Grounding) -> dict[str, Any]:
    """An utterance as a frame holds it: its text, verdict, hypotheses and mixture (the API's JSON forms)."""
    mixture = grounding.mixture
    owners = grounding.component_hypotheses()
    components = [
        {"weight": float(w), "mean": m.tolist(), "covariance": c.tolist(), "hypothesis": h}
        for w, m, c, h in zip(mixture.weights, mixture.means, mixture.covariances, owners, strict=True)
    ]
    uniform = [
        {"weight": float(v), "low": lo.tolist(), "high": hi.tolist()}
        for v, lo, hi in zip(mixture.box_weights, mixture.box_lows, mixture.box_highs, strict=True)
    ]
    hypotheses = [{"text": h.text, "weight": float(h.weight)} for h in grounding.hypotheses]
    return {
        "text": text,
        "fused": fused,
        "reason": reason,
        "hypotheses": hypotheses,
        "mixture": {"components": components, "uniform": uniform},
    }


def scene_graph_part(scene_graph: SceneGraph) -> dict[str, Any]:
    """The scene graph's JSON, without the objects' free-form attributes (not drawn, possibly large)."""
    data: dict[str, Any] = scene_graph.model_dump(
        mode="json", exclude={"objects": {"__all__": {"attributes"}}}
    )
    return data


def merged(frames: Sequence[Frame]) -> list[Frame]:
    """Frames in version order, one per version: two recorders that read the same version (module
    docstring) leave two frames of it, merged here (the first's summary, either's utterance or scene graph).
    An unfused utterance's frame follows its version's."""
    out: dict[int, Frame] = {}
    unfused: list[Frame] = []
    for frame in frames:
        first = out.get(frame.version)
        if frame.summary is None:
            unfused.append(frame)
        elif first is None:
            out[frame.version] = frame
        else:
            out[frame.version] = Frame(
                first.version,
                first.at,
                first.cause if first.utterance or first.scene_graph else frame.cause,
                first.target_label,
                first.summary,
                first.utterance or frame.utterance,
                first.scene_graph or frame.scene_graph,
            )
    return sorted([*out.values(), *unfused], key=lambda f: (f.version, f.summary is None, f.at))
