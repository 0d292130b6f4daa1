"""Output files replaced whole or not at all.

A data set, an evaluation's metrics or a run's report is written to a temporary file in the folder of the
file it replaces, flushed to disk, and renamed over it (`os.replace`, atomic within one file system) only
once it is complete. A run that fails or is stopped half-way leaves the previous file as it was, never a
truncated one that reads as complete.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

__all__ = ["atomic_write", "write_text_atomic"]


@contextmanager
def atomic_write(path: str | Path, encoding: str = "utf-8") -> Iterator[TextIO]:
    """A text handle on a new temporary file beside `path` (its folder created if need be) that replaces
    `path` when the block ends normally; when the block raises, the temporary file is removed and `path`
    is left untouched."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    # Hidden, unique and in the same folder, so that the rename stays on one file system; "x" mode creates
    # it with the umask's permissions, as writing `path` directly would.
    temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
    fh = temporary.open("x", encoding=encoding)
    try:
        with fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        temporary.replace(target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    """Write `text` to `path` through `atomic_write`."""
    with atomic_write(path, encoding) as fh:
        fh.write(text)
