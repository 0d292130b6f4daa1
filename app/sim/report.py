"""What a closed-loop run writes: metrics.json, a Markdown table in the layout of the reference's Table 2,
per-episode records (episodes.jsonl) and PNG plots of information gain and target mass against normalised
trajectory progress (one line per method, shaded +- one standard error, one panel per split).

The table and metrics.json say which setting the run had: the perception model (realistic or ideal, the
sensor model the service was told, and the rates the frames' labels realised) and the language (how many
episodes had human utterances and how many templated ones, per source).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, Literal

from app.files import atomic_write, write_text_atomic
from app.sim.metrics import SplitMetrics, aggregate
from app.sim.runner import SimResult

#: Row titles of the methods, in the table and the plots' legends.
METHOD_TITLES = {
    "vision-only": "Vision-only",
    "lsm": "LSM",
    "geometric": "Geometric",
    "fixed": "Fixed (anchor centroid, 0.1 m)",
}
#: Split name -> block title of the table and the plots.
SPLIT_TITLES = {"observed": "Target observed by vision", "unobserved": "Target never directly observed"}
#: Line colours per method (colour-blind safe, stable across plots).
METHOD_COLOURS = {"vision-only": "#7f7f7f", "lsm": "#009e73", "geometric": "#0072b2", "fixed": "#d55e00"}


def _clean(value: Any) -> Any:
    """JSON-safe copy: NaN and infinities become null, tuples lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


def metrics_document(
    result: SimResult,
    metrics: dict[str, dict[str, SplitMetrics]],
    success_mass: float,
    command: str | None = None,
) -> dict[str, Any]:
    """The content of metrics.json: setup, episode and skip counts, timings, and per method per split the
    aggregates of `app.sim.metrics` (curves included)."""
    config = result.config
    n_seen = sum(r.target_seen for r in result.records)
    told = config.sensor_model
    document: dict[str, Any] = _clean(
        {
            "command": command,
            "config": {
                "steps": config.n_steps,
                "seed": config.seed,
                "voxel_size_m": config.voxel_size,
                "margin_m": config.margin,
                "perception": config.perception,
                "noise": asdict(
                    config.noise
                ),  # the ideal model's parameters (used when perception is "ideal")
                "segmenter": asdict(config.segmenter) if config.perception == "realistic" else None,
                "sensor_model": {"tp": told[0], "fp": told[1]},
                "camera": asdict(config.camera),
                "policy": asdict(config.policy),
                "min_free_floor_m2": config.min_free_floor_m2,
                "checkpoint_steps": list(config.checkpoints),
                "success_mass": success_mass,
                "miss": "terminal target mass below the uniform prior's n_t / N",
                "argmax_distance": "MAP voxel centre to the target's axis-aligned box (0 inside)",
            },
            "methods": list(result.methods),
            "language": language_counts(result),
            "perception_realised": result.rates.summary(),
            "episodes": {
                "run": len(result.records),
                "observed": n_seen,
                "unobserved": len(result.records) - n_seen,
                "skipped": dict(sorted(result.skips.items())),
            },
            "grounded_pct": {
                method: _pct(result, method, "grounded")
                for method in result.methods
                if any(r.runs[method].grounded is not None for r in result.records)
            },
            "fused_pct": {
                method: _pct(result, method, "fused")
                for method in result.methods
                if any(r.runs[method].fused is not None for r in result.records)
            },
            "timing_s": {k: round(v, 3) for k, v in sorted(result.seconds.items())},
            "metrics": {
                method: {split: asdict(m) for split, m in by_split.items()}
                for method, by_split in metrics.items()
            },
        }
    )
    return document


def language_counts(result: SimResult) -> dict[str, dict[str, int]]:
    """Episodes per language ("human", "templated", "none") and per source of each language."""
    counts: dict[str, Counter[str]] = {}
    for record in result.records:
        counts.setdefault(record.language or "none", Counter())[record.source] += 1
    return {language: dict(sorted(by_source.items())) for language, by_source in sorted(counts.items())}


