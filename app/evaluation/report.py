"""The static evaluation's report: Markdown tables (methods x metrics) and PNG calibration plots.

Both read only what `app.evaluation.static` writes (the metrics dictionary of metrics.json, and for the
histogram of NLL - uniform_nll the rows of per_case.jsonl), so a report can be redrawn from saved files.
Every NLL stands beside the no-language baseline ("NLL U", the uniform density over the map's box) and the
share of cases that beat it ("< U").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from app.evaluation.metrics import DEFAULT_MASSES

_NOT_METHODS = ("config", "referent", "run")
_CALIBRATED_ANEES = 3.0


def evaluated_methods(metrics: dict[str, Any]) -> list[str]:
    """The evaluated methods, in the order they were run."""
    configured = metrics.get("config", {}).get("methods")
    if configured:
        return [m for m in configured if m in metrics]
    return [k for k, v in metrics.items() if k not in _NOT_METHODS and isinstance(v, dict) and "overall" in v]


def _number(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if abs(value) >= 1e5:
        return f"{value:.3g}"
    return f"{value:.{digits}f}"


def _interval(bounds: Sequence[float] | None, digits: int) -> str:
    if not bounds:
        return "-"
    return f"{_number(bounds[0], digits)}-{_number(bounds[1], digits)}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 1) -> list[str]:
    align = [":--"] * left + ["--:"] * (len(header) - left)
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def _metric_header(with_uniform: bool, with_matched: bool) -> list[str]:
    header = ["n", "RMSE (m)", "NLL", "NLL U", "< U", "ANEES", "ANEES 90% (rooms)"]
    if with_matched:
        header.append("ANEES n")
    header += ["ANEES full", *(f"cov {m:g}" for m in DEFAULT_MASSES)]
    if with_uniform:
        header.append("NLL, uniform w")
    return header


def _metric_cells(summary: dict[str, Any], with_uniform: bool, with_matched: bool) -> list[str]:
    coverage = summary.get("coverage", {})
    cells = [
        str(summary.get("n", 0)),
        _number(summary.get("rmse"), 3),
        _number(summary.get("nll"), 2),
        _number(summary.get("uniform_nll"), 2),
        _number(summary.get("better_than_uniform"), 3),
        _number(summary.get("anees"), 2),
        _interval(summary.get("anees_ci90"), 2),
    ]
    if with_matched:
        cells.append(str(summary.get("anees_n", 0)))
    cells.append(_number(summary.get("anees_full"), 2))
    cells += [_number(coverage.get(str(m)), 3) for m in DEFAULT_MASSES]
    if with_uniform:
        cells.append(_number(summary.get("uniform_weights_nll"), 2))
    return cells


def _groups(metrics: dict[str, Any], methods: Sequence[str]) -> list[tuple[str, str, str]]:
    """(label, metrics key, group name): overall, then every relation, then every ambiguity level."""
    out = [("all", "overall", "")]
    for key, title in (("per_relation", "relation"), ("per_ambiguity", "ambiguity")):
        names = dict.fromkeys(g for m in methods for g in metrics[m].get(key, {}))
        out += [(f"{title} {g}", key, g) for g in names]
    return out


def _baseline_table(metrics: dict[str, Any], methods: Sequence[str]) -> list[str]:
    """Group x method: NLL against the no-language baseline, the mean and the worst excess over it."""
    header = ["group", "method", "n", "NLL", "NLL U", "< U", "NLL - U", "worst excess", "outside U"]
    rows = []
    for label, key, group in _groups(metrics, methods):
        for m in methods:
            summary = metrics[m][key] if key == "overall" else metrics[m].get(key, {}).get(group)
            if not summary or "better_than_uniform" not in summary:
                continue
            rows.append(
                [
                    label,
                    m,
                    str(summary["n"]),
                    _number(summary.get("nll"), 2),
                    _number(summary.get("uniform_nll"), 2),
                    _number(summary.get("better_than_uniform"), 3),
                    _number(summary.get("nll_minus_uniform"), 2),
                    _number(summary.get("worst_excess_over_uniform"), 2),
                    str(summary.get("uniform_outside", 0)),
                ]
            )
    if not rows:
        return []
    return [
        "## Against no language",
        "",
        *_table(header, rows, left=2),
        "",
        "NLL U: -log of the uniform density over the map's box (every object box, sides >= 0.1 m), what is "
        "known without the utterance; < U: share of cases with a lower NLL; NLL - U (mean) and worst "
        "excess (max) over the cases inside the box; outside U: targets outside it (NLL U infinite, "
        "counted in < U).",
        "",
    ]


def format_report(metrics: dict[str, Any]) -> str:
    """Markdown: overall, per relation, per ambiguity (methods side by side), then the proposer's weights."""
    methods = evaluated_methods(metrics)
    config = metrics.get("config", {})
    with_uniform = any("uniform_weights_nll" in metrics[m]["overall"] for m in methods)
    with_matched = any(metrics[m]["overall"].get("unmatched", 0) for m in methods)
    lines = ["# Static evaluation", ""]
    if config:
        proposer = config.get("proposer", "?")
        if config.get("proposer_impl") not in (None, proposer):
            proposer += f" ({config['proposer_impl']})"
        lines += [
            f"`{config.get('cases')}`: {config.get('n')} cases, proposer {proposer}, "
            f"seed {config.get('seed')}, {config.get('hdr_samples')} Monte Carlo draws per mixture HDR.",
            "",
        ]

    lines += ["## Overall", ""]
    header = ["method", *_metric_header(with_uniform, with_matched), "failures"]
    rows = [
        [
            m,
            *_metric_cells(metrics[m]["overall"], with_uniform, with_matched),
            str(metrics[m].get("failures", {}).get("count", 0)),
        ]
        for m in methods
    ]
    lines += [*_table(header, rows), ""]

    for key, title in (("per_relation", "relation"), ("per_ambiguity", "ambiguity")):
        groups = list(dict.fromkeys(g for m in methods for g in metrics[m].get(key, {})))
        if not groups:
            continue
        lines += [f"## Per {title}", ""]
        header = [title, "method", *_metric_header(with_uniform, with_matched)]
        rows = [
            [group, m, *_metric_cells(metrics[m][key][group], with_uniform, with_matched)]
            for group in groups
            for m in methods
            if group in metrics[m].get(key, {})
        ]
        lines += [*_table(header, rows, left=2), ""]

    lines += _baseline_table(metrics, methods)

    referent = metrics.get("referent")
    if referent:
        lines += ["## Referent: the proposer's weights", ""]
        header = ["ambiguity", "n", "top-1 accuracy", "true-hypothesis NLL", "absent", "ECE", "hypotheses"]
        groups = [("all", referent["overall"]), *referent.get("per_ambiguity", {}).items()]
        rows = [
            [
                name,
                str(s.get("n", 0)),
                _number(s.get("top1_accuracy"), 3),
                _number(s.get("true_hypothesis_nll"), 3),
                str(s.get("absent", 0)),
                _number(s.get("ece"), 3),
                _number(s.get("mean_hypotheses"), 2),
            ]
            for name, s in groups
        ]
        lines += [*_table(header, rows), ""]
        lines += [
            "absent: cases whose hypotheses never hold the true anchors (scored -log 1e-6); hypotheses: mean "
            "number per case.",
            "",
        ]

    problems = [
        f"- {m}: {metrics[m]['failures']['count']} failed cases, e.g. {metrics[m]['failures']['examples'][0]}"
        for m in methods
        if metrics[m].get("failures", {}).get("count")
    ]
    proposer_failures = metrics.get("run", {}).get("proposer_failures", {})
    if proposer_failures.get("count"):
        problems.append(
            f"- proposer: {proposer_failures['count']} failed cases, e.g. {proposer_failures['examples'][0]}"
        )
    if config.get("llm_fallbacks"):
        problems.append(f"- LLM proposer fell back to the built-in one: {config['llm_fallbacks']}")
    skipped = metrics.get("run", {}).get("skipped_without_truth")
    if skipped:
        problems.append(f"- {skipped} cases without true hypotheses skipped (--proposer gt needs them)")
    if problems:
        lines += ["## Failures", "", *problems, ""]
    return "\n".join(lines)


