"""`vlmap data build` (grounding cases from ScanNet / AI2-THOR / synthetic layouts, `app.data.build`),
`vlmap data synth` (synthetic rooms, `app.data.synthetic`) and `vlmap data vla3d` (VLA-3D referential
statements as grounding cases)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("data", help="build grounding-case data sets")
    sub = parser.add_subparsers(dest="data_command", required=True, metavar="DATA_COMMAND")

    build = sub.add_parser(
        "build",
        help="grounding cases from real layouts, relations computed from their boxes",
        description="Write train.jsonl, val_seen.jsonl, val_unseen.jsonl, calib.jsonl and summary.json into "
        "--out. Relations follow three conventions (vlmap, Sr3D, VLA-3D); rooms are also joined into houses; "
        "train cases are repeated on moved, noisy, partial maps with other datasets' labels, calib cases are "
        "built that way from rooms of their own.",
    )
    build.add_argument("--scannet", type=Path, default=None, help="ScanNet scenes (JSONL)")
    build.add_argument("--ai2thor", type=Path, default=None, help="AI2-THOR scenes (JSONL)")
    build.add_argument(
        "--synthetic", type=Path, default=None, help="synthetic rooms (JSONL, from `vlmap data synth`)"
    )
    build.add_argument("--out", type=Path, required=True, help="output directory")
    build.add_argument("--seed", type=int, default=0)
    build.add_argument(
        "--augment",
        type=int,
        default=3,
        help="shifted maps (frame, noise, labels) per train case (default 3)",
    )
    build.add_argument("--max-cases-per-scene", type=int, default=40, help="un-augmented cases per map")
    build.add_argument("--cases-per-target", type=int, default=3, help="relations sampled per target")
    build.add_argument("--unseen-fraction", type=float, default=0.15, help="rooms held out per source")
    build.add_argument("--val-seen-fraction", type=float, default=0.1, help="targets held out per scene")
    build.add_argument(
        "--calib-fraction", type=float, default=0.1, help="rooms per source for the calib split (default 0.1)"
    )
    build.add_argument(
        "--conventions",
        default="vlmap,sr3d,vla3d",
        help="relation conventions to draw from, comma-separated (default vlmap,sr3d,vla3d)",
    )
    build.add_argument(
        "--house-fraction",
        type=float,
        default=0.6,
        help="houses joined per room of the train and calib pools (default 0.6; 0: no houses)",
    )
    build.add_argument(
        "--no-continuous-yaw", action="store_true", help="shifted maps turn by quarter turns only"
    )
    build.add_argument("--no-box-noise", action="store_true", help="no box noise nor missing objects")
    build.add_argument("--no-raw-labels", action="store_true", help="never rename into raw vocabularies")
    build.add_argument(
        "--small-targets-only", action="store_true", help="only small and medium movable objects as targets"
    )
    build.add_argument(
        "--relocate-fraction",
        type=float,
        default=0.0,
        help="share of train targets first moved to another resting place of their room (default 0)",
    )
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    build.set_defaults(func=build_command)

    synth = sub.add_parser(
        "synth",
        help="synthetic furnished rooms, a third source of layouts for `data build --synthetic`",
        description="Write ROOMS furnished rooms (bedrooms, kitchens, offices, ...) drawn from broad "
        "furniture and room ranges, one a line in the scans' format (app.data.synthetic). Room k depends "
        "only on the seed and k.",
    )
    synth.add_argument("--rooms", type=int, default=200, help="how many rooms (default 200)")
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--out", type=Path, required=True, help="rooms file to write (JSONL)")
    synth.set_defaults(func=synth_command)

    vla3d = sub.add_parser(
        "vla3d",
        help="VLA-3D referential statements as grounding cases",
        description="Convert every <scene>_referential_statements.json under DIR (one scene's folder or a "
        "tree of them) into grounding cases with the target removed from its scene graph.",
    )
    vla3d.add_argument("folder", type=Path, metavar="DIR")
    vla3d.add_argument("--out", type=Path, required=True, help="cases file to write (JSONL)")
    vla3d.add_argument("--no-progress", action="store_true", help="no progress bar")
    vla3d.set_defaults(func=vla3d_command)

    referring = sub.add_parser(
        "referring",
        help="human referring expressions (target known, anchor not) as grounding cases",
        description="Write one case per expression: the utterance, the scan's scene graph without the "
        "target, the target's position; no hypotheses (app.data.referring).",
    )
    referring.add_argument("--expressions", type=Path, required=True, help="expressions (JSONL)")
    referring.add_argument("--scenes", type=Path, required=True, help="the scans' boxes (JSONL)")
    referring.add_argument("--out", type=Path, required=True, help="cases file to write (JSONL)")
    referring.add_argument("--no-progress", action="store_true", help="no progress bar")
    referring.set_defaults(func=referring_command)


def build_command(args: argparse.Namespace) -> int:
    import time

    from app.data.build import SPLITS, BuildConfig, read_ai2thor, read_scannet, read_synthetic, write_build
    from app.data.conventions import Convention
    from app.errors import InvalidInput

    if args.scannet is None and args.ai2thor is None and args.synthetic is None:
        msg = "give --scannet, --ai2thor and/or --synthetic"
        raise SystemExit(msg)
    if args.augment < 0 or args.max_cases_per_scene < 1 or args.cases_per_target < 1:
        msg = "--augment must be >= 0, --max-cases-per-scene and --cases-per-target >= 1"
        raise SystemExit(msg)
    if args.house_fraction < 0:
        msg = "--house-fraction must be >= 0"
        raise SystemExit(msg)
    names = [n.strip() for n in args.conventions.split(",") if n.strip()]
    known = {c.value for c in Convention}
    if not names or any(n not in known for n in names):
        msg = f"--conventions takes a comma-separated subset of {', '.join(sorted(known))}"
        raise SystemExit(msg)
    start = time.perf_counter()
    try:
        # Before the layouts are read, so that a mistyped fraction fails at once.
        config = BuildConfig(
            seed=args.seed,
            augment=args.augment,
            max_cases_per_scene=args.max_cases_per_scene,
            cases_per_target=args.cases_per_target,
            unseen_fraction=args.unseen_fraction,
            val_seen_fraction=args.val_seen_fraction,
            calib_fraction=args.calib_fraction,
            conventions=tuple(Convention(n) for n in dict.fromkeys(names)),
            house_fraction=args.house_fraction,
            continuous_yaw=not args.no_continuous_yaw,
            box_noise=not args.no_box_noise,
            raw_labels=not args.no_raw_labels,
            all_targets=not args.small_targets_only,
            relocate_fraction=args.relocate_fraction,
        )
        scenes = []
        if args.scannet is not None:
            scenes += read_scannet(args.scannet)
        if args.ai2thor is not None:
            scenes += read_ai2thor(args.ai2thor)
        if args.synthetic is not None:
            scenes += read_synthetic(args.synthetic)
        summary = write_build(scenes, args.out, config, progress=not args.no_progress)
    except InvalidInput as exc:  # a bad option or layout file: a message, not a traceback
        msg = f"vlmap data build: {exc}"
        raise SystemExit(msg) from exc
    elapsed = time.perf_counter() - start
    print(
        f"wrote {len(scenes)} scenes' cases to {args.out}/ ("
        + ", ".join(f"{s}.jsonl" for s in SPLITS)
        + f") in {elapsed:.0f} s"
    )
    relations = sorted(summary.relation_totals())
    header = f"{'split':<11} {'source':<8} {'conv':<6} " + " ".join(f"{r:>8}" for r in relations)
    print(header + f" {'total':>8}")
    for split in SPLITS:
        for source, by_convention in sorted(summary.by_convention[split].items()):
            for convention, counts in sorted(by_convention.items()):
                cells = " ".join(f"{counts[r]:>8}" for r in relations)
                print(f"{split:<11} {source:<8} {convention:<6} {cells} {sum(counts.values()):>8}")
    print("maps: " + json.dumps({s: dict(c) for s, c in summary.maps.items()}))
    print("notes: " + json.dumps(dict(sorted(summary.notes.items()))))
    return 0


def synth_command(args: argparse.Namespace) -> int:
    from app.data.synthetic import write_synthetic_rooms

    if args.rooms < 1:
        msg = "--rooms must be >= 1"
        raise SystemExit(msg)
    objects = write_synthetic_rooms(args.out, args.rooms, args.seed)
    print(f"wrote {args.rooms} rooms ({objects} objects) to {args.out}")
    return 0


def vla3d_command(args: argparse.Namespace) -> int:
    from app.data.vla3d_statements import write_vla3d_cases

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    report = write_vla3d_cases(args.folder, args.out, progress=not args.no_progress)
    print(f"wrote {report.cases} cases to {args.out}")
    print(json.dumps(report.to_json(), indent=2))
    return 0


def referring_command(args: argparse.Namespace) -> int:
    from app.data.cases import write_cases
    from app.data.referring import ReferringReport, referring_cases, scene_objects

    report = ReferringReport()
    cases = referring_cases(
        args.expressions, scene_objects(args.scenes), report, progress=not args.no_progress
    )
    written = write_cases(args.out, cases)
    print(f"wrote {written} cases of {report.expressions} expressions to {args.out}")
    if report.skipped:
        print("skipped: " + json.dumps(dict(sorted(report.skipped.items()))))
    return 0
