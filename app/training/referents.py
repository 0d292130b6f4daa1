"""Fitting the built-in proposer end to end: its hypothesis weights, the spreads of vague readings and the
broad term's weight, by the marginal likelihood of true target positions over the latent hypotheses.

For a case with target position y, hypotheses h = 1..H (features x_h, weight key k_h, spread c_h), the
grounder's density p_h (a core and a tail Gaussian, N(mu, c Sigma) and N(mu, c Sigma_tail) with weights
1 - a_h and a_h), utterance features g, the map's uniform density U and the broad density B:

    pi_h    = softmax_h( w_{k_h} . x'_h + alpha attr_h )               x' standardised
    beta    = beta_min + (1 - beta_min) sigmoid(v . g')
    p(y)    = (1 - beta) sum_h pi_h p_h(y; c_h) + beta_min U(y) + (beta - beta_min) B(y)
    L       = -(1/C) sum_cases [ log p(y) + gamma 1[built] log sum_{h true} pi_h ] + (lambda / 2) ||W, v||^2

The anchor of a human description is latent: only the position enters. Built cases (templated statements
whose true anchors are known) add the log-probability of their true hypotheses (weight gamma), which keeps
the referent weights calibrated where a house has ten beds. The spreads c_k = floor_k + softplus(.) widen
vague and view-dependent readings (floors `MIN_SPREADS`). Each p_h(y; c) comes in closed form from the
grounder's density at c = 1: with m = NEES and l = log|Sigma| of each component,
log N(y; mu, c Sigma) = -(l + 3 log c + m / c + 3 log 2 pi) / 2. L-BFGS minimises L (torch autograd);
lambda is chosen on a held-out part of the training scans, which then fits one temperature T of the
hypothesis scores (pi = softmax(s / T)).

`vlmap fit-proposer` (below) reads the cases, writes `params.json` and a report.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import time
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.data.cases import GroundingCase, read_cases
from app.errors import InvalidInput
from app.grounding.builtin import MIN_SPREADS, REGION, SPREADS, BuiltinProposer, ProposerParams
from app.grounding.hypotheses import MIN_BACKGROUND_WEIGHT, Hypothesis
from app.grounding.interfaces import Grounder
from app.grounding.mixture import map_box
from app.grounding.relations import Relation
from app.grounding.sensor import broad_density
from app.training.search import golden_section
from app.vocabulary import lemmas

if TYPE_CHECKING:
    from app.evaluation.static import ReferentScore

log = logging.getLogger("vlmap.proposer")

_LOG_2PI = math.log(2.0 * math.pi)
DEFAULT_L2_GRID = (0.003, 0.03, 0.3)
_KEYS = (*(r.value for r in Relation), REGION)


@dataclass(frozen=True)
class FitCase:
    """One case's hypotheses as the objective reads them."""

    case_id: str
    kind: str  # "human" or "built"
    keys: np.ndarray  # (H,) int: index into _KEYS
    features: np.ndarray  # (H, F)
    attribute: np.ndarray  # (H,)
    spreads: np.ndarray  # (H,) int: -1 none, else index into SPREADS
    density: np.ndarray  # (H, 6): log(1 - a), log a, log|Sigma|, NEES, log|Sigma_tail|, NEES_tail
    utterance_features: np.ndarray  # (G,)
    log_uniform: float  # log U(y): -log vol(map box), -inf outside it
    log_broad: float  # log B(y)
    correct: np.ndarray | None  # (H,) bool: holds the true anchors (built cases)
    anchors: tuple[tuple[str, ...], ...] = ()  # (H,) each row's anchor ids; () for a region row


