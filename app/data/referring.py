"""Human referring expressions (target known, anchor not) as grounding cases.

Each expression names one object of a scan by its id (`{"scene_id", "target_id", "target_label",
"utterance", "source"}`, as in `human_referring_train.jsonl`). A case keeps the utterance, removes the
target from the scan's scene graph (boxes from a scenes file: `{"scene_id", "objects": [{"id", "label",
"center", "size"}]}`; no regions, as the development files have none) and holds its true position.
`hypotheses` stay empty (the anchor the speaker meant is not known), so the cases train and score the whole
language sensor on its mixture, not a given reading. Expressions whose scene or target is missing are
counted and skipped.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.data.cases import CaseTarget, GroundingCase
from app.scene_graph.model import SceneGraph, SceneObject
from app.vocabulary import same_class

__all__ = ["ReferringReport", "referring_cases", "scene_objects"]


@dataclass
class ReferringReport:
    """Expressions read, cases written, and skips by reason."""

    expressions: int = 0
    cases: int = 0
    skipped: Counter[str] = field(default_factory=Counter)


def scene_objects(path: Path) -> dict[str, list[SceneObject]]:
    """scene id -> its objects, from a scenes file."""
    scenes: dict[str, list[SceneObject]] = {}
    with Path(path).open(encoding="utf-8") as fh:
        for line in fh:
            if not line.strip():
                continue
            raw = json.loads(line)
            scenes[str(raw["scene_id"])] = [
                SceneObject(
                    id=str(o["id"]),
                    label=str(o["label"]).strip().lower(),
                    center=[float(v) for v in o["center"]],
                    size=[max(float(v), 0.01) for v in o["size"]],
                )
                for o in raw["objects"]
            ]
    return scenes


def referring_cases(
    expressions: Path,
    scenes: dict[str, list[SceneObject]],
    report: ReferringReport | None = None,
    progress: bool = False,
) -> Iterator[GroundingCase]:
    """One case per expression, in file order (case ids "<source>/<scene>/<target>/<line>"); `progress`
    shows a bar of the lines read."""
    from tqdm import tqdm

    report = report if report is not None else ReferringReport()
    with Path(expressions).open(encoding="utf-8") as fh:
        lines = tqdm(fh, desc="expressions", unit="line", disable=not progress)
        for number, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            raw: dict[str, Any] = json.loads(line)
            report.expressions += 1
            objects = scenes.get(str(raw["scene_id"]))
            if objects is None:
                report.skipped["scene_missing"] += 1
                continue
            target_id = str(raw["target_id"])
            target = next((o for o in objects if o.id == target_id), None)
            if target is None:
                report.skipped["target_missing"] += 1
                continue
            others = [o for o in objects if o.id != target_id]
            if not others:
                report.skipped["empty_scene"] += 1
                continue
            report.cases += 1
            source = str(raw.get("source", "human"))
            yield GroundingCase(
                case_id=f"{source}/{raw['scene_id']}/{target_id}/{number}",
                scene_graph=SceneGraph(frame_id=str(raw["scene_id"]), objects=others),
                utterance=str(raw["utterance"]),
                target=CaseTarget(label=target.label, position=list(target.center), size=list(target.size)),
                hypotheses=[],
                meta={
                    "source": source,
                    "scene_id": str(raw["scene_id"]),
                    "target_id": target_id,
                    "same_class_distractors": sum(same_class(o.label, target.label) for o in others),
                },
            )
