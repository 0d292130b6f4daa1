"""`vlmap data referring`: human referring expressions as grounding cases (app.data.referring)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.cli import main
from app.data.cases import read_cases

SCENE = {
    "scene_id": "scene0000_00",
    "objects": [
        {"id": "1", "label": "Chair", "center": [0.0, 0.0, 0.5], "size": [0.5, 0.5, 1.0]},
        {"id": "2", "label": "table", "center": [1.0, 0.0, 0.4], "size": [1.2, 0.8, 0.8]},
    ],
}
EXPRESSION = {
    "scene_id": "scene0000_00",
    "target_id": "1",
    "target_label": "chair",
    "utterance": "the chair next to the table",
    "source": "nr3d",
}


def _inputs(folder: Path, *expression_lines: str) -> list[str]:
    expressions, scenes = folder / "expressions.jsonl", folder / "scenes.jsonl"
    expressions.write_text("".join(line + "\n" for line in expression_lines), encoding="utf-8")
    scenes.write_text(json.dumps(SCENE) + "\n", encoding="utf-8")
    return ["data", "referring", "--expressions", str(expressions), "--scenes", str(scenes)]


def test_cli_writes_the_cases_with_a_progress_bar_unless_told_not_to(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cases.jsonl"
    missing = json.dumps({**EXPRESSION, "scene_id": "scene9999_00"})
    command = [*_inputs(tmp_path, json.dumps(EXPRESSION), missing), "--out", str(out)]
    assert main(command) == 0
    captured = capsys.readouterr()
    assert "wrote 1 cases of 2 expressions" in captured.out
    assert "expressions: 2line" in captured.err
    (case,) = read_cases(out)
    assert (case.target.label, [o.id for o in case.scene_graph.objects]) == ("chair", ["2"])
    assert main([*command, "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_a_conversion_that_fails_half_way_leaves_the_previous_cases_file(tmp_path: Path) -> None:
    out = tmp_path / "out" / "cases.jsonl"
    out.parent.mkdir()
    out.write_text("the previous cases\n", encoding="utf-8")
    command = [*_inputs(tmp_path, json.dumps(EXPRESSION), "{not json"), "--out", str(out), "--no-progress"]
    with pytest.raises(ValueError, match="Expecting property name"):
        main(command)
    assert out.read_text(encoding="utf-8") == "the previous cases\n"
    assert [p.name for p in out.parent.iterdir()] == ["cases.jsonl"]
