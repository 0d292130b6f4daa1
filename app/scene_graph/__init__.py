"""Scene graphs: the native model and the readers that normalise other formats into it."""

from app.scene_graph.model import Region, SceneGraph, SceneObject

__all__ = ["Region", "SceneGraph", "SceneObject"]
