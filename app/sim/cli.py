"""`vlmap sim`: closed-loop evaluation of language sensors by a simulated robot driving the HTTP API.

    vlmap sim --scenes data/cases/val_unseen.jsonl --source scannet --episodes 50 --steps 100 \\
        --methods vision-only,lsm,geometric,fixed --out runs/sim --seed 0

Without --url it starts `vlmap serve` itself on a free loopback port (a temporary session directory, the
service's default grounder settings, no rate limit) and stops it afterwards.
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

from app.sim.metrics import SUCCESS_MASS
from app.sim.runner import DEFAULT_METHODS, METHOD_OPTIONS


def add_parser(subparsers: argparse._SubParsersAction) -> None:
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
        required=True,
        help="grounding-case JSONL (vlmap data build), a raw ScanNet/AI2-THOR layout JSONL (vision-only), "
        "or a VLA-3D folder (vision-only)",
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
    parser.add_argument("--url", default=None, help="a running service (default: start one on loopback)")
    parser.add_argument(
        "--api-key", default=os.environ.get("VLMAP_API_KEY"), help="bearer key (default: $VLMAP_API_KEY)"
    )
    parser.add_argument("--voxel-size", type=float, default=0.1, help="metres")
    parser.add_argument("--margin", type=float, default=0.5, help="grid margin around the scene (metres)")
    parser.add_argument("--tp", type=float, default=0.9, help="segmenter true-positive rate for the target")
    parser.add_argument("--fp", type=float, default=0.05, help="segmenter false-positive rate")
    parser.add_argument("--confusion", type=float, default=0.05, help="rate of other-class confusions")
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
            noise=LabelNoise(tp=args.tp, fp=args.fp, confusion=args.confusion),
            camera=CameraConfig(hfov_deg=args.fov, vfov_deg=args.vfov, max_range=args.max_range),
            min_free_floor_m2=args.min_free_floor,
            n_checkpoints=args.checkpoints,
        )
        episodes = load_episodes(args.scenes, args.source, args.seed)
        if not episodes:
            msg = f"{args.scenes} holds no episode" + (f" of source {args.source!r}" if args.source else "")
            raise SimError(msg)
        if needs_utterance(methods) and not any(e.utterance for e in episodes):
            msg = (
                f"{args.scenes} carries no utterances, which {[m for m in methods if METHOD_OPTIONS[m]]} "
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


def service_env(methods: Sequence[str]) -> dict[str, str]:
    """Environment of the service `vlmap sim` starts: the default grounders plus those the methods need, no
    rate limit. SimError when the LSM's weights or the LLM endpoint the methods need are missing."""
    from app.settings import Settings
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
    return {"VLMAP_GROUNDERS": json.dumps(builtin), "VLMAP_RATE_LIMIT_PER_S": "0"}
