"""Fitting the built-in proposer's weights on grounding cases, and scoring its calibration.

The proposer's weights form a conditional logit model: for a case with candidate hypotheses h = 1..H, feature
rows x_h (standardised) and relation r,

    P(h | utterance, map) = exp(w_r . x_h) / sum_h' exp(w_r . x_h'),

fitted by maximum likelihood of the true hypothesis with an L2 penalty,

    L(W) = (1 / C) sum_cases -log P(h_true) + (lambda / 2) ||W||^2,

which is convex; L-BFGS with the analytic gradient dL/dw_r = (1 / C) sum_{cases of r} (E_P[x] - x_true)
+ lambda w_r. lambda is selected on val_seen, and the result reported on val_unseen, per ambiguity level
(how many objects share the true anchor's label: 1, 2, 3-4, 5+) with the same metrics as `vlmap eval
static` (top-1 accuracy, true-hypothesis NLL, ECE of the weights), next to the same weights with no cap on
the number of hypotheses and to uniform weights (over the returned hypotheses, and over all candidates).
`fit_temperature` then fits one softmax temperature T on val_seen the same way: P = softmax(w_r . x / T).

`vlmap fit-proposer --cases data/cases --out models/proposer/` writes params.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.data.cases import GroundingCase
from app.grounding.builtin import (
    BuiltinProposer,
    Candidates,
    ProposerParams,
    lemmas,
    softmax,
)
from app.grounding.parsing import normalise, parse_utterance
from app.grounding.referent_features import N_FEATURES
from app.grounding.relations import Relation

log = logging.getLogger("vlmap.proposer")

SPLITS = ("train", "val_seen", "val_unseen")
DEFAULT_L2_GRID = (0.001, 0.003, 0.01, 0.03, 0.1)
_RELATIONS = tuple(Relation)


# --- reading cases ------------------------------------------------------------------------------------------


def iter_cases(path: Path, every: int = 1, originals_only: bool = True) -> Iterator[GroundingCase]:
    """Cases of a JSONL file streamed line by line: every `every`-th one, augmented copies skipped."""
    seen = 0
    with path.open(encoding="utf-8") as fh:
        for line in fh:
            if not line.strip():
                continue
            raw = json.loads(line)
            if originals_only and raw.get("meta", {}).get("augmentation", 0):
                continue
            seen += 1
            if (seen - 1) % every:
                continue
            yield GroundingCase.model_validate(raw)


def target_box_table(cases: Sequence[GroundingCase], min_count: int = 3) -> dict[str, list[float]]:
    """Median target (dx, dy, dz, centre height above the floor) per lemmatised target label, for labels
    seen at least `min_count` times; the floor is the lowest object bottom of the case's scene."""
    boxes: dict[str, list[list[float]]] = {}
    for case in cases:
        if case.target.size is None or not case.scene_graph.objects:
            continue
        floor = min(float(o.min_corner[2]) for o in case.scene_graph.objects)
        box = [*case.target.size, case.target.position[2] - floor]
        boxes.setdefault(lemmas(case.target.label), []).append(box)
    return {k: np.median(v, axis=0).round(4).tolist() for k, v in boxes.items() if len(v) >= min_count}


# --- one case as rows of features ---------------------------------------------------------------------------


@dataclass(frozen=True)
class CaseRows:
    """A case's candidate hypotheses as features, with the index of the true one (-1: not a candidate)."""

    relation: Relation
    features: np.ndarray  # (H, F); (0, F) when the proposal is not grounded
    attribute: np.ndarray  # (H,)
    true_row: int
    ambiguity: str
    relation_parsed: bool  # the parse found the true relation
    anchors_parsed: bool  # the parsed anchor phrases name the true anchors' labels


