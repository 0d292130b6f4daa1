"""Recording frames (the JSON of `GET /v1/sessions/{id}/recording`, `app.sessions.recording.Frame.to_json`) as
Foxglove messages on the topics of `app.foxglove`: pure functions, shared by the live server and the MCAP
recording, so that both publish the same topics with the same schemas."""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove.messages import (
    Color,
    CubePrimitive,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

Json = Mapping[str, Any]
#: A message for one topic: a Foxglove message, or a dict for the JSON topic.
Message = SceneUpdate | PointCloud | Log | dict[str, Any]

#: Half-axes of a drawn Gaussian, in standard deviations: its 2-sigma surface.
SIGMAS = 2.0
#: Gaussians lighter than this are not drawn (a mixture's broad tail terms), nor their labels.
MIN_DRAWN_WEIGHT = 0.01
#: Hypotheses an utterance's log line names.
LOGGED_HYPOTHESES = 3
#: Colour stops of the probability ramp (viridis, from low to high).
_RAMP = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.231, 0.322, 0.545],
        [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ]
)
_POINT_FIELDS = [
    PackedElementField(name=name, offset=4 * i, type=PackedElementFieldNumericType.Float32)
    for i, name in enumerate(("x", "y", "z", "probability"))
] + [
    PackedElementField(name=name, offset=16 + i, type=PackedElementFieldNumericType.Uint8)
    for i, name in enumerate(("red", "green", "blue", "alpha"))
]
_POINT = struct.Struct("<4f4B")


@dataclass(frozen=True)
class Topics:
    """The topic names of one session (`app.foxglove`)."""

    session_id: str

    def _topic(self, name: str) -> str:
        return f"/vlmap/{self.session_id}/{name}"

    @property
    def scene_graph(self) -> str:
        return self._topic("scene_graph")

    @property
    def belief(self) -> str:
        return self._topic("belief")

    @property
    def estimate(self) -> str:
        return self._topic("estimate")

    @property
    def summary(self) -> str:
        return self._topic("summary")

    @property
    def mixture(self) -> str:
        return self._topic("mixture")

    @property
    def utterances(self) -> str:
        return self._topic("utterances")


def ramp(fraction: float) -> tuple[float, float, float]:
    """The colour of a probability at `fraction` (0..1) of the frame's largest."""
    x = min(max(fraction, 0.0), 1.0) * (len(_RAMP) - 1)
    i = min(int(x), len(_RAMP) - 2)
    r, g, b = _RAMP[i] + (x - i) * (_RAMP[i + 1] - _RAMP[i])
    return float(r), float(g), float(b)


def _stamp(at: float) -> Timestamp:
    return Timestamp.from_epoch_secs(at)


def _vector(values: Sequence[float]) -> Vector3:
    return Vector3(x=float(values[0]), y=float(values[1]), z=float(values[2]))


