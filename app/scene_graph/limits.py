"""Limits every scene graph and coordinate a request brings must respect, whatever its format."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from app.errors import InvalidInput, LimitExceeded
from app.scene_graph.model import SceneGraph


def check_coordinates(field: str, vectors: Sequence[Sequence[float]], max_abs: float) -> None:
    """InvalidInput unless every number of `vectors` lies within +-`max_abs` metres: a map spans metres to
    kilometres, and squares of larger numbers (a covariance, a distance) overflow downstream."""
    values = np.asarray(vectors, dtype=np.float64)
    if values.size and not np.all(np.abs(values) <= max_abs):
        msg = f"coordinates and sizes must lie within +-{max_abs:g} m"
        raise InvalidInput(msg, field=field)


def check_scene_graph(
    scene_graph: SceneGraph,
    *,
    max_objects: int,
    max_regions: int,
    max_coordinate_m: float,
    field: str = "scene_graph",
) -> SceneGraph:
    """The scene graph, once within the limits on objects, regions and coordinates."""
    if len(scene_graph.objects) > max_objects:
        msg = f"{field}: {len(scene_graph.objects)} objects exceed the limit of {max_objects}"
        raise LimitExceeded(msg, limit_name="max_objects")
    if len(scene_graph.regions) > max_regions:
        msg = f"{field}: {len(scene_graph.regions)} regions exceed the limit of {max_regions}"
        raise LimitExceeded(msg, limit_name="max_regions")
    objects = [v for o in scene_graph.objects for v in (o.center, o.size)]
    check_coordinates(f"{field}.objects", objects, max_coordinate_m)
    check_coordinates(
        f"{field}.regions", [v for r in scene_graph.regions for v in (r.center, r.size)], max_coordinate_m
    )
    return scene_graph
