"""Raw label vocabularies: how maps built by other pipelines name the objects of ours.

A deployed map's labels come from whatever detector or dataset built it, not from the words people use.
The builder renames a case's map objects into one of these vocabularies (the utterance keeps naming target
and anchors as a speaker would, from the clean labels):

* "nyu" (ScanNet layouts): the NYU class names of VLA-3D's `nyu_label` / `nyu40_label` columns. Where the
  VLA-3D sample scene (`vla3d_format_example/scene0010_01_object_result.csv`) shows a ScanNet label, its
  `nyu_label` is used (trash can -> garbage bin, doorframe -> door, shelf -> shelves, file cabinet -> cabinet,
  computer tower -> computer, books -> book, papers -> paper); the others are the NYU40 class that the label
  plainly belongs to (office chair -> chair, kitchen cabinets -> cabinet, tv -> television, refrigerator ->
  NYU40's own spelling "refridgerator"). Labels whose NYU40 class is a catch-all (otherprop,
  otherfurniture) keep their ScanNet name: a map that says "otherprop" names nothing a grounder could use.
* "ai2thor_types" (AI2-THOR layouts): the simulator's raw CamelCase object types ("DiningTable",
  "CounterTop", "SinkBasin"), as AI2-THOR's own metadata names them.
"""

from __future__ import annotations

from collections.abc import Mapping

NATIVE = "native"
NYU = "nyu"
AI2THOR_TYPES = "ai2thor_types"

SCANNET_TO_NYU: dict[str, str] = {
    # From the VLA-3D sample scene's raw_label -> nyu_label pairs.
    "trash can": "garbage bin",
    "doorframe": "door",
    "shelf": "shelves",
    "file cabinet": "cabinet",
    "computer tower": "computer",
    "books": "book",
    "papers": "paper",
    # The NYU40 class each label belongs to.
    "office chair": "chair",
    "armchair": "chair",
    "sofa chair": "chair",
    "couch": "sofa",
    "kitchen cabinets": "cabinet",
    "kitchen cabinet": "cabinet",
    "cabinets": "cabinet",
    "bathroom cabinet": "cabinet",
    "kitchen counter": "counter",
    "bathroom counter": "counter",
    "coffee table": "table",
    "end table": "table",
    "dining table": "table",
    "side table": "table",
    "doors": "door",
    "closet door": "door",
    "tv": "television",
    "nightstand": "night stand",
    "refrigerator": "refridgerator",
    "mini fridge": "refridgerator",
    "trash bin": "garbage bin",
    "clothing": "clothes",
    "curtains": "curtain",
    "windows": "window",
}


def vocabulary_of(source: str) -> str:
    """The raw vocabulary a map of this source is renamed into."""
    return AI2THOR_TYPES if source == "ai2thor" else NYU


def renamed_labels(source: str, labels: Mapping[str, str], raw_labels: Mapping[str, str]) -> dict[str, str]:
    """Object id -> label in the source's raw vocabulary, for every object whose label changes.

    `labels` are the objects' clean labels by id, `raw_labels` the labels as the source file writes them.
    """
    if source == "ai2thor":
        return {i: raw_labels[i] for i, label in labels.items() if raw_labels.get(i, label) != label}
    return {i: SCANNET_TO_NYU[label] for i, label in labels.items() if label in SCANNET_TO_NYU}
