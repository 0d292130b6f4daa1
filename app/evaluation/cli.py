"""`vlmap eval static`: the language sensor on a grounding-case file, scored (see app.evaluation.static)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

# The same names as app.evaluation.static's PROPOSERS and GROUNDERS (a test checks), spelled out here so that
# building the `vlmap` parser does not import the evaluation.
PROPOSER_CHOICES = ("gt", "builtin", "llm")
GROUNDER_CHOICES = ("lsm", "geometric", "fixed", "scaffolded-llm", "llm-e2e")


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("eval", help="evaluate grounding accuracy and calibration")
    sub = parser.add_subparsers(dest="eval_command", required=True, metavar="EVAL_COMMAND")

    static = sub.add_parser(
        "static",
        help="score a grounder (and baselines) on a grounding-case file",
        description="Ground every case of a grounding-case file (JSONL) through the language sensor and "
        "write DIR/metrics.json (RMSE, NLL beside the no-language baseline's, ANEES, HDR coverage overall, "
        "per relation and per ambiguity; "
        "the proposer's top-1 accuracy, true-hypothesis NLL and ECE), DIR/report.md, DIR/per_case.jsonl "
        "and calibration plots (PNG). LLM endpoints: --llm-url/--llm-model or VLMAP_LLM_URL, "
        "VLMAP_LLM_MODEL, VLMAP_LLM_API_KEY.",
    )
    static.add_argument("--cases", type=Path, required=True, help="grounding cases (JSONL)")
    static.add_argument("--proposer", choices=PROPOSER_CHOICES, default="gt", help="hypotheses (default gt)")
    static.add_argument(
        "--grounder", choices=GROUNDER_CHOICES, default="lsm", help="spatial grounder (default lsm)"
    )
    static.add_argument(
        "--baselines", action="store_true", help="also evaluate geometric and fixed in the same table"
    )
    static.add_argument("--max-cases", type=int, default=None, help="only the first N cases")
    static.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo HDR thresholds")
    static.add_argument(
        "--hdr-samples", type=int, default=5000, help="Monte Carlo draws per mixture HDR (default 5000)"
    )
    static.add_argument("--model-dir", type=Path, default=None, help="LSM checkpoint (default models/lsm)")
    static.add_argument(
        "--proposer-params",
        type=Path,
        default=None,
        help="the built-in proposer's params.json (default models/proposer/params.json)",
    )
    static.add_argument("--llm-url", default=None, help="OpenAI-compatible base URL, e.g. http://host/v1")
    static.add_argument("--llm-model", default=None, help="model name at that endpoint")
    static.add_argument("--out", type=Path, required=True, help="output directory")
    static.add_argument("--no-progress", action="store_true", help="no progress bar")
    static.set_defaults(func=static_command)


def static_command(args: argparse.Namespace) -> int:
    from app.errors import VLMapError
    from app.evaluation.report import format_report, write_plots
    from app.evaluation.static import LLMOptions, StaticOptions, run_static
    from app.files import atomic_write, write_text_atomic

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    options = StaticOptions(
        cases=args.cases,
        proposer=args.proposer,
        grounder=args.grounder,
        baselines=args.baselines,
        max_cases=args.max_cases,
        seed=args.seed,
        hdr_samples=args.hdr_samples,
        model_dir=args.model_dir,
        proposer_params=args.proposer_params,
        llm=LLMOptions.from_env(args.llm_url, args.llm_model),
        progress=not args.no_progress,
    )
    try:
        result = run_static(options)
    except VLMapError as exc:  # setup problems (no endpoint, no LSM, no file): a message, not a traceback
        msg = f"vlmap eval static: {exc}"
        raise SystemExit(msg) from exc

    out: Path = args.out
    write_text_atomic(out / "metrics.json", json.dumps(result.metrics, indent=2) + "\n")
    with atomic_write(out / "per_case.jsonl") as fh:
        for row in result.per_case:
            fh.write(json.dumps(row) + "\n")
    report = format_report(result.metrics)
    write_text_atomic(out / "report.md", report)
    plots = write_plots(result.metrics, out, result.per_case)
    print(report)
    print(f"wrote {out}/metrics.json, report.md, per_case.jsonl, " + ", ".join(p.name for p in plots))
    return 0
