"""Output files replaced whole or not at all (app.files)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from app.files import atomic_write, write_text_atomic


def test_a_complete_write_replaces_the_file_and_creates_its_folder(tmp_path: Path) -> None:
    path = tmp_path / "new" / "cases.jsonl"
    with atomic_write(path) as fh:
        fh.write("one\n")
        assert not path.exists()  # nothing is visible until the block ends
    assert path.read_text(encoding="utf-8") == "one\n"
    write_text_atomic(path, "two é\n")
    assert path.read_text(encoding="utf-8") == "two é\n"
    assert [p.name for p in path.parent.iterdir()] == ["cases.jsonl"]


def test_a_failed_write_leaves_the_previous_file_and_no_temporary_one(tmp_path: Path) -> None:
    path = tmp_path / "cases.jsonl"
    path.write_text("old\n", encoding="utf-8")
    with pytest.raises(KeyboardInterrupt), atomic_write(path) as fh:
        fh.write("half of the new\n")
        raise KeyboardInterrupt
    assert path.read_text(encoding="utf-8") == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["cases.jsonl"]


def test_the_new_file_gets_the_umask_permissions_not_a_temporary_file_s_private_ones(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "metrics.json", "{}\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "metrics.json").stat().st_mode) == 0o644
