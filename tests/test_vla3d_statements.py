"""VLA-3D referential statements as grounding cases, on the shared format example (tests/resources/data)."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import pytest

from app.cli import main
from app.data.cases import read_cases
from app.data.vla3d_statements import ConversionReport, convert_vla3d, statement_files
from app.errors import InvalidInput
from app.grounding.relations import Relation

EXAMPLE = Path(__file__).parent / "resources" / "data" / "vla3d_scene0010_01"
STATEMENTS = "scene0010_01_referential_statements.json"


def test_the_example_statements_become_cases_without_their_targets():
    report = ConversionReport()
    cases = list(convert_vla3d(EXAMPLE, report))
    assert report.to_json() == {"scenes": 1, "statements": 2, "cases": 2, "skipped": {}}
    backpack, bin_ = cases
    assert backpack.utterance == "the backpack that is on the desk"
    assert backpack.hypotheses[0].relation is Relation.ON
    assert backpack.hypotheses[0].anchor_ids == ["29"]
    assert backpack.target.label == "backpack"
    assert backpack.target.position == pytest.approx(
        [1.2712812490797198, -0.08181167329780964, 0.7790779769420624]
    )
    assert bin_.hypotheses[0].relation is Relation.NEAR and bin_.hypotheses[0].anchor_ids == ["7"]
    for case, target_id in ((backpack, "33"), (bin_, "18")):
        ids = {o.id for o in case.scene_graph.objects}
        assert target_id not in ids and case.meta["target_id"] == target_id
        assert len(ids) == 58  # the reader's 59 objects less the target
        anchor_label = case.scene_graph.object(case.hypotheses[0].anchor_ids[0]).label
        labels = Counter(o.label for o in case.scene_graph.objects)
        assert case.meta["ambiguity"] == labels[anchor_label]
        assert case.meta["source"] == "vla3d" and case.meta["scene_id"] == "scene0010_01"
    assert bin_.meta["ambiguity"] > 1  # the office has several walls


def _with_statements(folder: Path, statements: dict) -> None:
    folder.mkdir(parents=True)
    for path in EXAMPLE.iterdir():
        shutil.copy(path, folder / path.name)
    (folder / STATEMENTS).write_text(json.dumps(statements))


def _statement(target: str, relation: str, *anchors: str) -> dict:
    return {
        "target_index": target,
        "target_class": "thing",
        "target_position": [0.0, 0.0, 0.5],
        "relation": relation,
        "anchors": {f"anchor_{k + 1}": {"index": a, "class": "x"} for k, a in enumerate(anchors)},
    }


def test_a_tree_of_scene_folders_converts_and_skips_are_counted(tmp_path):
    base = json.loads((EXAMPLE / STATEMENTS).read_text())
    edited = {
        "scene_name": "scene0010_01",
        "regions": {
            "0": {
                "region": "Office",
                "the thing between the desk and the wall": [_statement("33", "between", "29", "7")],
                "the thing second closest to the desk": [_statement("33", "second_closest", "29")],
                "the thing beside the desk": [_statement("33", "beside", "29")],
                "the ghost near the desk": [_statement("9999", "near", "29")],
                "the thing near the ghost": [_statement("33", "near", "9999")],
                "the thing between the desk and nothing": [_statement("33", "between", "29")],
            }
        },
    }
    _with_statements(tmp_path / "benchmark" / "scannet" / "scene0010_01", base)
    _with_statements(tmp_path / "benchmark" / "edited" / "scene0010_01", edited)
    assert len(statement_files(tmp_path / "benchmark")) == 2
    report = ConversionReport()
    cases = list(convert_vla3d(tmp_path / "benchmark", report))
    assert report.scenes == 2 and report.statements == 8 and report.cases == 3
    assert report.skipped == Counter(
        relation_second_closest=1, relation_beside=1, target_missing=1, anchor_missing=1, anchors_malformed=1
    )
    between = next(c for c in cases if c.hypotheses[0].relation is Relation.BETWEEN)
    assert between.hypotheses[0].anchor_ids == ["29", "7"]
    assert between.meta["ambiguity"] == max(
        sum(o.label == between.scene_graph.object(a).label for o in between.scene_graph.objects)
        for a in ("29", "7")
    )


def test_an_unreadable_scene_is_skipped_and_a_missing_folder_refused(tmp_path):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / STATEMENTS).write_text("{}")  # statements without the scene's files
    report = ConversionReport()
    assert list(convert_vla3d(broken, report)) == []
    assert report.skipped == Counter(scene_unreadable=1)
    with pytest.raises(InvalidInput):
        statement_files(tmp_path / "nowhere")


def test_an_unreadable_scene_graph_json_beside_the_region_csv_is_not_read(tmp_path):
    scene = tmp_path / "scene0010_01"
    _with_statements(scene, json.loads((EXAMPLE / STATEMENTS).read_text()))
    (scene / "scene0010_01_scene_graph.json").write_text("{not json")  # only the region CSV's fallback
    report = ConversionReport()
    assert len(list(convert_vla3d(scene, report))) == 2
    assert report.skipped == Counter()


def test_cli_writes_the_cases(tmp_path, capsys):
    out = tmp_path / "vla3d.jsonl"
    assert main(["data", "vla3d", str(EXAMPLE), "--out", str(out)]) == 0
    cases = list(read_cases(out))
    assert [c.hypotheses[0].relation for c in cases] == [Relation.ON, Relation.NEAR]
    assert "wrote 2 cases" in capsys.readouterr().out


def test_cli_shows_a_progress_bar_unless_told_not_to(tmp_path, capsys):
    out = tmp_path / "vla3d.jsonl"
    assert main(["data", "vla3d", str(EXAMPLE), "--out", str(out)]) == 0
    assert "scenes: 100%" in capsys.readouterr().err
    assert main(["data", "vla3d", str(EXAMPLE), "--out", str(out), "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
