"""`vlmap train --config FILE --out DIR`: train, calibrate and evaluate an LSM (see app.training.lsm)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train the Language Sensor Model on grounding cases",
        description="Train the LSM (configs/lsm_*.yaml), keep the best val_seen checkpoint, calibrate it on "
        "val_seen and report it with the baselines on val_seen and val_unseen.",
    )
    parser.add_argument("--config", type=Path, required=True, help="training config (YAML)")
    parser.add_argument(
        "--out", type=Path, required=True, help="output directory (checkpoint, metrics, history)"
    )
    parser.add_argument(
        "--evaluate-only",
        type=Path,
        default=None,
        metavar="MODEL_DIR",
        help="skip training: evaluate the checkpoint in MODEL_DIR on the config's validation splits",
    )
    parser.add_argument(
        "--recalibrate",
        type=Path,
        default=None,
        metavar="MODEL_DIR",
        help="skip training: fit the calibration of the checkpoint in MODEL_DIR anew on the config's calib "
        "split (its fit, margins and tail floor) and write the recalibrated checkpoint, its report and the "
        "config to --out",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.training.lsm import TrainConfig, evaluate_checkpoint, recalibrate, train, write_report

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    config = TrainConfig.from_yaml(args.config)
    if args.recalibrate is not None:
        recalibrate(args.recalibrate, config, args.out)
    elif args.evaluate_only is None:
        train(config, args.out)
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        write_report(evaluate_checkpoint(args.evaluate_only, config, cache_dir=args.out), args.out)
    print((args.out / "metrics.md").read_text(encoding="utf-8"))
    return 0
