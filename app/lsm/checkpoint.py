"""What an LSM checkpoint directory holds, read without loading it (no torch): its file names, its
config, the checksum of its weights, and the description `/v1/models` gives of it."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

#: The shippable checkpoint: weights and the config (model shape, calibration, version) beside them.
WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
#: The grounder's name in requests and in `/v1/models`.
LSM_NAME = "lsm"


def file_sha256(path: Path, chunk_bytes: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(chunk_bytes):
            digest.update(chunk)
    return digest.hexdigest()


def description(meta: dict[str, Any], weights_sha256: str) -> dict[str, Any]:
    """Name, version, config and weights checksum of a checkpoint (`Grounder.describe`)."""
    return {
        "name": LSM_NAME,
        "version": str(meta.get("version", "unversioned")),
        "config": meta,
        "checksum": f"sha256:{weights_sha256}",
    }


def describe_checkpoint(model_dir: Path) -> dict[str, Any]:
    """`description` of the checkpoint in `model_dir`, from its files alone."""
    meta = json.loads((Path(model_dir) / CONFIG_NAME).read_text(encoding="utf-8"))
    return description(meta, file_sha256(Path(model_dir) / WEIGHTS_NAME))
