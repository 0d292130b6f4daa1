"""`vlmap sim`: closed-loop evaluation of language sensors by a simulated robot driving the HTTP API.

    vlmap sim --scenes ../shared/data/dev/cases_nr3d_dev.jsonl ../shared/data/dev/cases_scanrefer_dev.jsonl \\
        --episodes 50 --steps 100 --methods vision-only,lsm,geometric,fixed --out runs/sim --seed 0

Without --url it starts `vlmap serve` itself on a free loopback port (a temporary session directory, the
service's default grounder settings, no rate limit) and stops it afterwards. `--perception realistic` (the
default) labels the frames with `app.sim.perception`'s segmenter, `--perception ideal` with the independent
per-voxel noise of the earlier tables. `--measure-rates` computes the frames only (no service) and prints the
rates their labels realised.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from app.sim.metrics import SUCCESS_MASS
from app.sim.perception import MAPPING_PASSES, PERCEPTION_MODELS, PerceptionConfig
from app.sim.runner import DEFAULT_METHODS, METHOD_OPTIONS

if TYPE_CHECKING:
    from app.sim.runner import SimConfig
    from app.sim.scenes import Episode


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "sim",
        help="closed-loop evaluation: a simulated robot drives the service, one session per method",
        description="Run identical seeded episodes (trajectory and noisy frames computed once) against one "
        "session per language-sensor method and report information gain, target mass, argmax distance, "
        "success and miss rates, split by whether the camera ever saw the target.",
    )
    parser.add_argument(
        "--scenes",
        type=Path,
        nargs="+",
        action="extend",
        required=True,
        help="one or more of: grounding-case JSONL (vlmap data build, vlmap data referring, the dev set's "
        "cases), a raw ScanNet/AI2-THOR layout JSONL (vision-only), a VLA-3D folder (vision-only); "
        "their episodes are pooled, then drawn in a seeded order",
    )
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--episodes", type=int, default=50, help="episodes to run (skipped ones not counted)")
    parser.add_argument("--steps", type=int, default=100, help="camera frames per episode")
    parser.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated, of {', '.join(METHOD_OPTIONS)} (the last two need an LLM endpoint)",
    )
    parser.add_argument("--seed", type=int, default=0, help="episode order, trajectories and label noise")
    parser.add_argument("--source", default=None, help="only episodes of this source (scannet, ai2thor, ...)")
    parser.add_argument(
        "--max-target-size",
        type=float,
        default=None,
        metavar="M",
        help="only episodes whose target's largest side is at most M metres (the small objects a robot is "
        "sent to find, which a map would not already hold)",
    )
    parser.add_argument("--url", default=None, help="a running service (default: start one on loopback)")
    parser.add_argument(
        "--api-key", default=os.environ.get("VLMAP_API_KEY"), help="bearer key (default: $VLMAP_API_KEY)"
    )
    parser.add_argument("--voxel-size", type=float, default=0.1, help="metres")
    parser.add_argument("--margin", type=float, default=0.5, help="grid margin around the scene (metres)")
    parser.add_argument(
        "--perception",
        choices=PERCEPTION_MODELS,
        default="realistic",
        help="realistic: per-object, per-frame segmenter errors, recall by apparent size, look-alike false "
        "positives, a mis-specified sensor model (app/sim/perception.py); ideal: independent per-voxel flips "
        "at exactly the told rates (the earlier tables)",
    )
    ideal = parser.add_argument_group("ideal perception")
    ideal.add_argument("--tp", type=float, default=0.9, help="true-positive rate for the target (also told)")
    ideal.add_argument("--fp", type=float, default=0.05, help="false-positive rate (also told)")
    ideal.add_argument("--confusion", type=float, default=0.05, help="rate of other-class confusions")
    default = PerceptionConfig()
    real = parser.add_argument_group(
        "realistic perception (defaults and their sources: app/sim/perception.py)"
    )
    real.add_argument(
        "--image-width", type=int, default=default.image_width_px, help="pixels across the image"
    )
    real.add_argument("--max-recall", type=float, default=default.max_recall, help="recall of large objects")
    real.add_argument(
        "--half-recall-area",
        type=float,
        default=default.half_recall_area_px,
        help="apparent area (pixels) at which recall is half the maximum",
    )
    real.add_argument("--recall-slope", type=float, default=default.recall_slope, help="exponent of the area")
    real.add_argument(
        "--accuracy", type=float, default=default.accuracy, help="P(right class | detected), target's class"
    )
    real.add_argument(
        "--lookalike-share",
        type=float,
        default=default.lookalike_share,
        help="share of an object's misclassifications that go to a full look-alike of the target",
    )
    real.add_argument(
        "--shape-scale", type=float, default=default.shape_scale, help="look-alike scale, log box extents"
    )
    real.add_argument(
        "--frame-correlation",
        type=float,
        default=default.frame_correlation,
        help="correlation of one object's labels across frames (0: independent frames)",
    )
    real.add_argument(
        "--speckle", type=float, default=default.speckle, help="scattered false-positive rate per voxel"
    )
    real.add_argument(
        "--mapping-pass",
        choices=MAPPING_PASSES,
        default=default.mapping_pass,
        help="why the map lacks the target: 'route', the robot mapped along the same route and its segmenter "
        "never labelled the target where it saw it (its propensity drawn given those misses); 'none', the "
        "target came after the map (the tables before this option)",
    )
    real.add_argument(
        "--misspecification",
        type=float,
        default=default.misspecification,
        help="the service is told error rates this many times smaller than the true ones (1: told the truth)",
    )
    real.add_argument(
        "--true-rates",
        type=float,
        nargs=2,
        metavar=("TP", "FP"),
        default=default.true_rates,
        help="the segmenter's true voxel rates that --misspecification applies to (default: measured on "
        "training rooms, CALIBRATED_RATES)",
    )
    parser.add_argument(
        "--measure-rates",
        action="store_true",
        help="compute the episodes' frames only (no service, no methods) and print the rates their labels "
        "realised",
    )
    parser.add_argument("--fov", type=float, default=90.0, help="horizontal field of view (degrees)")
    parser.add_argument("--vfov", type=float, default=60.0, help="vertical field of view (degrees)")
    parser.add_argument("--range", type=float, default=3.5, dest="max_range", help="camera range (metres)")
    parser.add_argument(
        "--checkpoints", type=int, default=20, help="evenly spaced steps at which the full posterior is read"
    )
    parser.add_argument(
        "--min-free-floor", type=float, default=2.0, help="skip scenes with less free floor (m^2)"
    )
    parser.add_argument(
        "--success-mass", type=float, default=SUCCESS_MASS, help="terminal target mass counted as success"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.client import VLMapClient
    from app.errors import InvalidInput
    from app.sim.camera import CameraConfig
    from app.sim.noise import LabelNoise
    from app.sim.report import write_report
    from app.sim.runner import (
        SimConfig,
        SimError,
        check_methods,
        load_episodes,
        needs_utterance,
        run_simulation,
    )
    from app.sim.service import running_service

    try:
        methods = check_methods([m.strip() for m in args.methods.split(",") if m.strip()])
        config = SimConfig(
            n_steps=args.steps,
            seed=args.seed,
            voxel_size=args.voxel_size,
            margin=args.margin,
            perception=args.perception,
            noise=LabelNoise(tp=args.tp, fp=args.fp, confusion=args.confusion),
            segmenter=PerceptionConfig(
                image_width_px=args.image_width,
                max_recall=args.max_recall,
                half_recall_area_px=args.half_recall_area,
                recall_slope=args.recall_slope,
                accuracy=args.accuracy,
                lookalike_share=args.lookalike_share,
                shape_scale=args.shape_scale,
                frame_correlation=args.frame_correlation,
                speckle=args.speckle,
                mapping_pass=args.mapping_pass,
                misspecification=args.misspecification,
                true_rates=(args.true_rates[0], args.true_rates[1]),
            ),
            camera=CameraConfig(hfov_deg=args.fov, vfov_deg=args.vfov, max_range=args.max_range),
            min_free_floor_m2=args.min_free_floor,
            n_checkpoints=args.checkpoints,
        )
        episodes = load_episodes(args.scenes, args.source, args.seed, args.max_target_size)
        scenes = " ".join(str(p) for p in args.scenes)
        if not episodes:
            msg = f"{scenes} holds no episode" + (f" of source {args.source!r}" if args.source else "")
            if args.max_target_size is not None:
                msg += f" with a target of at most {args.max_target_size:g} m"
            raise SimError(msg)
        if args.measure_rates:
            return measure_rates(episodes, args.episodes, config, args.out, progress=not args.no_progress)
        if needs_utterance(methods) and not any(e.utterance for e in episodes):
            msg = (
                f"{scenes} carries no utterances, which {[m for m in methods if METHOD_OPTIONS[m]]} "
                "need: pass grounding cases built from these scenes (vlmap data build), "
                "or --methods vision-only"
            )
            raise SimError(msg)
        command = "vlmap sim " + shlex.join(sys.argv[2:]) if sys.argv[1:2] == ["sim"] else None

        def simulate(url: str) -> int:
            with VLMapClient(url, api_key=args.api_key, timeout_s=120.0) as client:
                result = run_simulation(
                    client, episodes, args.episodes, methods, config, progress=not args.no_progress
                )
            if not result.records:
                msg = f"no episode could run; skipped: {dict(result.skips)}"
                raise SimError(msg)
            print(write_report(result, args.out, args.success_mass, command))
            print(f"{len(result.records)} episodes, skipped {dict(result.skips)}; written to {args.out}")
            return 0

        if args.url is not None:
            return simulate(args.url)
        env = service_env(methods)
        with tempfile.TemporaryDirectory(prefix="vlmap-sim-") as data_dir, ExitStack() as stack:
            try:
                url = stack.enter_context(running_service({**env, "VLMAP_DATA_DIR": data_dir}))
            except RuntimeError as exc:
                settings = " ".join(f"{k}={shlex.quote(v)}" for k, v in env.items())
                msg = f"{exc}; `{settings} vlmap serve` shows why (e.g. LSM weights that do not fit the code)"
                raise SimError(msg) from exc
            return simulate(url)
    except (SimError, InvalidInput) as exc:
        print(f"vlmap sim: {exc}", file=sys.stderr)
        return 2


def measure_rates(
    episodes: Sequence[Episode], n_episodes: int, config: SimConfig, out: Path, progress: bool = False
) -> int:
    """`--measure-rates`: the rates the labels of `n_episodes` fit episodes' frames realise (no service);
    printed and written to out/perception_rates.json. `progress` shows a bar of the episodes measured."""
    from collections import Counter

    from tqdm import tqdm

    from app.files import write_text_atomic
    from app.sim.perception import RateCounts
    from app.sim.runner import prepared_episodes

    skips: Counter[str] = Counter()
    rates, seen, run = RateCounts(), 0, 0
    with tqdm(total=n_episodes, desc="episodes", unit="episode", disable=not progress) as bar:
        for prepared in prepared_episodes(episodes, config, skips):
            rates.add(prepared.rates)
            seen += prepared.target_seen
            run += 1
            bar.update()
            if run >= n_episodes:
                break
    document = {
        "perception": config.perception,
        "episodes": run,
        "target_observed": seen,
        "skipped": dict(sorted(skips.items())),
        "realised": rates.summary(),
    }
    write_text_atomic(out / "perception_rates.json", json.dumps(document, indent=2) + "\n")
    print(json.dumps(document, indent=2))
    return 0


def service_env(methods: Sequence[str]) -> dict[str, str]:
    """Environment of the service `vlmap sim` starts: the default grounders plus those the methods need, no
    rate limit, utterances as long as the service can read (a case file has no length limit, and `vlmap eval
    static` grounds any). SimError when the LSM's weights or the LLM endpoint the methods need are missing."""
    from app.settings import MAX_UTTERANCE_CHARS_CEILING, Settings
    from app.sim.runner import LLM_METHODS, SimError, needed_parts

    settings = Settings()
    grounders, _ = needed_parts(methods)
    if "lsm" in grounders and not (settings.model_dir / "lsm").is_dir():
        msg = f"method lsm needs trained weights in {settings.model_dir / 'lsm'} (or set VLMAP_MODEL_DIR)"
        raise SimError(msg)
    llm = [m for m in methods if m in LLM_METHODS]
    if llm and not settings.llm_url:
        msg = (
            f"methods {llm} need an LLM endpoint: set VLMAP_LLM_URL (and VLMAP_LLM_MODEL, VLMAP_LLM_API_KEY)"
        )
        raise SimError(msg)
    builtin = sorted((grounders - set(LLM_METHODS)) | set(settings.grounders))
    return {
        "VLMAP_GROUNDERS": json.dumps(builtin),
        "VLMAP_RATE_LIMIT_PER_S": "0",
        "VLMAP_MAX_UTTERANCE_CHARS": str(MAX_UTTERANCE_CHARS_CEILING),
    }
