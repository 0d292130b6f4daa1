"""The grounding-case file (JSONL, one case a line): the project's evaluation and training interface.

    {"case_id": str, "scene_graph": <native SceneGraph>, "utterance": str,
     "target": {"label": str, "position": [x, y, z], "size": [dx, dy, dz] | null},
     "hypotheses": [{"anchor_ids": [str, ...], "relation": str}] | null,  # ground truth when known
     "meta": {...}}  # free-form: source, scene_id, ambiguity

The target is absent from `scene_graph`; `hypotheses` hold the true grounding (first = the one used).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from app.errors import InvalidInput
from app.files import atomic_write
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, Vec3


class CaseTarget(BaseModel):
    model_config = ConfigDict(extra="forbid")

    label: str
    position: Vec3
    size: Vec3 | None = None


class CaseHypothesis(BaseModel):
    model_config = ConfigDict(extra="forbid")

    anchor_ids: list[str] = Field(min_length=1, max_length=2)
    relation: Relation


class GroundingCase(BaseModel):
    """One utterance about a target that was removed from its scene graph."""

    model_config = ConfigDict(extra="forbid")

    case_id: str
    scene_graph: SceneGraph
    utterance: str
    target: CaseTarget
    hypotheses: list[CaseHypothesis] | None = None
    meta: dict[str, Any] = Field(default_factory=dict)


def case_room(case: GroundingCase) -> str:
    """The room (or house) a case is about: its `meta.scene_id` when the file says, else the case itself.
    Cases of one room err together, so a bootstrap of their mean resamples rooms."""
    scene = case.meta.get("scene_id")
    return str(scene) if scene else case.case_id


def read_cases(path: str | Path) -> Iterator[GroundingCase]:
    """Cases of a JSONL file, in order; a bad line raises with its line number."""
    with Path(path).open(encoding="utf-8") as fh:
        for number, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                yield GroundingCase.model_validate_json(line)
            except ValueError as exc:
                msg = f"{path}:{number}: not a grounding case: {exc}"
                raise InvalidInput(msg, field=f"{path}:{number}") from exc


def write_cases(path: str | Path, cases: Iterable[GroundingCase]) -> int:
    """Write cases as JSONL, replacing `path` once complete; returns how many were written."""
    count = 0
    with atomic_write(path) as fh:
        for case in cases:
            fh.write(case.model_dump_json(exclude_none=True))
            fh.write("\n")
            count += 1
    return count