def setting_line(document: dict[str, Any]) -> str:
    """One sentence naming the run's perception model and language, for the table page."""
    config, realised = document["config"], document["perception_realised"]
    told = config["sensor_model"]
    if config["perception"] == "realistic":
        route = (config.get("segmenter") or {}).get("mapping_pass") == "route"
        missed = "never labelled along the route while mapping" if route else "placed after mapping"
        perception = (
            "realistic perception (`app/sim/perception.py`: per-object, per-frame labels, recall by apparent "
            f"size, look-alike false positives, the target {missed}; the service told "
            f"tp {told['tp']:.3f}, fp {told['fp']:.4f})"
        )
    else:
        perception = (
            f"idealised perception (independent per-voxel flips at the told tp {told['tp']}, fp {told['fp']})"
        )
    if realised.get("tp") is not None and realised.get("fp") is not None:
        perception += (
            f"; the labels realised tp {realised['tp']:.3f}, fp {realised['fp']:.4f}, target-class precision "
            f"{realised['precision']:.2f}, IoU {realised['iou']:.2f}"
        )
        if realised.get("target_frames_labelled_t_pct") is not None:
            perception += (
                f", the target labelled as its class in {realised['target_frames_labelled_t_pct']:.0f}% of "
                "the frames it was in view"
            )
    parts = []
    for language, by_source in document["language"].items():
        sources = ", ".join(f"{source} {n}" for source, n in by_source.items())
        parts.append(f"{language} {sum(by_source.values())} ({sources})")
    return f"Setting: {perception}. Language: {'; '.join(parts) or 'none'}."


def _pct(result: SimResult, method: str, flag: Literal["grounded", "fused"]) -> float | None:
    """The share of episodes whose utterance the grounder grounded, or the session fused (a session refuses
    one whose target names another class: such an episode runs on vision alone)."""
    flags = [getattr(r.runs[method], flag) for r in result.records]
    return 100.0 * sum(bool(f) for f in flags) / len(flags) if flags else None


def _pm(mean: float | None, se: float | None, digits: int) -> str:
    if mean is None:
        return "–"
    text = f"{mean:.{digits}f}"
    return text if se is None else f"{text} ± {se:.{digits}f}"