def case_rows(proposer: BuiltinProposer, case: GroundingCase) -> CaseRows:
    """Featurise one case as the proposer does at run time, and find its true hypothesis."""
    from app.evaluation.static import ambiguity_bucket, case_ambiguity

    if not case.hypotheses:
        msg = f"case {case.case_id} carries no true hypothesis"
        raise ValueError(msg)
    truth = case.hypotheses[0]
    region_names = tuple(normalise(r.name) for r in case.scene_graph.regions if r.name)
    parse = parse_utterance(case.utterance, region_names)
    labels = {o.id: o.label for o in case.scene_graph.objects}
    anchors_parsed = _phrases_name(parse.anchor_phrases, [labels[a] for a in truth.anchor_ids])
    found = proposer.candidates(case.scene_graph, parse)
    if isinstance(found, str):  # not grounded: no candidate at all
        relation, features, attribute, true_row = parse.relation, np.zeros((0, N_FEATURES)), np.zeros(0), -1
    else:
        relation, features, attribute = found.relation, found.features, found.attribute
        true_row = _true_row(found, frozenset(truth.anchor_ids))
    return CaseRows(
        relation=relation,
        features=features,
        attribute=attribute,
        true_row=true_row,
        ambiguity=ambiguity_bucket(case_ambiguity(case)),
        relation_parsed=parse.relation is truth.relation,
        anchors_parsed=anchors_parsed,
    )


def _true_row(found: Candidates, truth: frozenset[str]) -> int:
    for row in range(len(found.groups)):
        if frozenset(found.anchor_ids(row)) == truth:
            return row
    return -1


def _phrases_name(phrases: tuple[str, ...], labels: list[str]) -> bool:
    """Whether the anchor phrases are what the data generator says for these labels (label or synonym)."""
    from app.data.templates import LABEL_SYNONYMS

    if len(phrases) != len(labels):
        return False
    said = [{label.lower(), *LABEL_SYNONYMS.get(label.lower(), ())} for label in labels]
    in_order = all(p in s for p, s in zip(phrases, said, strict=True))
    return in_order or (len(phrases) == 2 and phrases[0] in said[1] and phrases[1] in said[0])


def featurise(proposer: BuiltinProposer, cases: Sequence[GroundingCase], name: str = "") -> list[CaseRows]:
    start = time.perf_counter()
    rows = [case_rows(proposer, c) for c in cases]
    log.info("featurised %d %s cases in %.1f s", len(rows), name, time.perf_counter() - start)
    return rows


# --- the conditional logit ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class LogitProblem:
    """Cases stacked for fitting: rows (M, F) standardised, each case a contiguous block."""

    x: np.ndarray  # (M, F)
    offsets: np.ndarray  # (C,) first row of each case
    relation_of_row: np.ndarray  # (M,) relation index
    relation_of_case: np.ndarray  # (C,)
    true_rows: np.ndarray  # (C,) global row index of the true hypothesis
    case_of_row: np.ndarray  # (M,)


def logit_problem(
    cases: Sequence[tuple[int, np.ndarray, int]], mean: np.ndarray, scale: np.ndarray
) -> LogitProblem:
    """Cases as (relation index, features (H, F), true row); cases with H < 2 or no true row carry no
    information and are dropped."""
    used = [(r, f, t) for r, f, t in cases if len(f) >= 2 and t >= 0]
    if not used:
        msg = "no case has two or more candidates with the true one among them: nothing to fit"
        raise ValueError(msg)
    sizes = np.array([len(f) for _, f, _ in used])
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    x = (np.concatenate([f for _, f, _ in used]) - mean) / scale
    relation_of_case = np.array([r for r, _, _ in used])
    return LogitProblem(
        x=x,
        offsets=offsets,
        relation_of_row=np.repeat(relation_of_case, sizes),
        relation_of_case=relation_of_case,
        true_rows=offsets + np.array([t for _, _, t in used]),
        case_of_row=np.repeat(np.arange(len(used)), sizes),
    )


def logit_loss(
    w_flat: np.ndarray, problem: LogitProblem, l2: float, n_relations: int
) -> tuple[float, np.ndarray]:
    """L(W) and dL/dW (flattened (R, F)) of the penalised conditional logit."""
    w = w_flat.reshape(n_relations, -1)  # (R, F)
    x = problem.x
    scores = np.einsum("mf,mf->m", x, w[problem.relation_of_row])  # (M,)
    top = np.maximum.reduceat(scores, problem.offsets)  # (C,)
    exp = np.exp(scores - top[problem.case_of_row])
    total = np.add.reduceat(exp, problem.offsets)  # (C,)
    lse = top + np.log(total)
    n_cases = len(problem.offsets)
    loss = float(np.sum(lse - scores[problem.true_rows])) / n_cases + 0.5 * l2 * float(np.sum(w * w))
    prob = exp / total[problem.case_of_row]  # (M,)
    grad = np.zeros_like(w)
    weighted = prob[:, None] * x
    for r in range(n_relations):
        grad[r] = weighted[problem.relation_of_row == r].sum(axis=0)
        grad[r] -= x[problem.true_rows[problem.relation_of_case == r]].sum(axis=0)
    grad = grad / n_cases + l2 * w
    return loss, grad.ravel()