def write_plots(
    metrics: dict[str, Any], out_dir: Path, per_case: Sequence[dict[str, Any]] = ()
) -> list[Path]:
    """anees_per_relation.png, coverage.png, (with a proposer) reliability.png and (given the per-case rows)
    nll_minus_uniform.png in `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [_anees_per_relation(metrics, out_dir / "anees_per_relation.png")]
    written.append(_coverage(metrics, out_dir / "coverage.png"))
    if metrics.get("referent", {}).get("overall", {}).get("reliability"):
        written.append(_reliability(metrics["referent"]["overall"], out_dir / "reliability.png"))
    excess = _excess_over_uniform(evaluated_methods(metrics), per_case)
    if any(excess.values()):
        written.append(_excess_histogram(excess, out_dir / "nll_minus_uniform.png"))
    return written


def _excess_over_uniform(
    methods: Sequence[str], per_case: Sequence[dict[str, Any]]
) -> dict[str, list[float]]:
    """Per method, NLL - uniform_nll of every case it scored with the target inside the map's box."""
    return {
        m: [
            row[m]["nll"] - row["uniform_nll"]
            for row in per_case
            if row.get("uniform_nll") is not None and "nll" in row.get(m, {})
        ]
        for m in methods
    }


def _excess_histogram(excess: dict[str, list[float]], path: Path) -> Path:
    """Histogram of NLL - uniform_nll per case and method; left of 0 the utterance helped.

    A wrong anchor costs hundreds of nats, which would squeeze every other case into one bar: the axis spans
    the 1st to the 97th percentile (and 0), the cases beyond are drawn in the end bins and counted below.
    """
    import numpy as np
    from matplotlib.figure import Figure

    values = np.concatenate([v for v in excess.values() if v])
    low = min(-1.0, float(np.percentile(values, 1)))
    high = max(1.0, float(np.percentile(values, 97)))
    edges = np.linspace(low, high, 61).tolist()
    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    ax = fig.add_subplot()
    for m, v in excess.items():
        if v:
            better = float(np.mean(np.asarray(v) < 0.0))
            ax.hist(
                np.clip(v, low, high),
                bins=edges,
                histtype="step",
                linewidth=1.5,
                label=f"{m} ({better:.0%} below 0)",
            )
    ax.axvline(0.0, color="black", linestyle="--", linewidth=1, label="no language")
    beyond = int(np.sum((values < low) | (values > high)))
    ax.set_xlabel(f"NLL - NLL U, nats (U: uniform over the map's box; {beyond} outliers in the end bins)")
    ax.set_ylabel("cases")
    ax.set_title("Against no language (left of 0: the utterance helped)")
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=120)
    return path


