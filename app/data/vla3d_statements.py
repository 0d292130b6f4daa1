"""VLA-3D referential statements (`<scene>_referential_statements.json`) as grounding cases.

Each statement names a target object, a relation and one or two anchors by object index. A case keeps the
statement's utterance, removes the target from the scene graph read by `app.scene_graph.vla3d`, and holds
the true hypothesis (anchors, relation); the target position is the statement's own.

Relations: above, below, on, in, near, between, closest and farthest map one-to-one onto `Relation`.
"second_/third_closest" and "second_/third_farthest" are skipped, not mapped to closest/farthest: the target
is then *not* the closest instance, and the hypothesis would teach the wrong place. Other relations the
benchmark's scene graphs know ("beside", "hanging_on") are skipped too. Statements whose target or anchors
are missing from the scene graph (for instance "unknown"-labelled segments, which the reader leaves out) are
skipped. Every skip is counted by reason in the `ConversionReport`.

Any layout works: a folder holding one scene's files, or a tree of scene folders; every statements file
under the folder is converted, its scene read from the files beside it.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.data.cases import CaseHypothesis, CaseTarget, GroundingCase, write_cases
from app.errors import InvalidInput, InvalidSceneGraph
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph
from app.scene_graph.vla3d import STATEMENTS_FILE_SUFFIX, load_vla3d_scene

VLA3D_RELATIONS: dict[str, Relation] = {r.value: r for r in Relation}
_ANCHOR_KEYS = ("anchor_1", "anchor_2")
log = logging.getLogger(__name__)


@dataclass
class ConversionReport:
    """How many scenes and statements were read, cases written, and statements skipped (by reason)."""

    scenes: int = 0
    statements: int = 0
    cases: int = 0
    skipped: Counter[str] = field(default_factory=Counter)

    def to_json(self) -> dict[str, Any]:
        return {
            "scenes": self.scenes,
            "statements": self.statements,
            "cases": self.cases,
            "skipped": dict(sorted(self.skipped.items())),
        }


def statement_files(folder: str | Path) -> list[Path]:
    """Every `<scene>_referential_statements.json` in the folder or below it, sorted."""
    root = Path(folder)
    if root.is_file():
        return [root] if root.name.endswith(STATEMENTS_FILE_SUFFIX) else []
    if not root.is_dir():
        msg = f"{root} is neither a folder nor a statements file"
        raise InvalidInput(msg, "folder")
    return sorted(p for p in root.rglob(f"*{STATEMENTS_FILE_SUFFIX}") if p.is_file())


def _iter_statements(data: Mapping[str, Any]) -> Iterator[tuple[str, str, str, Mapping[str, Any]]]:
    """(region id, region name, utterance, statement) in file order."""
    regions = data.get("regions")
    if not isinstance(regions, Mapping):
        return
    for region_id, region in regions.items():
        if not isinstance(region, Mapping):
            continue
        name = region.get("region", "")
        for utterance, statements in region.items():
            if utterance == "region" or not isinstance(statements, list):
                continue
            for statement in statements:
                if isinstance(statement, Mapping):
                    yield str(region_id), str(name), utterance, statement


def _anchor_ids(statement: Mapping[str, Any], relation: Relation) -> list[str] | None:
    anchors = statement.get("anchors")
    if not isinstance(anchors, Mapping):
        return None
    ids = []
    for key in _ANCHOR_KEYS[: relation.n_anchors]:
        anchor = anchors.get(key)
        if not isinstance(anchor, Mapping) or anchor.get("index") is None:
            return None
        ids.append(str(anchor["index"]))
    return ids


def convert_statement(
    statement: Mapping[str, Any],
    utterance: str,
    graph: SceneGraph,
    case_id: str,
    meta: Mapping[str, Any],
) -> GroundingCase | str:
    """The case of one statement, or the reason it is skipped."""
    raw_relation = str(statement.get("relation", ""))
    relation = VLA3D_RELATIONS.get(raw_relation)
    if relation is None:
        return f"relation_{raw_relation or 'missing'}"
    anchor_ids = _anchor_ids(statement, relation)
    if anchor_ids is None:
        return "anchors_malformed"
    target_id = str(statement.get("target_index"))
    by_id = {o.id: o for o in graph.objects}
    target = by_id.get(target_id)
    if target is None:
        return "target_missing"
    if any(a not in by_id for a in anchor_ids):
        return "anchor_missing"
    if target_id in anchor_ids or len(set(anchor_ids)) != len(anchor_ids):
        return "anchors_malformed"
    position = statement.get("target_position")
    if not (isinstance(position, list) and len(position) == 3):
        position = list(target.center)
    others = [o for o in graph.objects if o.id != target_id]
    labels = Counter(o.label for o in others)
    return GroundingCase(
        case_id=case_id,
        scene_graph=graph.model_copy(update={"objects": others}),
        utterance=utterance,
        target=CaseTarget(
            label=str(statement.get("target_class") or target.label),
            position=[float(v) for v in position],
            size=(2.0 * target.half_extent).tolist(),
        ),
        hypotheses=[CaseHypothesis(anchor_ids=anchor_ids, relation=relation)],
        meta={
            **meta,
            "target_id": target_id,
            "target_box": {"center": target.center, "size": target.size, "yaw": target.yaw},
            "ambiguity": max(labels[by_id[a].label] for a in anchor_ids),
            "distractors": len(statement.get("distractor_ids") or []),
            "augmentation": 0,
        },
    )


def convert_vla3d(
    folder: str | Path, report: ConversionReport | None = None, progress: bool = False
) -> Iterator[GroundingCase]:
    """Cases of every statements file under `folder`; skips are counted in `report`; `progress` shows a
    bar of the scenes converted.

    A scene whose files cannot be read is skipped whole ("scene_unreadable"), its statements uncounted.
    """
    from tqdm import tqdm

    report = ConversionReport() if report is None else report
    for path in tqdm(statement_files(folder), desc="scenes", unit="scene", disable=not progress):
        scene_name = path.name.removesuffix(STATEMENTS_FILE_SUFFIX)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            graph = load_vla3d_scene(path.parent, scene_name)
        except (OSError, ValueError, InvalidSceneGraph) as exc:
            log.warning("skipping VLA-3D scene %s: %s", path, exc)
            report.skipped["scene_unreadable"] += 1
            continue
        report.scenes += 1
        for number, (region_id, region_name, utterance, statement) in enumerate(_iter_statements(data)):
            report.statements += 1
            meta = {
                "source": "vla3d",
                "scene_id": scene_name,
                "region_id": region_id,
                "region": region_name,
                "vla3d_relation": statement.get("relation"),
            }
            result = convert_statement(statement, utterance, graph, f"vla3d/{scene_name}/{number}", meta)
            if isinstance(result, str):
                report.skipped[result] += 1
                continue
            report.cases += 1
            yield result


def write_vla3d_cases(folder: str | Path, out_file: str | Path, progress: bool = False) -> ConversionReport:
    """Convert every statement under `folder` into grounding cases written to `out_file` (JSONL, replaced
    once complete); `progress` shows a bar of the scenes converted."""
    report = ConversionReport()
    write_cases(out_file, convert_vla3d(folder, report, progress))
    return report
