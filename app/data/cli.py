"""`vlmap data build` (grounding cases from real ScanNet / AI2-THOR layouts) and `vlmap data vla3d`
(VLA-3D referential statements as grounding cases)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("data", help="build grounding-case data sets")
    sub = parser.add_subparsers(dest="data_command", required=True, metavar="DATA_COMMAND")

    build = sub.add_parser(
        "build",
        help="grounding cases from real layouts, relations computed from their boxes",
        description="Write train.jsonl, val_seen.jsonl, val_unseen.jsonl and summary.json into --out.",
    )
    build.add_argument("--scannet", type=Path, default=None, help="ScanNet scenes (JSONL)")
    build.add_argument("--ai2thor", type=Path, default=None, help="AI2-THOR scenes (JSONL)")
    build.add_argument("--out", type=Path, required=True, help="output directory")
    build.add_argument("--seed", type=int, default=0)
    build.add_argument("--augment", type=int, default=2, help="rigid motions per train case (default 2)")
    build.add_argument("--max-cases-per-scene", type=int, default=40, help="un-augmented cases (default 40)")
    build.add_argument("--cases-per-target", type=int, default=3, help="relations sampled per target")
    build.add_argument("--unseen-fraction", type=float, default=0.15, help="rooms held out per source")
    build.add_argument("--val-seen-fraction", type=float, default=0.1, help="targets held out per scene")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    build.set_defaults(func=build_command)

    vla3d = sub.add_parser(
        "vla3d",
        help="VLA-3D referential statements as grounding cases",
        description="Convert every <scene>_referential_statements.json under DIR (one scene's folder or a "
        "tree of them) into grounding cases with the target removed from its scene graph.",
    )
    vla3d.add_argument("folder", type=Path, metavar="DIR")
    vla3d.add_argument("--out", type=Path, required=True, help="cases file to write (JSONL)")
    vla3d.set_defaults(func=vla3d_command)


def build_command(args: argparse.Namespace) -> int:
    from app.data.build import SPLITS, BuildConfig, read_ai2thor, read_scannet, write_build

    if args.scannet is None and args.ai2thor is None:
        msg = "give --scannet and/or --ai2thor"
        raise SystemExit(msg)
    if args.augment < 0 or args.max_cases_per_scene < 1 or args.cases_per_target < 1:
        msg = "--augment must be >= 0, --max-cases-per-scene and --cases-per-target >= 1"
        raise SystemExit(msg)
    scenes = []
    if args.scannet is not None:
        scenes += read_scannet(args.scannet)
    if args.ai2thor is not None:
        scenes += read_ai2thor(args.ai2thor)
    config = BuildConfig(
        seed=args.seed,
        augment=args.augment,
        max_cases_per_scene=args.max_cases_per_scene,
        cases_per_target=args.cases_per_target,
        unseen_fraction=args.unseen_fraction,
        val_seen_fraction=args.val_seen_fraction,
    )
    summary = write_build(scenes, args.out, config, progress=not args.no_progress)
    print(
        f"wrote {len(scenes)} scenes' cases to {args.out}/ (" + ", ".join(f"{s}.jsonl" for s in SPLITS) + ")"
    )
    relations = sorted(summary.relation_totals())
    print(f"{'split':<11} {'source':<8} " + " ".join(f"{r:>8}" for r in relations) + f" {'total':>8}")
    for split in SPLITS:
        for source, counts in summary.counts[split].items():
            cells = " ".join(f"{counts[r]:>8}" for r in relations)
            print(f"{split:<11} {source:<8} {cells} {sum(counts.values()):>8}")
    print("notes: " + json.dumps(dict(sorted(summary.notes.items()))))
    return 0


def vla3d_command(args: argparse.Namespace) -> int:
    from app.data.vla3d_statements import write_vla3d_cases

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    report = write_vla3d_cases(args.folder, args.out)
    print(f"wrote {report.cases} cases to {args.out}")
    print(json.dumps(report.to_json(), indent=2))
    return 0