def prepare_case(
    case: GroundingCase, proposer: BuiltinProposer, grounder: Grounder, kind: str
) -> FitCase | None:
    """Features and densities at the truth of every hypothesis the proposer makes for the case (None when
    it makes none)."""
    parse = proposer.parse(case.scene_graph, case.utterance)
    if not parse.english or not case.scene_graph.objects:
        return None
    found = proposer.candidates(case.scene_graph, parse)
    hypotheses = [
        Hypothesis(
            found.anchor_ids(h), found.relations[h], region_id=None if found.anchors[h] else found.region_id
        )
        for h in range(len(found.keys))
    ]
    y = np.asarray(case.target.position, dtype=np.float64)
    box = map_box(case.scene_graph)
    log_broad = float(broad_density(case.scene_graph, parse, box, found.avoid).logpdf(y[None])[0])
    # Under a negation the region reading is served as the broad density B itself (`BuiltinProposer.propose`
    # moves its weight into beta, which is the same mixture): its row scores log B(y).
    as_broad = [bool(found.avoid) and not found.anchors[h] for h in range(len(hypotheses))]
    density = np.empty((len(hypotheses), 6))
    grounded = [h for h in range(len(hypotheses)) if not as_broad[h]]
    densities = grounder.ground(case.scene_graph, case.utterance, [hypotheses[h] for h in grounded])
    for h, d in zip(grounded, densities, strict=True):
        density[h] = density_terms(d.weights, d.means, d.covariances, y)
    for h in np.flatnonzero(as_broad).tolist():
        density[h] = fixed_density_terms(log_broad)
    inside = bool(box.contains(y[None])[0])
    correct = None
    if case.hypotheses:
        truth = frozenset(case.hypotheses[0].anchor_ids)
        correct = np.array([frozenset(found.anchor_ids(h)) == truth for h in range(len(found.keys))])
    return FitCase(
        case_id=case.case_id,
        kind=kind,
        keys=np.array([_KEYS.index(k) for k in found.keys]),
        features=found.features,
        attribute=found.attribute,
        spreads=np.array([-1 if s is None else SPREADS.index(s) for s in found.spreads]),
        density=density,
        utterance_features=found.utterance_features,
        log_uniform=-math.log(box.volume) if inside else -math.inf,
        log_broad=log_broad,
        correct=correct,
        anchors=tuple(found.anchor_ids(h) for h in range(len(found.keys))),
    )


def density_terms(
    weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """(log(1 - a), log a, log|Sigma|, NEES, log|Sigma_tail|, NEES_tail) of a one- or two-component density
    (a = 0 and the tail = the core for one component)."""
    terms = []
    for cov, mean in zip(covariances[:2], means[:2], strict=True):
        chol = np.linalg.cholesky(cov)
        z = np.linalg.solve(chol, y - mean)
        terms.append((2.0 * float(np.sum(np.log(np.diag(chol)))), float(z @ z)))
    if len(terms) == 1:
        terms.append(terms[0])
        a = 0.0
    else:
        a = float(weights[1] / weights[:2].sum())
    with np.errstate(divide="ignore"):
        return np.array([math.log1p(-a), math.log(a) if a > 0 else -math.inf, *terms[0], *terms[1]])


def fixed_density_terms(log_density: float) -> np.ndarray:
    """The `density_terms` of a row without a spread (c = 1) whose density at the truth is `log_density`: one
    component (a = 0) with NEES 0 and log|Sigma| = -2 log_density - 3 log 2 pi, so the core term equals it."""
    log_det = -2.0 * log_density - 3.0 * _LOG_2PI
    return np.array([0.0, -math.inf, log_det, 0.0, log_det, 0.0])


# --- the objective ---


@dataclass(frozen=True)
class _Batch:
    """Every case's rows stacked, with the case each row belongs to (torch tensors)."""

    row_case: Any  # (R,) long
    keys: Any  # (R,) long
    features: Any  # (R, F)
    attribute: Any  # (R,)
    spreads: Any  # (R,) long, -1 none
    density: Any  # (R, 6)
    correct: Any  # (R,) bool
    utterance: Any  # (C, G)
    log_uniform: Any  # (C,)
    log_broad: Any  # (C,)
    built: Any  # (C,) bool
    n_cases: int


def _batch(
    cases: Sequence[FitCase], mean: np.ndarray, scale: np.ndarray, g_mean: np.ndarray, g_scale: np.ndarray
) -> _Batch:
    import torch

    row_case = np.concatenate([np.full(len(c.keys), i) for i, c in enumerate(cases)])

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(c, name) for c in cases])

    correct = np.concatenate(
        [c.correct if c.correct is not None else np.zeros(len(c.keys), bool) for c in cases]
    )
    return _Batch(
        row_case=torch.as_tensor(row_case),
        keys=torch.as_tensor(cat("keys")),
        features=torch.as_tensor((cat("features") - mean) / scale),
        attribute=torch.as_tensor(cat("attribute")),
        spreads=torch.as_tensor(cat("spreads")),
        density=torch.as_tensor(cat("density")),
        correct=torch.as_tensor(correct),
        utterance=torch.as_tensor((np.stack([c.utterance_features for c in cases]) - g_mean) / g_scale),
        log_uniform=torch.as_tensor(np.array([c.log_uniform for c in cases])),
        log_broad=torch.as_tensor(np.array([c.log_broad for c in cases])),
        built=torch.as_tensor(np.array([c.kind == "built" for c in cases])),
        n_cases=len(cases),
    )


