"""A recording drawn top-down (`vlmap record --png`): what Foxglove's 3D panel shows of its last frame, seen
from above: object boxes with their labels, region outlines, the belief's top voxels coloured by probability,
the last mixture's Gaussians as their 2-sigma ellipses, the MAP voxel and the posterior mean.

It reads the MCAP back with the `mcap` package and decodes the Foxglove messages from the schemas the file
carries (`mcap-protobuf-support`): development packages (requirements-dev.lock), like matplotlib.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory


class JsonDecoderFactory(DecoderFactory):
    """Decodes the JSON topics (`/vlmap/<s>/summary`)."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


def decoded_messages(path_or_data: Path | bytes) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time in ns, decoded message) of every message of an MCAP file, in log-time order."""
    data = path_or_data if isinstance(path_or_data, bytes) else path_or_data.read_bytes()
    reader = make_reader(io.BytesIO(data), decoder_factories=[ProtobufDecoderFactory(), JsonDecoderFactory()])
    for _, channel, message, decoded in reader.iter_decoded_messages():
        yield channel.topic, message.log_time, decoded


def last_messages(path_or_data: Path | bytes) -> dict[str, Any]:
    """The last message of each topic, by its name within the session (`belief`, `mixture`, ...)."""
    return {topic.rsplit("/", 1)[1]: message for topic, _, message in decoded_messages(path_or_data)}


def _yaw_of(q: Any) -> float:
    return 2 * math.atan2(q.z, q.w)


def _shadow(sphere: Any) -> tuple[float, float, float]:
    """The top-down outline of an ellipsoid (width, height, angle in degrees): the 2-D marginal of the
    quadratic form its axes and rotation make."""
    import numpy as np

    q, size = sphere.pose.orientation, sphere.size
    x, y, z, w = q.x, q.y, q.z, q.w
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    form = rotation @ np.diag(np.array([size.x, size.y, size.z]) ** 2 / 4) @ rotation.T
    values, vectors = np.linalg.eigh(form[:2, :2])
    angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
    return 2 * math.sqrt(max(values[1], 0.0)), 2 * math.sqrt(max(values[0], 0.0)), angle


def render_png(mcap_path: Path, png_path: Path) -> None:
    """Draw the recording's last frame top-down to `png_path` (module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, Polygon, Rectangle

    last = last_messages(mcap_path)
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    for entity in getattr(last.get("scene_graph"), "entities", []):
        for cube in entity.cubes:
            c, s, yaw = cube.pose.position, cube.size, _yaw_of(cube.pose.orientation)
            corners = [(-s.x / 2, -s.y / 2), (s.x / 2, -s.y / 2), (s.x / 2, s.y / 2), (-s.x / 2, s.y / 2)]
            cos, sin = math.cos(yaw), math.sin(yaw)
            xy = [(c.x + cos * dx - sin * dy, c.y + sin * dx + cos * dy) for dx, dy in corners]
            ax.add_patch(Polygon(xy, closed=True, facecolor="none", edgecolor="0.35", lw=0.8))
            for text in entity.texts:
                ax.annotate(text.text, (c.x, c.y), fontsize=6, ha="center", va="center", color="0.25")
        for line in entity.lines:
            xs, ys = [p.x for p in line.points], [p.y for p in line.points]
            ax.add_patch(
                Rectangle(
                    (min(xs), min(ys)), max(xs) - min(xs), max(ys) - min(ys), fill=False, ls="--", ec="C0"
                )
            )
    cloud = last.get("belief")
    if cloud is not None and cloud.data:
        points = [
            struct.unpack_from("<4f", cloud.data, i) for i in range(0, len(cloud.data), cloud.point_stride)
        ]
        xs, ys, ps = [p[0] for p in points], [p[1] for p in points], [p[3] for p in points]
        scatter = ax.scatter(xs, ys, c=ps, cmap="viridis", s=14, zorder=3)
        fig.colorbar(scatter, ax=ax, shrink=0.6, label="posterior probability (top voxels)")
    for entity in getattr(last.get("mixture"), "entities", []):
        for sphere in entity.spheres:
            c = sphere.pose.position
            width, height, angle = _shadow(sphere)
            ax.add_patch(
                Ellipse((c.x, c.y), width, height, angle=angle, fill=False, ec="C3", lw=1.2, zorder=4)
            )
        for text in entity.texts:
            p = text.pose.position
            ax.annotate(text.text, (p.x, p.y), fontsize=6, color="C3", zorder=5)
    for entity in getattr(last.get("estimate"), "entities", []):
        for cube in entity.cubes:
            ax.plot(cube.pose.position.x, cube.pose.position.y, "r*", ms=11, zorder=6, label="MAP voxel")
        for sphere in entity.spheres:
            ax.plot(
                sphere.pose.position.x, sphere.pose.position.y, "bx", ms=8, zorder=6, label="posterior mean"
            )
    summary = last.get("summary") or {}
    ax.set_title(f"VL-Map recording, version {summary.get('version', '?')}: belief, mixture (2 sigma), boxes")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(png_path)
    plt.close(fig)