def _pose(center: Sequence[float], quaternion: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> Pose:
    qx, qy, qz, qw = (float(q) for q in quaternion)
    return Pose(position=_vector(center), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def _yaw(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a proper rotation matrix, by Shepperd's method.

    4w^2, 4x^2, 4y^2 and 4z^2 are read off the diagonal; the largest (at least 1) gives its component, and
    the off-diagonal sums and differences divided by it give the others with their signs. Taking every sign
    from a difference instead fails near a half turn, where the differences vanish into rounding.
    """
    m = rotation
    squares = (  # 4w^2, 4x^2, 4y^2, 4z^2
        1.0 + m[0, 0] + m[1, 1] + m[2, 2],
        1.0 + m[0, 0] - m[1, 1] - m[2, 2],
        1.0 - m[0, 0] + m[1, 1] - m[2, 2],
        1.0 - m[0, 0] - m[1, 1] + m[2, 2],
    )
    largest = max(range(4), key=squares.__getitem__)
    s = 2.0 * math.sqrt(squares[largest])  # 4 times the largest component
    if largest == 0:
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    if largest == 1:
        return (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    if largest == 2:
        return ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    return ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)


def ellipsoid(mean: Sequence[float], covariance: Sequence[Sequence[float]], color: Color) -> SpherePrimitive:
    """A Gaussian's `SIGMAS`-sigma surface: its principal axes, `SIGMAS` standard deviations each way."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, dtype=np.float64))
    if np.linalg.det(vectors) < 0:  # a reflection: flip one axis to make it a rotation
        vectors[:, 0] = -vectors[:, 0]
    diameters = 2 * SIGMAS * np.sqrt(np.clip(values, 0.0, None))
    return SpherePrimitive(pose=_pose(mean, _quaternion(vectors)), size=_vector(diameters), color=color)


def _label(center: Sequence[float], text: str, color: Color | None = None) -> TextPrimitive:
    white = Color(r=1.0, g=1.0, b=1.0, a=1.0)
    return TextPrimitive(
        pose=_pose(center),
        billboard=True,
        font_size=14.0,
        scale_invariant=True,
        color=color or white,
        text=text,
    )


def _wire_box(
    low: Sequence[float] | np.ndarray, high: Sequence[float] | np.ndarray, color: Color
) -> LinePrimitive:
    """An axis-aligned box's twelve edges."""
    corners = [
        Point3(x=float(x), y=float(y), z=float(z))
        for x in (low[0], high[0])
        for y in (low[1], high[1])
        for z in (low[2], high[2])
    ]
    edges = [0, 1, 2, 3, 4, 5, 6, 7, 0, 2, 1, 3, 4, 6, 5, 7, 0, 4, 1, 5, 2, 6, 3, 7]
    return LinePrimitive(
        type=LinePrimitiveLineType.LineList,
        thickness=2.0,
        scale_invariant=True,
        points=corners,
        indices=edges,
        color=color,
    )


def _replace_all(at: float, entities: list[SceneEntity]) -> SceneUpdate:
    """An update that clears what the topic showed, then shows `entities`."""
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=_stamp(at), type=SceneEntityDeletionType.All)],
        entities=entities,
    )


def scene_graph_update(scene_graph: Json, at: float) -> SceneUpdate:
    """Each object as a translucent box (yawed) with its label above it; each region as a wireframe box."""
    frame_id = str(scene_graph.get("frame_id") or "map")
    box, region_colour = Color(r=0.95, g=0.6, b=0.2, a=0.3), Color(r=0.4, g=0.7, b=1.0, a=0.8)
    entities = []
    for obj in scene_graph.get("objects", []):
        center, size = obj["center"], obj["size"]
        above = (center[0], center[1], center[2] + size[2] / 2 + 0.1)
        entities.append(
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id=f"object/{obj['id']}",
                cubes=[
                    CubePrimitive(
                        pose=_pose(center, _yaw(float(obj.get("yaw", 0.0)))), size=_vector(size), color=box
                    )
                ],
                texts=[_label(above, f"{obj['label']} {obj['id']}")],
            )
        )
    for region in scene_graph.get("regions", []):
        center, half = np.asarray(region["center"]), np.asarray(region["size"]) / 2
        name = region.get("name") or region["id"]
        entities.append(
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id=f"region/{region['id']}",
                lines=[_wire_box(center - half, center + half, region_colour)],
                texts=[_label((center[0], center[1], center[2] + half[2]), str(name), region_colour)],
            )
        )
    return _replace_all(at, entities)


def belief_cloud(summary: Json, at: float, frame_id: str) -> PointCloud:
    """The summary's top voxels as points, coloured by their probability relative to the largest."""
    voxels = summary.get("top_voxels", [])
    top = max((float(v["probability"]) for v in voxels), default=0.0) or 1.0
    data = bytearray()
    for voxel in voxels:
        p = float(voxel["probability"])
        r, g, b = ramp(p / top)
        x, y, z = voxel["center"]
        data += _POINT.pack(x, y, z, p, round(255 * r), round(255 * g), round(255 * b), 255)
    return PointCloud(
        timestamp=_stamp(at),
        frame_id=frame_id,
        pose=_pose((0.0, 0.0, 0.0)),
        point_stride=_POINT.size,
        fields=_POINT_FIELDS,
        data=bytes(data),
    )