def _segment_logsumexp(values: Any, segments: Any, n: int) -> Any:
    """log sum exp of `values` (R,) within each segment (R,) -> (n,); -inf for an empty segment."""
    import torch

    peak = (
        torch.full((n,), -math.inf, dtype=values.dtype).scatter_reduce(0, segments, values, "amax").detach()
    )
    safe = torch.where(torch.isfinite(peak), peak, torch.zeros_like(peak))
    total = torch.zeros(n, dtype=values.dtype).index_add(0, segments, torch.exp(values - safe[segments]))
    return torch.log(total) + safe


@dataclass
class _Parameters:
    weights: Any  # (K, F)
    background: Any  # (G,)
    spreads: Any  # (S,) raw: c = 1 + softplus(raw)


def _log_density(
    params: _Parameters, batch: _Batch, attribute_weight: float, temperature: float = 1.0
) -> tuple[Any, Any]:
    """(log p(y) per case (C,), log pi per row (R,))."""
    import torch
    import torch.nn.functional as F

    scores = (
        torch.sum(batch.features * params.weights[batch.keys], dim=1) + attribute_weight * batch.attribute
    ) / temperature
    log_pi = scores - _segment_logsumexp(scores, batch.row_case, batch.n_cases)[batch.row_case]
    floors = torch.tensor([MIN_SPREADS[s] for s in SPREADS], dtype=scores.dtype)
    c = torch.ones_like(scores)
    has = batch.spreads >= 0
    c = torch.where(has, (floors + F.softplus(params.spreads))[batch.spreads.clamp(min=0)], c)
    log_c = torch.log(c)
    d = batch.density
    core = d[:, 0] - 0.5 * (d[:, 2] + 3 * log_c + d[:, 3] / c + 3 * _LOG_2PI)
    tail = d[:, 1] - 0.5 * (d[:, 4] + 3 * log_c + d[:, 5] / c + 3 * _LOG_2PI)
    log_p = torch.logaddexp(core, tail)
    mixture = _segment_logsumexp(log_pi + log_p, batch.row_case, batch.n_cases)  # (C,)
    floor = MIN_BACKGROUND_WEIGHT
    beta = floor + (1.0 - floor) * torch.sigmoid(batch.utterance @ params.background)  # (C,)
    terms = torch.stack(
        [
            torch.log1p(-beta) + mixture,
            math.log(floor) + batch.log_uniform,
            torch.log(beta - floor) + batch.log_broad,
        ]
    )
    return torch.logsumexp(terms, dim=0), log_pi


def _loss(params: _Parameters, batch: _Batch, l2: float, gamma: float, attribute_weight: float) -> Any:
    import torch

    log_p, log_pi = _log_density(params, batch, attribute_weight)
    loss = -log_p.mean()
    if bool(batch.built.any()) and gamma > 0:
        masked = torch.where(batch.correct, log_pi, torch.full_like(log_pi, -math.inf))
        referent = _segment_logsumexp(masked, batch.row_case, batch.n_cases)  # (C,)
        usable = batch.built & torch.isfinite(referent)
        if bool(usable.any()):
            loss = loss - gamma * referent[usable].sum() / batch.n_cases
    return loss + 0.5 * l2 * (torch.sum(params.weights**2) + torch.sum(params.background[1:] ** 2))


def fit_parameters(
    batch: _Batch, l2: float, gamma: float, attribute_weight: float, max_iter: int = 300
) -> _Parameters:
    """L-BFGS on the objective of the module docstring, from zero weights and beta at its floor's side."""
    import torch

    n_keys, n_features = len(_KEYS), batch.features.shape[1]
    params = _Parameters(
        weights=torch.zeros(n_keys, n_features, dtype=torch.float64, requires_grad=True),
        background=torch.zeros(batch.utterance.shape[1], dtype=torch.float64, requires_grad=True),
        spreads=torch.zeros(len(SPREADS), dtype=torch.float64, requires_grad=True),
    )
    with torch.no_grad():
        params.background[0] = -2.0  # beta ~ 0.14 to start
    optimizer = torch.optim.LBFGS(
        [params.weights, params.background, params.spreads], max_iter=max_iter, line_search_fn="strong_wolfe"
    )

    def closure() -> Any:
        optimizer.zero_grad()
        loss = _loss(params, batch, l2, gamma, attribute_weight)
        loss.backward()
        return loss

    optimizer.step(closure)
    return params