def _anees_per_relation(metrics: dict[str, Any], path: Path) -> Path:
    """Grouped bars with their 90% intervals over rooms, log scale (overconfident baselines reach the
    hundreds), the calibrated 3 as a line."""
    import numpy as np
    from matplotlib.figure import Figure

    methods = evaluated_methods(metrics)
    relations = list(dict.fromkeys(r for m in methods for r in metrics[m].get("per_relation", {})))
    fig = Figure(figsize=(max(6.0, 1.1 * len(relations) + 2.0), 4.0), layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(relations))
    for j, m in enumerate(methods):
        groups = [metrics[m]["per_relation"].get(r, {}) for r in relations]
        heights = np.array([math.nan if g.get("anees") is None else g["anees"] for g in groups])
        bounds = np.array([g.get("anees_ci90") or [math.nan, math.nan] for g in groups]).reshape(-1, 2)
        errors = np.abs(bounds.T - heights)  # (2, R): below and above the bar; nan draws no whisker
        ax.bar(x + (j - (len(methods) - 1) / 2) * width, heights, width, yerr=errors, capsize=2, label=m)
    ax.axhline(_CALIBRATED_ANEES, color="black", linestyle="--", linewidth=1, label="calibrated (3)")
    ax.set_yscale("log")
    ax.set_xticks(x, relations)
    ax.set_ylabel("ANEES (log scale)")
    ax.set_title("Calibration per relation: ANEES (3 = calibrated, above = overconfident)")
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=120)
    return path


def _coverage(metrics: dict[str, Any], path: Path) -> Path:
    """Observed HDR coverage against the nominal mass; a calibrated method lies on the diagonal."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.5, 4.5), layout="constrained")
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], color="black", linestyle="--", linewidth=1, label="calibrated")
    for m in evaluated_methods(metrics):
        coverage = metrics[m]["overall"].get("coverage", {})
        if coverage:
            ax.plot(DEFAULT_MASSES, [coverage[str(k)] for k in DEFAULT_MASSES], marker="o", label=m)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("HDR mass (nominal)")
    ax.set_ylabel("targets inside (observed)")
    ax.set_title("Coverage of the mixture's HDR")
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=120)
    return path


def _reliability(summary: dict[str, Any], path: Path) -> Path:
    """Fraction correct per weight bin against the bin's mean weight, with the pairs per bin below."""
    from matplotlib.figure import Figure

    bins = summary["reliability"]
    centres = [0.5 * (b["low"] + b["high"]) for b in bins]
    width = bins[0]["high"] - bins[0]["low"]
    fig = Figure(figsize=(5.0, 6.0), layout="constrained")
    top, bottom = fig.subplots(2, 1, height_ratios=[3, 1], sharex=True)
    top.plot([0, 1], [0, 1], color="black", linestyle="--", linewidth=1, label="calibrated")
    filled = [b for b in bins if b["n"]]
    top.bar(
        [0.5 * (b["low"] + b["high"]) for b in filled],
        [b["accuracy"] for b in filled],
        width * 0.9,
        alpha=0.7,
        label="fraction correct",
    )
    top.plot([b["mean_weight"] for b in filled], [b["accuracy"] for b in filled], "o-", color="C3")
    top.set_ylim(0, 1)
    top.set_ylabel("hypothesis holds the true anchors")
    top.set_title(f"Proposer weights: reliability (ECE {_number(summary.get('ece'), 3)})")
    top.legend(fontsize="small", loc="upper left")
    bottom.bar(centres, [b["n"] for b in bins], width * 0.9, color="grey")
    bottom.set_xlim(0, 1)
    bottom.set_xlabel("hypothesis weight")
    bottom.set_ylabel("hypotheses")
    fig.savefig(path, dpi=120)
    return path
