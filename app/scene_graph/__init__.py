"""Scene graphs: the native model and the readers that normalise other formats into it.

`__all__` is what the other rooms use: the model (`model`), the limits a service applies (`limits`), the
format detection and parsing (`loader`), the region-grouped form the LLM prompts use (`region_grouped`) and
the VLA-3D scenes (`vla3d`). The Hydra / Spark-DSG reader (`app.scene_graph.hydra`) is imported only by the
loader, when a binary graph arrives (it needs spark_dsg).
"""

from app.scene_graph.limits import check_coordinates, check_scene_graph
from app.scene_graph.loader import SceneGraphFormat, parse_scene_graph
from app.scene_graph.model import (
    MAX_OBJECTS_CEILING,
    MAX_REGIONS_CEILING,
    Id,
    Region,
    SceneGraph,
    SceneObject,
    Vec3,
)
from app.scene_graph.region_grouped import region_integer_ids, to_region_grouped
from app.scene_graph.vla3d import STATEMENTS_FILE_SUFFIX, list_vla3d_scenes, load_vla3d_scene

__all__ = [
    "MAX_OBJECTS_CEILING",
    "MAX_REGIONS_CEILING",
    "STATEMENTS_FILE_SUFFIX",
    "Id",
    "Region",
    "SceneGraph",
    "SceneGraphFormat",
    "SceneObject",
    "Vec3",
    "check_coordinates",
    "check_scene_graph",
    "list_vla3d_scenes",
    "load_vla3d_scene",
    "parse_scene_graph",
    "region_integer_ids",
    "to_region_grouped",
]