def fit_temperature(params: _Parameters, batch: _Batch, attribute_weight: float) -> float:
    """The temperature T of the hypothesis scores minimising the held-out -log p(y) (golden section)."""
    import torch

    def loss(log_t: float) -> float:
        with torch.no_grad():
            return float(-_log_density(params, batch, attribute_weight, math.exp(log_t))[0].mean())

    return math.exp(golden_section(loss, math.log(0.25), math.log(4.0), iterations=40))


def case_referent(case: FitCase, weights: np.ndarray) -> ReferentScore:
    """A built case's readings, weighted, as `vlmap eval static` scores a proposal (`referent_score`)."""
    from app.evaluation.static import referent_score

    readings = [
        Hypothesis(anchors, Relation.NEAR, float(w)) for anchors, w in zip(case.anchors, weights, strict=True)
    ]
    correct = case.correct if case.correct is not None else np.zeros(len(case.anchors), dtype=bool)
    hits = [frozenset(a) for a, hit in zip(case.anchors, correct, strict=True) if hit]
    truth = hits[0] if hits else frozenset({"\0no true reading"})
    return referent_score("", readings, truth)


def summarise(
    params: _Parameters, batch: _Batch, cases: Sequence[FitCase], attribute_weight: float, temperature: float
) -> dict[str, Any]:
    """Held-out figures at the truth: mean -log p(y), the uniform's, the share better, per kind; and the
    built cases' referent figures as `vlmap eval static` has them (`summarize_referent`: the weights of the
    readings of one anchor set summed, region readings left out)."""
    import torch

    from app.evaluation.static import summarize_referent

    with torch.no_grad():
        log_p, log_pi = _log_density(params, batch, attribute_weight, temperature)
    nll = -log_p.numpy()
    uniform = -batch.log_uniform.numpy()
    out: dict[str, Any] = {}
    kinds = np.array([c.kind for c in cases])
    for kind in sorted(set(kinds)):
        mask = (kinds == kind) & np.isfinite(uniform)
        out[kind] = {
            "n": int(mask.sum()),
            "nll": float(nll[mask].mean()),
            "uniform_nll": float(uniform[mask].mean()),
            "better_than_uniform": float(np.mean(nll[mask] < uniform[mask])),
        }
    built = [i for i, c in enumerate(cases) if c.correct is not None]
    if built:
        pi = np.exp(log_pi.numpy())
        row_case = batch.row_case.numpy()
        scores = [case_referent(cases[i], pi[row_case == i]) for i in built]
        out["referent"] = summarize_referent(scores)
    return out


def to_params(
    params: _Parameters,
    template: ProposerParams,
    mean: np.ndarray,
    scale: np.ndarray,
    g_mean: np.ndarray,
    g_scale: np.ndarray,
    temperature: float,
    info: dict[str, Any],
) -> ProposerParams:
    import torch.nn.functional as F

    weights = params.weights.detach().numpy()
    return ProposerParams(
        weights={k: weights[i] for i, k in enumerate(_KEYS)},
        feature_mean=mean,
        feature_scale=scale,
        background=params.background.detach().numpy(),
        background_mean=g_mean,
        background_scale=g_scale,
        spreads={
            s: float(MIN_SPREADS[s] + F.softplus(params.spreads[i].detach())) for i, s in enumerate(SPREADS)
        },
        temperature=temperature,
        attribute_weight=template.attribute_weight,
        min_label_similarity=template.min_label_similarity,
        sibling_similarity=template.sibling_similarity,
        max_candidates=template.max_candidates,
        target_boxes=template.target_boxes,
        default_target_box=template.default_target_box,
        encoder_sha256=template.encoder_sha256,
        info=info,
    )


def standardisers(cases: Sequence[FitCase]) -> tuple[np.ndarray, ...]:
    """Means and scales of the hypothesis and the utterance features (scale 1 where constant; the
    background's intercept stays 1)."""
    rows = np.concatenate([c.features for c in cases])
    g = np.stack([c.utterance_features for c in cases])
    mean, scale = rows.mean(axis=0), rows.std(axis=0)
    # Below 1e-6 a feature is constant here; params.json keeps 6 decimals, so a smaller scale would load as 0.
    scale = np.where(scale >= 1e-6, scale, 1.0)
    g_mean, g_scale = g.mean(axis=0), g.std(axis=0)
    g_mean[0], g_scale[0] = 0.0, 1.0
    g_scale = np.where(g_scale >= 1e-6, g_scale, 1.0)
    return mean, scale, g_mean, g_scale