def fit_conditional_logit(problem: LogitProblem, l2: float, n_relations: int = len(_RELATIONS)) -> np.ndarray:
    """The weights (R, F) minimising `logit_loss`."""
    from scipy.optimize import minimize

    n_features = problem.x.shape[1]
    result = minimize(
        logit_loss,
        np.zeros(n_relations * n_features),
        args=(problem, l2, n_relations),
        jac=True,
        method="L-BFGS-B",
        options={"maxiter": 2000},
    )
    if not result.success:
        log.warning("conditional logit fit stopped early: %s", result.message)
    return np.asarray(result.x).reshape(n_relations, n_features)


def fit_temperature(scores: Sequence[np.ndarray], true_rows: Sequence[int]) -> float:
    """T minimising the mean of -log softmax(s / T)_true over cases (cases without a true row skipped)."""
    from scipy.optimize import minimize_scalar

    used = [(s, t) for s, t in zip(scores, true_rows, strict=True) if t >= 0 and len(s) >= 2]
    if not used:
        msg = "no case to fit a temperature on"
        raise ValueError(msg)

    def nll(log_t: float) -> float:
        inverse = math.exp(-log_t)
        total = 0.0
        for s, t in used:
            z = s * inverse
            top = float(np.max(z))
            total += top + math.log(float(np.sum(np.exp(z - top)))) - float(z[t])
        return total / len(used)

    result = minimize_scalar(nll, bounds=(math.log(0.01), math.log(100.0)), method="bounded")
    return float(math.exp(result.x))