def estimate_update(summary: Json, at: float, frame_id: str, voxel_size: float) -> SceneUpdate:
    """The MAP voxel as a cube, and the posterior mean with its covariance as a 2-sigma ellipsoid."""
    best = summary["map_voxel"]
    mean = summary["mean"]
    red, blue = Color(r=1.0, g=0.1, b=0.1, a=0.9), Color(r=0.2, g=0.5, b=1.0, a=0.25)
    side = _vector((voxel_size, voxel_size, voxel_size))
    return _replace_all(
        at,
        [
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id="map_voxel",
                cubes=[CubePrimitive(pose=_pose(best["center"]), size=side, color=red)],
                texts=[_label(best["center"], f"MAP p={float(best['probability']):.3g}", red)],
            ),
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id="posterior",
                spheres=[ellipsoid(mean, summary["covariance"], blue)],
                texts=[_label(mean, f"mean, H={float(summary['entropy_nats']):.2f} nats", blue)],
            ),
        ],
    )


def mixture_update(utterance: Json, at: float, frame_id: str) -> SceneUpdate:
    """One ellipsoid per Gaussian of the utterance's mixture at its 2-sigma surface, labelled with its
    hypothesis's text and its weight; each uniform box as a wireframe."""
    hypotheses = utterance.get("hypotheses", [])
    mixture = utterance["mixture"]
    entities = []
    for k, component in enumerate(mixture["components"]):
        weight = float(component["weight"])
        if weight < MIN_DRAWN_WEIGHT:
            continue
        owner = component.get("hypothesis")
        text = hypotheses[owner]["text"] if owner is not None and owner < len(hypotheses) else "broad prior"
        r, g, b = ramp(weight / max(float(c["weight"]) for c in mixture["components"]))
        color = Color(r=r, g=g, b=b, a=0.35)
        entities.append(
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id=f"component/{k}",
                spheres=[ellipsoid(component["mean"], component["covariance"], color)],
                texts=[_label(component["mean"], f"{text} (w={weight:.2f})")],
            )
        )
    for b, box in enumerate(mixture.get("uniform", [])):
        entities.append(
            SceneEntity(
                timestamp=_stamp(at),
                frame_id=frame_id,
                id=f"uniform/{b}",
                lines=[_wire_box(box["low"], box["high"], Color(r=0.7, g=0.7, b=0.7, a=0.5))],
            )
        )
    return _replace_all(at, entities)


def utterance_log(utterance: Json, at: float) -> Log:
    """An utterance as a log line: its text, whether it was fused, and its best hypotheses."""
    ranked = sorted(utterance.get("hypotheses", []), key=lambda h: -float(h["weight"]))[:LOGGED_HYPOTHESES]
    readings = "; ".join(f"{h['text']} ({float(h['weight']):.2f})" for h in ranked) or "no hypothesis"
    verdict = "fused" if utterance.get("fused") else "not fused"
    why = f" ({utterance['reason']})" if utterance.get("reason") else ""
    return Log(
        timestamp=_stamp(at),
        level=LogLevel.Info if utterance.get("fused") else LogLevel.Warning,
        message=f'"{utterance["text"]}": {verdict}{why}: {readings}',
        name="vlmap",
    )


def summary_json(frame: Json) -> dict[str, Any]:
    """The JSON topic's message: the version, its target class and its summary."""
    return {"version": frame["version"], "target_label": frame.get("target_label"), **frame["summary"]}


@dataclass
class Converter:
    """Frames of one session to messages, in order: it remembers the scene graph's frame id and the grid's
    voxel size, which later frames need but do not repeat."""

    topics: Topics
    voxel_size: float
    frame_id: str = "map"

    def messages(self, frame: Json) -> Iterator[tuple[str, Message]]:
        """(topic, message) for each message the frame makes (`app.foxglove` lists which)."""
        at = float(frame["at"])
        if frame.get("scene_graph") is not None:
            self.frame_id = str(frame["scene_graph"].get("frame_id") or "map")
            yield self.topics.scene_graph, scene_graph_update(frame["scene_graph"], at)
        utterance = frame.get("utterance")
        if utterance is not None and utterance.get("fused"):
            yield self.topics.mixture, mixture_update(utterance, at, self.frame_id)
        if frame.get("summary") is not None:
            yield self.topics.belief, belief_cloud(frame["summary"], at, self.frame_id)
            yield self.topics.estimate, estimate_update(frame["summary"], at, self.frame_id, self.voxel_size)
            yield self.topics.summary, summary_json(frame)
        if utterance is not None:
            yield self.topics.utterances, utterance_log(utterance, at)