def held_out(case: GroundingCase, share: float) -> bool | None:
    """Whether a case is in the held-out part of the training scans (a fixed share by scan id); None for a
    house whose rooms fall on both sides, which belongs to neither part.

    A house is split by its rooms, not by its own id: the rooms' own cases and the human descriptions of
    those scans are split by scan id, so a house on one side by its id would carry the other side's scans.
    A straddling house is dropped rather than held out: held out, it would measure scans the fit has seen."""
    scenes = case.meta.get("scene_ids") or [case.meta.get("scene_id", case.case_id)]
    sides = {_scan_held_out(str(scene), share) for scene in scenes}
    return sides.pop() if len(sides) == 1 else None


def _scan_held_out(scene: str, share: float) -> bool:
    """Whether a scan is held out, by its room: rescans ("scene0010_00", "scene0010_01") share one side."""
    room = scene.rsplit("_", 1)[0] if scene.startswith("scene") else scene
    return zlib.crc32(room.encode()) / 2**32 < share


def target_box_table(cases: Iterable[GroundingCase], min_count: int = 3) -> dict[str, list[float]]:
    """Median target (dx, dy, dz, centre height above the floor) per lemmatised target label, for labels
    seen at least `min_count` times; the floor is the lowest object bottom of the case's scene."""
    boxes: dict[str, list[list[float]]] = {}
    for case in cases:
        if case.target.size is None or not case.scene_graph.objects:
            continue
        floor = min(float(o.min_corner[2]) for o in case.scene_graph.objects)
        boxes.setdefault(lemmas(case.target.label), []).append(
            [*case.target.size, case.target.position[2] - floor]
        )
    return {k: np.median(v, axis=0).round(4).tolist() for k, v in boxes.items() if len(v) >= min_count}


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cases(path: Path, every: int, originals_only: bool) -> list[GroundingCase]:
    """Every `every`-th case of a file, shifted copies of the case builder skipped (read as JSON first: a
    built train file holds a hundred thousand cases, most of them copies)."""
    out = []
    kept = 0
    with Path(path).open(encoding="utf-8") as fh:
        for line in fh:
            if not line.strip():
                continue
            raw = json.loads(line)
            if originals_only and raw.get("meta", {}).get("augmentation", 0):
                continue
            if kept % every == 0:
                out.append(GroundingCase.model_validate(raw))
            kept += 1
    return out


