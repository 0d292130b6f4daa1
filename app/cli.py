"""The `vlmap` console script. Each subcommand lives beside the code it drives and registers itself here."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from app.allocator import keep_freed_buffers

# Modules exposing `add_parser(subparsers)`; each sets `func` on its parser and keeps its heavy imports
# (torch, matplotlib) inside its functions, so building the parser stays cheap.
_COMMAND_MODULES = {
    "serve": "app.api.cli",
    "openapi": "app.api.cli",
    "keys": "app.api.cli",
    "data": "app.data.cli",
    "train": "app.training.cli",
    "fit-proposer": "app.training.referents",
    "sim": "app.sim.cli",
    "eval": "app.evaluation.cli",
    "hydra-bridge": "app.hydra_bridge",
    "foxglove": "app.foxglove.cli",
    "record": "app.foxglove.cli",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vlmap", description="VL-Map: language as a calibrated sensor for robots."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name in dict.fromkeys(_COMMAND_MODULES.values()):
        importlib.import_module(module_name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    keep_freed_buffers()
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