def _number(value: float | None, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def render_table(metrics: dict[str, dict[str, SplitMetrics]], methods: Sequence[str]) -> str:
    """Markdown in the layout of the reference's Table 2: a block per split, a row per method."""
    header = (
        "| Method | Mean IG (nats) ↑ | Mean prob. mass ↑ | Mean argmax dist (m) ↓ "
        "| Success % ↑ | Miss % ↓ |\n|---|---:|---:|---:|---:|---:|"
    )
    lines = [header]
    for split, title in SPLIT_TITLES.items():
        n = metrics[methods[0]][split].n
        lines.append(f"| *{title} (n={n})* | | | | | |")
        for method in methods:
            m = metrics[method][split]
            cells = [
                METHOD_TITLES.get(method, method),
                _pm(m.mean_ig, m.se_ig, 2),
                _pm(m.mean_mass, m.se_mass, 3),
                _number(m.mean_argmax_distance, 2),
                _number(m.success_pct, 1),
                _number(m.miss_pct, 1),
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_curves(
    metrics: dict[str, dict[str, SplitMetrics]], methods: Sequence[str], quantity: str, path: Path
) -> None:
    """One panel per split: the mean of `quantity` ("ig" or "mass") per method against progress, +- SE."""
    import numpy as np
    from matplotlib.figure import Figure

    ylabel = {"ig": "Information gain at the target (nats)", "mass": "Target probability mass"}[quantity]
    fig = Figure(figsize=(11, 4.4), layout="constrained")
    axes = fig.subplots(1, len(SPLIT_TITLES), sharey=True)
    for ax, (split, title) in zip(axes, SPLIT_TITLES.items(), strict=True):
        for method in methods:
            m = metrics[method][split]
            if m.n == 0:
                continue
            x = np.asarray(m.progress)
            mean = np.asarray(m.ig_curve_mean if quantity == "ig" else m.mass_curve_mean, dtype=float)
            se = np.asarray(m.ig_curve_se if quantity == "ig" else m.mass_curve_se, dtype=float)
            colour = METHOD_COLOURS.get(method)
            ax.plot(x, mean, color=colour, linewidth=2, label=METHOD_TITLES.get(method, method))
            if np.all(np.isfinite(se)):
                ax.fill_between(x, mean - se, mean + se, color=colour, alpha=0.2, linewidth=0)
        if quantity == "ig":
            ax.axhline(0.0, color="black", linewidth=0.8, linestyle=":")
        n = metrics[methods[0]][split].n
        ax.set_title(f"{title} (n={n})")
        ax.set_xlabel("Normalised trajectory progress")
        ax.set_xlim(0.0, 1.0)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(ylabel)
    axes[0].legend(loc="best", fontsize=9)
    fig.savefig(path, dpi=120)


def write_report(
    result: SimResult, out_dir: str | Path, success_mass: float, command: str | None = None
) -> str:
    """Write metrics.json, table.md, episodes.jsonl, information_gain.png and target_mass.png into
    `out_dir`; returns the table."""
    out = Path(out_dir)
    methods = list(result.methods)
    metrics = aggregate(result.outcomes, methods, success_mass)
    document = metrics_document(result, metrics, success_mass, command)
    write_text_atomic(out / "metrics.json", json.dumps(document, indent=2) + "\n")
    with atomic_write(out / "episodes.jsonl") as fh:
        for record in result.records:
            fh.write(json.dumps(_clean(record.to_dict())) + "\n")
    table = render_table(metrics, methods)
    write_text_atomic(out / "table.md", _table_page(table, document))
    plot_curves(metrics, methods, "ig", out / "information_gain.png")
    plot_curves(metrics, methods, "mass", out / "target_mass.png")
    return table


def _table_page(table: str, document: dict[str, Any]) -> str:
    """table.md: the table, then how it was made."""
    config, episodes = document["config"], document["episodes"]
    skipped = ", ".join(f"{k}: {v}" for k, v in episodes["skipped"].items()) or "none"
    lines = [
        table,
        f"{episodes['run']} episodes of {config['steps']} steps (seed {config['seed']}); skipped: {skipped}.",
        setting_line(document),
        f"Mean IG and mass at the last step, +- standard error; success: terminal target mass >= "
        f"{config['success_mass']}; miss: below the uniform prior's. Definitions: `app/sim/metrics.py`.",
    ]
    if document.get("command"):
        lines.append(f"\nCommand: `{document['command']}`")
    return "\n".join(lines) + "\n"


def render_summary(documents: dict[str, dict[str, Any]]) -> str:
    """Markdown: several runs' metrics.json side by side (setting name -> document), a row per setting and
    method, the observed and never-observed splits' n, mean IG +- SE, success % and miss %."""
    lines = [
        "| Setting | Method | Observed: n | IG (nats) | Success % | Miss % | Never observed: n | IG (nats) "
        "| Success % | Miss % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, document in documents.items():
        for k, method in enumerate(document["methods"]):
            cells = [name if k == 0 else "", METHOD_TITLES.get(method, method)]
            for split in ("observed", "unobserved"):
                m = document["metrics"][method][split]
                cells += [
                    str(m["n"]),
                    _pm(m["mean_ig"], m["se_ig"], 2),
                    _number(m["success_pct"], 1),
                    _number(m["miss_pct"], 1),
                ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m app.sim.report NAME=DIR ...`: the summary table of several `vlmap sim` output folders."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("runs", nargs="+", help="NAME=DIR: a setting's name and its vlmap sim --out folder")
    args = parser.parse_args(argv)
    documents = {}
    for run in args.runs:
        name, _, folder = run.rpartition("=")
        path = Path(folder) / "metrics.json"
        documents[name or folder] = json.loads(path.read_text(encoding="utf-8"))
    print(render_summary(documents), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
