"""Hand-written spatial grounders: where a relation puts the target, from the anchor's box alone.

`GeometricGrounder` turns each hypothesis into a Gaussian whose mean sits where the relation points
(on the top surface, inside the box, around it, under it, ...) and whose covariance spreads over the
region the relation allows (a uniform distribution over an interval of width w has variance w^2/12).
`FixedGrounder` is the overconfident behaviour of the reference's foundation-model baselines:
the anchor centroid with a fixed 0.1 m standard deviation.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from app.grounding.hypotheses import Hypothesis
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox, map_box
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, SceneObject


@dataclass(frozen=True)
class GeometricConfig:
    """The spreads (metres) each relation allows beyond the anchor's own extent."""

    target_half_height: float = 0.10  # a small object's centre sits this far above its support
    vertical_sigma: float = 0.10  # height uncertainty for on/in
    near_margin: float = 0.75  # "near": up to this far from the anchor's surface
    near_vertical_sigma: float = 0.40
    closest_margin: float = 0.50
    above_height: float = 0.50  # "above": centre this far over the anchor's top
    above_vertical_sigma: float = 0.25
    below_clearance: float = 0.30  # anchors whose bottom is this close to the floor stand on it
    between_lateral_sigma: float = 0.30


def _rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box_covariance(obj: SceneObject, sigma_z: float) -> np.ndarray:
    """Uniform over the object's (yawed) footprint in x, y: R diag(dx^2/12, dy^2/12, sigma_z^2) R^T."""
    dx, dy, _ = obj.size
    rot = _rotation(obj.yaw)
    covariance: np.ndarray = rot @ np.diag([dx * dx / 12.0, dy * dy / 12.0, sigma_z * sigma_z]) @ rot.T
    return covariance


class GeometricGrounder:
    """Documented, learning-free Gaussians for on/in/near/between/above/below/closest/farthest."""

    name = "geometric"
    version = "1"

    def __init__(self, config: GeometricConfig | None = None) -> None:
        self.config = config or GeometricConfig()

    def describe(self) -> dict[str, Any]:
        config = asdict(self.config)
        digest = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()
        return {"name": self.name, "version": self.version, "config": config, "checksum": f"sha256:{digest}"}

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        floor_z = float(scene_graph.bounds()[0][2])
        return [GaussianMixture.of(self.ground_one(scene_graph, h, floor_z)) for h in hypotheses]

    def ground_one(self, scene_graph: SceneGraph, hypothesis: Hypothesis, floor_z: float) -> Gaussian:
        if not hypothesis.anchor_ids:
            return region_gaussian(scene_graph, hypothesis.region_id)
        cfg = self.config
        anchors = [scene_graph.object(i) for i in hypothesis.anchor_ids]
        first = anchors[0]
        center = np.asarray(first.center, dtype=np.float64)
        top = float(first.max_corner[2])
        relation = hypothesis.relation
        if relation is Relation.BETWEEN and len(anchors) == 2:
            return self._between(anchors[0], anchors[1])
        if relation is Relation.ON:
            mean = np.array([center[0], center[1], top + cfg.target_half_height])
            return Gaussian(mean, _box_covariance(first, cfg.vertical_sigma))
        if relation is Relation.IN:
            dz = first.size[2]
            cov = _box_covariance(first, dz / math.sqrt(12.0))
            return Gaussian(center.copy(), cov)
        if relation is Relation.ABOVE:
            mean = np.array([center[0], center[1], top + cfg.above_height])
            return Gaussian(mean, _box_covariance(first, cfg.above_vertical_sigma))
        if relation is Relation.BELOW:
            bottom = float(first.min_corner[2])
            standing = bottom - floor_z < cfg.below_clearance
            # Under a table: on the floor within its footprint. Under a shelf or a hanging object: beneath it.
            z = floor_z + cfg.target_half_height if standing else bottom - cfg.below_clearance
            return Gaussian(np.array([center[0], center[1], z]), _box_covariance(first, cfg.vertical_sigma))
        if relation is Relation.FARTHEST:
            return self._farthest(scene_graph, first)
        margin = cfg.closest_margin if relation is Relation.CLOSEST else cfg.near_margin
        # Near: a ring around the box, approximated by an isotropic spread of half-extent plus margin.
        half = first.half_extent
        sigma_xy = 0.5 * (max(half[0], half[1]) + margin)
        cov = np.diag([sigma_xy**2, sigma_xy**2, cfg.near_vertical_sigma**2])
        return Gaussian(center.copy(), cov)

    def _between(self, a: SceneObject, b: SceneObject) -> Gaussian:
        """Centred on the midpoint; uniform along the segment joining the anchors, narrow across it."""
        ca, cb = np.asarray(a.center, dtype=np.float64), np.asarray(b.center, dtype=np.float64)
        mid = 0.5 * (ca + cb)
        axis = cb - ca
        length = float(np.linalg.norm(axis))
        lateral = self.config.between_lateral_sigma
        if length < 1e-6:
            return Gaussian(mid, np.eye(3) * lateral**2)
        u = axis / length
        along_var = max(length * length / 12.0, lateral**2)
        cov = along_var * np.outer(u, u) + lateral**2 * (np.eye(3) - np.outer(u, u))
        return Gaussian(mid, cov)

    def _farthest(self, scene_graph: SceneGraph, anchor: SceneObject) -> Gaussian:
        """The far side of the map: the anchor mirrored through the map's centre, a quarter of it wide."""
        low, high = scene_graph.bounds()
        centre = 0.5 * (low + high)
        mean = 2.0 * centre - np.asarray(anchor.center, dtype=np.float64)
        mean = np.clip(mean, low, high)
        mean[2] = float(np.asarray(anchor.center)[2])
        spread = np.maximum(0.25 * (high - low), 0.3)
        return Gaussian(mean, np.diag(spread**2))


class FixedGrounder:
    """The anchor(s)' centroid with a fixed isotropic 0.1 m standard deviation (an overconfident baseline)."""

    name = "fixed"
    version = "1"
    sigma = 0.1

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {"sigma": self.sigma}, "checksum": None}

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        out = []
        for h in hypotheses:
            if not h.anchor_ids:
                out.append(GaussianMixture.of(region_gaussian(scene_graph, h.region_id)))
                continue
            centers = np.array([scene_graph.object(i).center for i in h.anchor_ids], dtype=np.float64)
            out.append(GaussianMixture.of(Gaussian(centers.mean(axis=0), np.eye(3) * self.sigma**2)))
        return out


def region_gaussian(scene_graph: SceneGraph, region_id: str | None) -> Gaussian:
    """A region hypothesis (no anchor object) for the hand-written grounders: the Gaussian with the moments
    of the uniform density over the region's box, or the map's (`map_box`) when the region is unknown."""
    region = next((r for r in scene_graph.regions if r.id == region_id), None)
    if region is None:
        box = map_box(scene_graph)
    else:
        half = 0.5 * np.asarray(region.size, dtype=np.float64)
        box = UniformBox.around(np.asarray(region.center) - half, np.asarray(region.center) + half)
    return Gaussian(box.center, box.covariance)