def fit_proposer(
    human: list[Path],
    built: list[Path],
    out: Path,
    model_dir: Path | None,
    *,
    built_every: int = 4,
    held_out_share: float = 0.2,
    gamma: float = 1.0,
    l2_grid: Sequence[float] = DEFAULT_L2_GRID,
    progress: bool = True,
) -> dict[str, Any]:
    """Prepare the cases, fit on the training part, choose lambda and T on the held-out part, write
    params.json and report.json into `out`; returns the report."""
    import torch
    from tqdm import tqdm

    from app.lsm.grounder import DEFAULT_MODEL_DIR, LSMGrounder
    from app.lsm.text_encoder import default_text_encoder

    torch.set_num_threads(1)
    started = time.perf_counter()
    encoder = default_text_encoder()
    grounder = LSMGrounder.load(model_dir or DEFAULT_MODEL_DIR, encoder=encoder)
    sources: list[tuple[str, GroundingCase]] = []
    for path in human:
        sources += [("human", c) for c in read_cases(path)]
    for path in built:
        sources += [("built", c) for c in _cases(path, built_every, originals_only=True)]
    template = ProposerParams.untrained(
        encoder_sha256=encoder.sha256,
        target_boxes=target_box_table(c for _, c in sources if held_out(c, held_out_share) is False),
    )
    proposer = BuiltinProposer(encoder, template)
    prepared: dict[str, list[FitCase]] = {"fit": [], "held_out": []}
    skipped = straddling = 0
    for kind, case in tqdm(sources, desc="cases", unit="case", disable=not progress):
        side = held_out(case, held_out_share)
        if side is None:
            straddling += 1
            continue
        fit_case = prepare_case(case, proposer, grounder, kind)
        if fit_case is None:
            skipped += 1
            continue
        prepared["held_out" if side else "fit"].append(fit_case)
    prepare_s = time.perf_counter() - started
    for part in ("fit", "held_out"):
        if not prepared[part]:
            counts = f"{len(prepared['fit'])} fit, {len(prepared['held_out'])} held out, {skipped} skipped"
            name = part.replace("_", "-")
            msg = (
                f"no usable case fell in the {name} part ({counts}, {straddling} straddling; --held-out "
                f"{held_out_share:g}): the held-out part chooses the penalty, so both parts need cases of "
                "several scans"
            )
            raise InvalidInput(msg, field="--held-out")
    mean, scale, g_mean, g_scale = standardisers(prepared["fit"])
    fit_batch = _batch(prepared["fit"], mean, scale, g_mean, g_scale)
    held_batch = _batch(prepared["held_out"], mean, scale, g_mean, g_scale)
    attribute_weight = template.attribute_weight
    trials = []
    for l2 in l2_grid:
        params = fit_parameters(fit_batch, l2, gamma, attribute_weight)
        with torch.no_grad():
            held = float(-_log_density(params, held_batch, attribute_weight)[0].mean())
        if not math.isfinite(held):
            # L-BFGS can step into a non-finite region under a strong penalty; such a fit is not a candidate.
            log.warning("lambda %g: the fit diverged (held-out -log p(y) %s); not a candidate", l2, held)
            held = math.inf
        trials.append((held, l2, params))
        log.info("lambda %g: held-out -log p(y) %.4f", l2, held)
    if not any(math.isfinite(t[0]) for t in trials):
        msg = f"every fit diverged (lambda grid {list(l2_grid)})"
        raise RuntimeError(msg)
    _, l2, params = min(trials, key=lambda t: t[0])
    temperature = fit_temperature(params, held_batch, attribute_weight)
    report = {
        "cases": {k: len(v) for k, v in prepared.items()},
        "cases_by_kind": {
            k: {kind: sum(c.kind == kind for c in v) for kind in ("human", "built")}
            for k, v in prepared.items()
        },
        "skipped": skipped,
        "straddling_houses": straddling,
        "l2": l2,
        "l2_trials": {str(t[1]): (t[0] if math.isfinite(t[0]) else None) for t in trials},
        "gamma": gamma,
        "temperature": temperature,
        "held_out": summarise(params, held_batch, prepared["held_out"], attribute_weight, temperature),
        "fit": summarise(params, fit_batch, prepared["fit"], attribute_weight, temperature),
        "seconds": {"prepare": round(prepare_s, 1), "total": round(time.perf_counter() - started, 1)},
    }
    info = {
        "fitted_on": {str(p): _sha256(p)[:16] for p in [*human, *built]},
        "built_every": built_every,
        "held_out_share": held_out_share,
        "lsm": grounder.describe()["checksum"],
        "report": report,
    }
    fitted = to_params(params, template, mean, scale, g_mean, g_scale, temperature, info)
    out.mkdir(parents=True, exist_ok=True)
    fitted.save(out / "params.json")
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return report


# --- vlmap fit-proposer ---


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "fit-proposer",
        help="fit the built-in proposer end to end on human descriptions and built cases",
        description="Fit the proposer's weights, the spreads of vague readings and the broad term's weight "
        "by the marginal likelihood of the true target positions (app.training.referents).",
    )
    parser.add_argument(
        "--human", type=Path, action="append", default=[], help="cases without anchors (JSONL)"
    )
    parser.add_argument(
        "--built", type=Path, action="append", default=[], help="cases with true anchors (JSONL)"
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for params.json and report.json")
    parser.add_argument("--model-dir", type=Path, default=None, help="the LSM (default models/lsm)")
    parser.add_argument(
        "--built-every", type=int, default=4, help="every Nth original built case (default 4)"
    )
    parser.add_argument("--held-out", type=float, default=0.2, help="share of training scans held out")
    parser.add_argument("--gamma", type=float, default=1.0, help="weight of the built cases' referent term")
    parser.add_argument("--no-progress", action="store_true")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not args.human and not args.built:
        msg = "give --human and/or --built case files"
        raise SystemExit(msg)
    try:
        report = fit_proposer(
            args.human,
            args.built,
            args.out,
            args.model_dir,
            built_every=args.built_every,
            held_out_share=args.held_out,
            gamma=args.gamma,
            progress=not args.no_progress,
        )
    except InvalidInput as exc:
        msg = f"vlmap fit-proposer: {exc}"
        raise SystemExit(msg) from exc
    print(json.dumps(report, indent=2))
    return 0


__all__ = ["FitCase", "fit_proposer", "prepare_case"]