def standardisation(rows: Sequence[CaseRows]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and scale (standard deviation, 1 for constant features) over all candidate rows."""
    stacked = np.concatenate([r.features for r in rows if len(r.features)])
    scale = stacked.std(axis=0)
    return stacked.mean(axis=0), np.where(scale > 1e-6, scale, 1.0)


def params_with(
    base: ProposerParams, weights: np.ndarray, mean: np.ndarray, scale: np.ndarray
) -> ProposerParams:
    return dataclasses.replace(
        base,
        weights={r: weights[i] for i, r in enumerate(_RELATIONS)},
        feature_mean=mean,
        feature_scale=scale,
    )


# --- scoring ------------------------------------------------------------------------------------------------


def proposal_weights(
    params: ProposerParams, row: CaseRows, max_hypotheses: int
) -> tuple[np.ndarray, np.ndarray]:
    """(weights, correct) of the hypotheses the proposer returns: the heaviest, renormalised."""
    if len(row.features) == 0:
        return np.zeros(0), np.zeros(0, dtype=bool)
    weights = softmax(params.scores(row.relation, row.features, row.attribute))
    order = np.argsort(-weights, kind="stable")[:max_hypotheses]
    return weights[order] / weights[order].sum(), order == row.true_row


def referent_report(
    params: ProposerParams, rows: Sequence[CaseRows], max_hypotheses: int = 5
) -> dict[str, Any]:
    """Referent metrics (overall with reliability bins, per ambiguity) of the proposer's weights, of its
    weights over all candidates (no cap on the number of hypotheses), of uniform weights over the same
    returned hypotheses and of uniform weights over all candidates; how often the true hypothesis is a
    candidate and among those returned; the parse accuracy."""
    from app.evaluation.static import ReferentScore, group_referent

    builtin, uncapped, uniform_returned, uniform_candidates = [], [], [], []
    for row in rows:
        weights, correct = proposal_weights(params, row, max_hypotheses)
        builtin.append(ReferentScore(row.ambiguity, weights, correct))
        uncapped.append(ReferentScore(row.ambiguity, *proposal_weights(params, row, len(row.features))))
        uniform_returned.append(
            ReferentScore(row.ambiguity, np.full(len(weights), 1.0 / max(len(weights), 1)), correct)
        )
        n = len(row.features)
        every = ReferentScore(row.ambiguity, np.full(n, 1.0 / max(n, 1)), np.arange(n) == row.true_row)
        uniform_candidates.append(every)
    n_cases = max(len(rows), 1)
    return {
        "n": len(rows),
        "builtin": group_referent(builtin),
        "builtin_uncapped": group_referent(uncapped),
        "uniform_returned": group_referent(uniform_returned),
        "uniform_candidates": group_referent(uniform_candidates),
        "true_among_candidates": sum(r.true_row >= 0 for r in rows) / n_cases,
        "true_among_returned": sum(bool(np.any(s.correct)) for s in builtin) / n_cases,
        "mean_candidates": float(np.mean([len(r.features) for r in rows])) if rows else 0.0,
        "parse": {
            "relation_accuracy": sum(r.relation_parsed for r in rows) / n_cases,
            "anchor_phrase_accuracy": sum(r.anchors_parsed for r in rows) / n_cases,
        },
    }


def _nll_of(report: dict[str, Any]) -> float:
    return float(report["builtin"]["overall"]["true_hypothesis_nll"])


# --- the whole fit ------------------------------------------------------------------------------------------


def split_paths(cases: Path) -> dict[str, Path]:
    """train / val_seen / val_unseen files of a `vlmap data build` folder, or one file used for all three."""
    if cases.is_file():
        return {"train": cases}
    paths = {s: cases / f"{s}.jsonl" for s in SPLITS}
    if not paths["train"].is_file():
        msg = f"{cases} holds no train.jsonl (pass the folder written by `vlmap data build`, or one file)"
        raise FileNotFoundError(msg)
    return {s: p for s, p in paths.items() if p.is_file()}


def fit_proposer(
    cases: Path,
    encoder: Any,
    train_every: int = 1,
    l2_grid: Sequence[float] = DEFAULT_L2_GRID,
    max_hypotheses: int = 5,
) -> ProposerParams:
    """Fit on train (originals, every `train_every`-th), select lambda on val_seen, report on val_unseen."""
    from app.lsm.text_encoder import file_sha256

    paths = split_paths(cases)
    train_cases = list(iter_cases(paths["train"], every=train_every))
    table = target_box_table(train_cases)
    base = ProposerParams.untrained(target_boxes=table, encoder_sha256=encoder.sha256)
    if table:
        base.default_target_box = tuple(float(v) for v in np.median(list(table.values()), axis=0))  # type: ignore[assignment]
    proposer = BuiltinProposer(encoder, base, max_hypotheses)
    rows = {"train": featurise(proposer, train_cases, "train")}
    for split in ("val_seen", "val_unseen"):
        if split in paths:
            rows[split] = featurise(proposer, list(iter_cases(paths[split])), split)
    mean, scale = standardisation(rows["train"])
    relation_index = {r: i for i, r in enumerate(_RELATIONS)}
    problem = logit_problem(
        [(relation_index[r.relation], r.features, r.true_row) for r in rows["train"]], mean, scale
    )

    selection_split = "val_seen" if "val_seen" in rows else "train"
    selection: dict[str, float] = {}
    fitted: dict[float, ProposerParams] = {}
    for l2 in l2_grid:
        start = time.perf_counter()
        fitted[l2] = params_with(base, fit_conditional_logit(problem, l2), mean, scale)
        selection[str(l2)] = _nll_of(referent_report(fitted[l2], rows[selection_split], max_hypotheses))
        log.info(
            "l2=%g: %s NLL %.4f (%.1f s)",
            l2,
            selection_split,
            selection[str(l2)],
            time.perf_counter() - start,
        )
    best = min(l2_grid, key=lambda v: selection[str(v)])
    # A last softmax temperature on the selection split: the penalty and the shift between splits can leave
    # the fitted scores a little too sharp or too flat.
    chosen = fitted[best]
    held_out = [r for r in rows[selection_split] if len(r.features)]
    temperature = fit_temperature(
        [chosen.scores(r.relation, r.features, r.attribute) for r in held_out], [r.true_row for r in held_out]
    )
    params = dataclasses.replace(chosen, temperature=round(temperature, 4))
    params.info = {
        "fitted_on": {
            split: {"path": str(path), "sha256": file_sha256(path), "cases": len(rows[split])}
            for split, path in paths.items()
        },
        "train_subsample": {"originals_only": True, "every": train_every, "fit_cases": len(problem.offsets)},
        "model": "conditional logit (weights per relation on standardised features), softmax temperature",
        "selection": {
            "split": selection_split,
            "true_hypothesis_nll_by_l2": selection,
            "l2": best,
            "temperature": params.temperature,
        },
        "max_hypotheses": max_hypotheses,
        "metrics": {split: referent_report(params, r, max_hypotheses) for split, r in rows.items()},
    }
    return params


def summary_table(report: dict[str, Any]) -> str:
    """Per ambiguity level: top-1, true-hypothesis NLL and ECE of the proposer; NLL and ECE of its weights
    with no cap on the hypotheses, and of uniform weights over the returned hypotheses; top-1, NLL and ECE of
    uniform weights over all candidates."""
    methods = ("builtin", "builtin_uncapped", "uniform_returned", "uniform_candidates")
    lines = [
        f"{'':>10} {'':>6} | {'builtin':^22} | {'builtin, no cap':^15} | {'uniform, returned':^15} | "
        f"{'uniform, all candidates':^24}",
        f"{'ambiguity':>10} {'n':>6} | {'top1':>6} {'NLL':>7} {'ECE':>7} | {'NLL':>7} {'ECE':>7} | "
        f"{'NLL':>7} {'ECE':>7} | {'top1':>8} {'NLL':>7} {'ECE':>7}",
    ]
    for level in ["overall", *report["builtin"]["per_ambiguity"]]:
        b, u, r, c = (
            report[m]["overall"] if level == "overall" else report[m]["per_ambiguity"][level] for m in methods
        )
        lines.append(
            f"{level:>10} {b['n']:>6} | {b['top1_accuracy']:6.3f} {b['true_hypothesis_nll']:7.3f} "
            f"{_num(b['ece'])} | {u['true_hypothesis_nll']:7.3f} {_num(u['ece'])} | "
            f"{r['true_hypothesis_nll']:7.3f} {_num(r['ece'])} | "
            f"{c['top1_accuracy']:8.3f} {c['true_hypothesis_nll']:7.3f} {_num(c['ece'])}"
        )
    return "\n".join(lines)


def _num(value: float | None) -> str:
    return f"{'-':>7}" if value is None else f"{value:7.3f}"


# --- vlmap fit-proposer -------------------------------------------------------------------------------------


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "fit-proposer",
        help="fit the built-in referent proposer's calibrated weights on grounding cases",
        description=(
            "Fit the built-in proposer's conditional logit on DIR/train.jsonl (original cases, no augmented "
            "copies), select its L2 penalty on DIR/val_seen.jsonl, report on DIR/val_unseen.jsonl, and write "
            "OUT/params.json with the weights, the data they were fitted on and the metrics."
        ),
    )
    parser.add_argument(
        "--cases", type=Path, required=True, help="folder of `vlmap data build`, or one JSONL"
    )
    parser.add_argument("--out", type=Path, default=Path("models/proposer"), help="output folder")
    parser.add_argument("--train-every", type=int, default=1, help="use every N-th original train case")
    parser.add_argument(
        "--l2", type=float, nargs="+", default=list(DEFAULT_L2_GRID), help="L2 penalties to try"
    )
    parser.add_argument("--max-hypotheses", type=int, default=5)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.lsm.text_encoder import TextEncoder

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    # Fitted on float32 embeddings, like the LSM; serving may use the bfloat16 pass (cosine 0.99998).
    encoder = TextEncoder(precision="float32")
    params = fit_proposer(args.cases, encoder, args.train_every, args.l2, args.max_hypotheses)
    out = args.out / "params.json"
    params.save(out)
    metrics = params.info["metrics"]
    for split in ("val_seen", "val_unseen", "train"):
        if split in metrics:
            report = metrics[split]
            print(f"\n{split}: {report['n']} cases; parse {report['parse']}")
            print(
                f"{report['mean_candidates']:.1f} candidates per case; the true hypothesis among them "
                f"{report['true_among_candidates']:.3f}, among the returned "
                f"{report['true_among_returned']:.3f}"
            )
            print(summary_table(report))
    selection = params.info["selection"]
    print(f"\nwrote {out} (l2 = {selection['l2']}, temperature = {selection['temperature']})")
    return 0
