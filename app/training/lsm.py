"""Train the LSM on grounding cases; select and calibrate on held-out data of another distribution; report.

Splits (all grounding-case files; the true grounding of a case is `hypotheses[0]`, the label its
`target.position`):

- `train`: what the optimiser sees. A share `region_rate` of its cases also teaches a region hypothesis
  (the target in the room that holds it, or in the whole map: `make_sample` without anchors).
- `calib`: checkpoint selection (lowest NLL) and the post-hoc calibration. It should come from rooms never
  trained on and be built differently (the case builder's `calib` split: houses, any yaw, heavier noise);
  without it, `val_seen` plays that part.
- `val_seen`, `val_unseen` and any `reports` (e.g. the Sr3D dev set given its true hypotheses): reported,
  never used to choose anything.
- `exclude_sources` leaves sources (`meta.source`) out of train, calib and val_seen: the leave-one-source-out
  runs (train without AI2-THOR, score AI2-THOR in val_unseen, and the reverse). Reports are broken down by
  source.

Calibration: one covariance scale c_k per relation (and one for region hypotheses), Sigma <- c_k Sigma for
the core and the tail alike, each the NLL-minimising scale on calib (`calibration_fit: nll`) or the one
that makes its moment-matched ANEES 3 (`nees`), shrunk towards the pooled one in log space as if
`calibration_prior_cases` more cases had the pooled value, then times a margin (`fit_calibration`). For a
single Gaussian the two fits agree: the NLL-optimal scale is exactly ANEES / 3.

Metrics are those of the served density p(y | h) = (1 - a) N(mu, Sigma) + a N(mu, Sigma + Delta): NLL of
the density, ANEES of its moment-matched covariance Sigma + a Delta, HDR coverage of the density (Monte
Carlo), RMSE of mu; beside them the NLL of a uniform density over the case's map box (the no-language
baseline of `vlmap eval static`).

Outputs in `--out`: `model.safetensors` + `config.json` (the shippable checkpoint, calibration included),
`metrics.json` / `metrics.md`, `history.jsonl` (one line per validation) and `embeddings.npz`.
"""

from __future__ import annotations

import json
import logging
import math
import random
import time
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from app.data.cases import GroundingCase, case_room, read_cases
from app.evaluation.metrics import clustered_interval, gaussian_nll, nees, no_language_nll
from app.grounding.box_relations import internal_support_reach
from app.grounding.hypotheses import Hypothesis
from app.grounding.interfaces import Grounder
from app.grounding.parsing import target_noun
from app.grounding.relations import Relation
from app.lsm.features import EmbeddingCache, PackedSamples, Sample, make_sample, to_world
from app.lsm.grounder import REGION_KEY, calibrated_tail_weight, calibration_scale
from app.lsm.model import LanguageSensorModel, LSMConfig, load_checkpoint, save_checkpoint
from app.lsm.text_encoder import MINILM_SHA256, TextEncoder
from app.training.search import golden_section

log = logging.getLogger(__name__)
MASSES = (0.5, 0.9, 0.95)
_HDR_DRAWS = 1000


@dataclass
class DataConfig:
    train: str
    val_seen: str | None = None
    val_unseen: str | None = None
    calib: str | None = None  # selection and calibration; val_seen when None
    reports: dict[str, str] = field(default_factory=dict)  # more report-only case files, by name
    exclude_sources: list[str] = field(default_factory=list)  # left out of train, calib and val_seen
    region_rate: float = 0.25  # share of cases that also give a region sample
    # Train "on" targets resting on a plain top (`resting_position`). Off in every shipped model: until
    # the option reached the train split it had no effect, whatever a training record says.
    resting_on: bool = False
    max_train_cases: int | None = None  # first N usable cases of the train file (for quick runs)
    embedding_cache: str | None = None  # .npz; default <out>/embeddings.npz


@dataclass
class OptimConfig:
    epochs: int = 20
    batch_size: int = 64
    lr: float = 3e-4
    weight_decay: float = 0.01
    warmup_steps: int = 200
    min_lr_ratio: float = 0.1  # cosine decay to lr * min_lr_ratio
    prior_lr_scale: float = 10.0  # the per-relation linear prior (a linear map) learns this much faster
    grad_clip: float = 1.0
    eval_every_steps: int = 500  # and at the end of every epoch
    eval_batch_size: int = 256
    seed: int = 0
    threads: int = 2  # this machine has 2 cores


@dataclass
class TrainConfig:
    data: DataConfig
    model: LSMConfig = field(default_factory=LSMConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    version: str = "dev"
    calibration_prior_cases: float = 50.0  # see fit_calibration
    calibration_margin: float = 1.0  # every fitted scale times this (see fit_calibration) ...
    calibration_margins: dict[str, float] = field(default_factory=dict)  # ... or this, per relation
    calibration_tail_floor: float = 0.0  # every tail weight a -> a + (1 - a) eps (see fit_calibration)
    calibration_fit: str = "nll"  # each scale NLL-optimal or NEES-consistent ("nees"), see fit_calibration

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        unknown = sorted(set(values) - {f.name for f in fields(cls)})
        if unknown or "data" not in values:
            msg = (
                f"training config: unknown sections {unknown}"
                if unknown
                else "training config needs a data section"
            )
            raise ValueError(msg)
        data = DataConfig(**values["data"])
        fit = str(values.get("calibration_fit", "nll"))
        if fit not in CALIBRATION_FITS:
            msg = f"training config: calibration_fit must be one of {CALIBRATION_FITS}, not {fit!r}"
            raise ValueError(msg)
        if data.calib is None and data.val_seen is None:
            msg = "training config: data needs calib (or val_seen) for checkpoint selection and calibration"
            raise ValueError(msg)
        return cls(
            data=data,
            model=LSMConfig.from_dict(values.get("model", {})),
            optim=OptimConfig(**values.get("optim", {})),
            version=str(values.get("version", "dev")),
            calibration_prior_cases=float(values.get("calibration_prior_cases", 50.0)),
            calibration_margin=float(values.get("calibration_margin", 1.0)),
            calibration_margins={k: float(v) for k, v in (values.get("calibration_margins") or {}).items()},
            calibration_tail_floor=float(values.get("calibration_tail_floor", 0.0)),
            calibration_fit=fit,
        )

    @classmethod
    def from_yaml(cls, path: Path) -> TrainConfig:
        import yaml

        return cls.from_dict(yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {})


@dataclass
class Split:
    """Featurised cases of one file: samples with their group (relation, or "region") and source."""

    name: str
    samples: list[Sample]
    groups: list[str]
    sources: list[str]
    cases: list[GroundingCase]  # the case of each object sample (for the baselines), when kept
    skipped: int
    map_log_volumes: (
        np.ndarray
    )  # (S,) the uniform baseline's NLL (`no_language_nll`; inf outside the map box)
    rooms: list[str]  # each sample's room (`case_room`): the unit the ANEES interval resamples
    conventions: list[str]  # each sample's relation convention (`meta.convention`; "" when not said)

    @property
    def targets(self) -> np.ndarray:
        """(S, 3) world positions."""
        return np.stack([s.to_world(s.target, np.eye(3))[0] for s in self.samples if s.target is not None])


def target_region(case: GroundingCase) -> str | None:
    """The target's region: the case's own word for it (`meta.target_region_id`, which the builder writes),
    else the smallest region whose box holds the target, or None (the map). The boxes of turned rooms are
    axis-aligned and overlap near shared walls, so the box alone can name the neighbour."""
    said = case.meta.get("target_region_id")
    if said is not None and any(r.id == str(said) for r in case.scene_graph.regions):
        return str(said)
    y = np.asarray(case.target.position, dtype=np.float64)
    holding = [
        (float(np.prod(r.size)), r.id)
        for r in case.scene_graph.regions
        if np.all(np.abs(y - np.asarray(r.center)) <= 0.5 * np.asarray(r.size))
    ]
    return min(holding)[1] if holding else None


def resting_position(case: GroundingCase) -> list[float]:
    """The training label of an "on" case on a plain top (not a seat or a shelf, which hold things inside
    their box): the target rests on the anchor, centre z >= top + half its height. Scanned boxes of things on
    furniture often start inside it (a keyboard's box 5 cm into the desk), which taught "on" to sit at the
    top surface rather than on it; every other label is the case's own."""
    position = list(case.target.position)
    truth = case.hypotheses[0] if case.hypotheses else None
    if (
        truth is None
        or truth.relation is not Relation.ON
        or len(truth.anchor_ids) != 1
        or case.target.size is None
    ):
        return position
    anchor = case.scene_graph.object(truth.anchor_ids[0])
    if internal_support_reach(anchor.label) > 0:
        return position
    resting = float(anchor.max_corner[2]) + 0.5 * float(case.target.size[2])
    position[2] = max(position[2], resting)
    return position


def _takes_region(case_id: str, rate: float) -> bool:
    """Whether a case also gives a region sample: a fixed pseudo-random share `rate` of the case ids."""
    return rate > 0 and zlib.crc32(case_id.encode()) / 2**32 < rate


def load_split(
    name: str,
    path: str,
    cfg: LSMConfig,
    limit: int | None = None,
    keep_cases: bool = False,
    exclude_sources: tuple[str, ...] = (),
    region_rate: float = 0.0,
    resting_on: bool = False,
) -> Split:
    """Cases with a ground-truth hypothesis whose anchors exist -> samples; the others count as skipped.

    The text of each sample is made (`make_sample`, `cfg.text_input`) from the target's name as the
    utterance says it; with `resting_on`, "on" labels rest on plain tops (`resting_position`).
    """
    samples: list[Sample] = []
    groups: list[str] = []
    sources: list[str] = []
    cases: list[GroundingCase] = []
    volumes: list[float] = []
    rooms: list[str] = []
    conventions: list[str] = []
    skipped = taken = 0
    for case in read_cases(path):
        if limit is not None and taken >= limit:  # cases, not samples: a case may also give a region sample
            break
        source = str(case.meta.get("source", "unknown"))
        truth = case.hypotheses[0] if case.hypotheses else None
        known = {o.id for o in case.scene_graph.objects}
        if source in exclude_sources or truth is None or not set(truth.anchor_ids) <= known:
            skipped += 1
            continue
        regions = tuple(r.name.lower() for r in case.scene_graph.regions if r.name)
        target = target_noun(case.utterance, regions) or case.target.label
        position = resting_position(case) if resting_on else case.target.position
        volume = no_language_nll(case.scene_graph, np.asarray(position, dtype=np.float64))
        samples.append(make_sample(case.scene_graph, truth.anchor_ids, truth.relation, target, cfg, position))
        taken += 1
        groups.append(truth.relation.value)
        sources.append(source)
        volumes.append(volume)
        rooms.append(case_room(case))
        conventions.append(str(case.meta.get("convention", "")))
        if keep_cases:
            cases.append(case)
        if _takes_region(case.case_id, region_rate):
            region = target_region(case)
            samples.append(make_sample(case.scene_graph, (), Relation.IN, target, cfg, position, region))
            groups.append(REGION_KEY)
            sources.append(source)
            volumes.append(volume)
            rooms.append(rooms[-1])
            conventions.append(conventions[-1])
    if not samples:
        msg = (
            f"{path}: no usable grounding cases (need hypotheses[0] with anchors present in the scene graph)"
        )
        raise ValueError(msg)
    return Split(name, samples, groups, sources, cases, skipped, np.asarray(volumes), rooms, conventions)


# --- predictions and their scores --------------------------------------------------------------------------


@dataclass(frozen=True)
class Densities:
    """Per sample p(y | h) = (1 - a) N(mu, Sigma) + a N(mu, Sigma_tail), world frame; a = 0 without a tail."""

    means: np.ndarray  # (S, 3)
    core: np.ndarray  # (S, 3, 3)
    tail: np.ndarray  # (S, 3, 3)
    weights: np.ndarray  # (S,) a

    def scaled(self, scales: np.ndarray) -> Densities:
        """Every covariance of sample i times scales[i]."""
        c = np.asarray(scales, dtype=np.float64)[:, None, None]
        return Densities(self.means, self.core * c, self.tail * c, self.weights)

    def take(self, index: np.ndarray) -> Densities:
        return Densities(self.means[index], self.core[index], self.tail[index], self.weights[index])

    def with_tail_floor(self, calibration: dict[str, Any]) -> Densities:
        """The tail weights raised as the calibration says (`calibrated_tail_weight`)."""
        weights = np.asarray(calibrated_tail_weight(calibration, self.weights), dtype=np.float64)
        return Densities(self.means, self.core, self.tail, weights)

    @property
    def moment_covariances(self) -> np.ndarray:
        """(1 - a) Sigma + a Sigma_tail, (S, 3, 3)."""
        a = self.weights[:, None, None]
        covariances: np.ndarray = (1.0 - a) * self.core + a * self.tail
        return covariances

    def nll(self, targets: np.ndarray) -> np.ndarray:
        """-log p(y_i | h_i), (S,)."""
        core = -gaussian_nll(self.means, self.core, targets)
        tail = -gaussian_nll(self.means, self.tail, targets)
        with np.errstate(divide="ignore"):
            terms = np.stack([np.log1p(-self.weights) + core, np.log(self.weights) + tail])  # (2, S)
        peak = terms.max(axis=0)
        nll: np.ndarray = -(peak + np.log(np.exp(terms - peak).sum(axis=0)))
        return nll

    def coverage(self, targets: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Whether y_i lies in the density's HDR of each mass in `MASSES`, (S, M), by `_HDR_DRAWS` draws."""
        out = np.empty((len(self.means), len(MASSES)), dtype=bool)
        levels = 1.0 - np.asarray(MASSES)
        for start in range(0, len(self.means), 256):
            part = self.take(np.arange(start, min(start + 256, len(self.means))))
            n = len(part.means)
            normal = rng.standard_normal((n, _HDR_DRAWS, 3))
            in_tail = rng.uniform(size=(n, _HDR_DRAWS)) < part.weights[:, None]
            chol = np.where(
                in_tail[..., None, None],
                np.linalg.cholesky(part.tail)[:, None],
                np.linalg.cholesky(part.core)[:, None],
            )
            draws = part.means[:, None] + np.einsum("sdij,sdj->sdi", chol, normal)  # (n, D, 3)
            log_p = -part._nll_many(draws)  # (n, D)
            thresholds = np.quantile(log_p, levels, axis=1).T  # (n, M)
            log_y = -part.nll(targets[start : start + n])  # (n,)
            out[start : start + n] = log_y[:, None] >= thresholds
        return out

    def _nll_many(self, points: np.ndarray) -> np.ndarray:
        """-log p(x) of points (S, D, 3), one density per row, (S, D)."""
        s, d, _ = points.shape
        repeat = np.repeat(np.arange(s), d)
        flat = self.take(repeat)
        return flat.nll(points.reshape(-1, 3)).reshape(s, d)


def predict(
    model: LanguageSensorModel, packed: PackedSamples, samples: list[Sample], batch_size: int
) -> Densities:
    """Uncalibrated densities of every sample, in the world frame."""
    model.eval()
    means, core, tail, weights = [], [], [], []
    with torch.inference_mode():
        for start in range(0, len(packed), batch_size):
            out = model(packed.batch(slice(start, start + batch_size)))
            means.append(out.mean.double().numpy())
            core.append(out.covariance.double().numpy())
            tail_cov = out.tail_covariance
            tail.append((tail_cov if tail_cov is not None else out.covariance).double().numpy())
            a = out.tail_weight
            weights.append(np.zeros(len(out.mean)) if a is None else a.double().numpy())
    local = Densities(
        np.concatenate(means), np.concatenate(core), np.concatenate(tail), np.concatenate(weights)
    )
    world_means, world = to_world(samples, local.means, np.stack([local.core, local.tail], axis=1))
    return Densities(world_means, world[:, 0], world[:, 1], local.weights)


def density_summary(
    densities: Densities,
    targets: np.ndarray,
    map_log_volumes: np.ndarray,
    rng: np.random.Generator | None,
    rooms: np.ndarray | None = None,
) -> dict[str, Any]:
    """n, RMSE, NLL (mean, median), the uniform baseline and the share better than it, ANEES (moment
    matched; mean, median; with `rooms` its 90% interval over them, `clustered_interval`), and with `rng`
    the HDR coverage of each mass."""
    errors = np.linalg.norm(densities.means - targets, axis=1)
    nll = densities.nll(targets)
    per_case = nees(densities.means, densities.moment_covariances, targets)
    # As `vlmap eval static` has them: the baseline's mean over the targets inside the map box, and a target
    # outside it (no density there) counted as better.
    inside = np.isfinite(map_log_volumes)
    out: dict[str, Any] = {
        "n": len(errors),
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "nll_mean": float(np.mean(nll)),
        "nll_median": float(np.median(nll)),
        "uniform_nll": float(np.mean(map_log_volumes[inside])) if inside.any() else None,
        "uniform_outside": int(np.sum(~inside)),
        "better_than_uniform": float(np.mean(nll < map_log_volumes)),
        "anees": float(np.mean(per_case)),
        "nees_median": float(np.median(per_case)),
        "tail_weight_mean": float(np.mean(densities.weights)),
    }
    if rooms is not None:
        interval = clustered_interval(per_case, rooms)
        out["anees_ci90"] = None if interval is None else list(interval)
    if rng is not None:
        covered = densities.coverage(targets, rng)
        out["coverage"] = {str(m): float(np.mean(covered[:, j])) for j, m in enumerate(MASSES)}
    return out


def summarize(
    densities: Densities, split: Split, rng: np.random.Generator | None, index: np.ndarray | None = None
) -> dict[str, Any]:
    """Object hypotheses overall, then per group (relations and "region"), per source, per source and group
    (a source never trained on, relation by relation), and per relation convention and group where the
    cases say which convention made them (a model that cannot tell the conventions apart is calibrated on
    their mix, not on each)."""
    groups, sources = np.asarray(split.groups), np.asarray(split.sources)
    targets, volumes, rooms = split.targets, split.map_log_volumes, np.asarray(split.rooms)
    conventions = np.asarray(split.conventions)
    if index is not None:
        groups, sources, targets = groups[index], sources[index], targets[index]
        volumes, rooms, conventions = volumes[index], rooms[index], conventions[index]

    def part(mask: np.ndarray) -> dict[str, Any]:
        return density_summary(densities.take(mask), targets[mask], volumes[mask], rng, rooms[mask])

    objects = groups != REGION_KEY
    return {
        "overall": part(objects) if objects.any() else {"n": 0},
        "per_relation": {g: part(groups == g) for g in sorted(set(groups.tolist()))},
        "per_source": {
            s: part(objects & (sources == s))
            for s in sorted(set(sources.tolist()))
            if (objects & (sources == s)).any()
        },
        "per_source_group": {
            f"{s} {g}": part((sources == s) & (groups == g))
            for s in sorted(set(sources.tolist()))
            for g in sorted(set(groups[sources == s].tolist()))
        },
        "per_convention": {
            f"{c} {g}": part((conventions == c) & (groups == g))
            for c in sorted(set(conventions.tolist()) - {""})
            for g in sorted(set(groups[conventions == c].tolist()) - {REGION_KEY})
        },
    }


def fit_calibration(
    densities: Densities,
    targets: np.ndarray,
    groups: list[str],
    prior_cases: float = 50.0,
    margin: float = 1.0,
    margins: dict[str, float] | None = None,
    tail_floor: float = 0.0,
    fit: str = "nll",
) -> dict[str, Any]:
    """Covariance scales c_k per group k: the scale c^_k of every covariance of the group's densities that
    `fit` asks for, shrunk towards the pooled one, log c_k = (n_k log c^_k + K log c^) / (n_k + K), K =
    `prior_cases`, so that a group with few calibration cases does not get a noisy scale; then times
    `margins[k]` (default `margin`), for data further from training than the calibration split. With
    `tail_floor` eps every tail weight is first raised to a + (1 - a) eps (`calibrated_tail_weight`) and the
    scales fitted to those densities. The model card says how the margins and eps were chosen.

    `fit` "nll": c^ minimises the NLL of the densities. "nees": c^ = ANEES / 3 of their moment-matched
    covariances, so that the scaled densities' ANEES is 3 (NEES consistency); the two agree for Gaussians,
    not for a mixture with a tail, whose NLL-optimal scale leaves the moment-matched ANEES wherever the tail
    puts it, relation by relation."""
    if fit not in CALIBRATION_FITS:
        msg = f"calibration fit must be one of {CALIBRATION_FITS}, not {fit!r}"
        raise ValueError(msg)
    criterion, fitted_scale = _SCALE_FITS[fit]
    margins = margins or {}
    densities = densities.with_tail_floor({"tail_floor": tail_floor})
    names = np.asarray(groups)
    pooled = fitted_scale(densities, targets)
    per_group, counts = {}, {}
    for g in sorted(set(groups)):
        mask = names == g
        own = fitted_scale(densities.take(mask), targets[mask])
        n = int(mask.sum())
        counts[g] = n
        shrunk = math.exp((n * math.log(own) + prior_cases * math.log(pooled)) / (n + prior_cases))
        per_group[g] = float(margins.get(g, margin) * shrunk)
    return {
        "method": f"covariance scale per relation (and for region hypotheses): the {criterion} scale on the "
        "calibration split, shrunk to the pooled one in log space, times the margin; tail weights raised to "
        "a + (1 - a) tail_floor",
        "fit": fit,
        "prior_cases": prior_cases,
        "tail_floor": tail_floor,
        "margin": margin,
        "margins": margins,
        "overall": margin * pooled,
        "per_relation": per_group,
        "cases": counts,
    }


def _nees_consistent_scale(densities: Densities, targets: np.ndarray) -> float:
    """ANEES / 3 of the moment-matched covariances: the scale whose scaled densities have ANEES 3."""
    return float(np.mean(nees(densities.means, densities.moment_covariances, targets))) / 3.0


def _nll_optimal_scale(densities: Densities, targets: np.ndarray) -> float:
    """argmin_c sum_i -log p_i(y_i) with every covariance times c (golden-section search on log c)."""
    core_m = nees(densities.means, densities.core, targets)
    tail_m = nees(densities.means, densities.tail, targets)
    core_det = np.linalg.slogdet(densities.core)[1]
    tail_det = np.linalg.slogdet(densities.tail)[1]
    log_w = np.log1p(-densities.weights)
    with np.errstate(divide="ignore"):
        log_a = np.log(densities.weights)

    def total(log_c: float) -> float:
        c = math.exp(log_c)
        core = log_w - 0.5 * (core_det + 3 * log_c + core_m / c)
        tail = log_a - 0.5 * (tail_det + 3 * log_c + tail_m / c)
        peak = np.maximum(core, tail)
        return float(-np.sum(peak + np.log(np.exp(core - peak) + np.exp(tail - peak))))

    return math.exp(golden_section(total, -4.0, 4.0))


# fit -> (its name in the calibration record, the scale it fits to a group's densities)
_SCALE_FITS: dict[str, tuple[str, Callable[[Densities, np.ndarray], float]]] = {
    "nll": ("NLL-optimal", _nll_optimal_scale),
    "nees": ("NEES-consistent (ANEES / 3)", _nees_consistent_scale),
}
CALIBRATION_FITS = tuple(_SCALE_FITS)  # what `calibration_fit` may name


def apply_calibration(densities: Densities, groups: list[str], calibration: dict[str, Any]) -> Densities:
    """What the grounder serves: the tail floor, then each group's covariance scale."""
    floored = densities.with_tail_floor(calibration)
    return floored.scaled(np.array([calibration_scale(calibration, g) for g in groups]))


def ground_cases(grounder: Grounder, cases: list[GroundingCase]) -> Densities:
    """Any grounder's density for each case's ground-truth hypothesis (moment-matched into one Gaussian)."""
    means, covs = [], []
    for case in cases:
        if not case.hypotheses:
            msg = f"case {case.case_id} has no ground-truth hypothesis"
            raise ValueError(msg)
        truth = case.hypotheses[0]
        hypothesis = Hypothesis(anchor_ids=tuple(truth.anchor_ids), relation=truth.relation)
        density = grounder.ground(case.scene_graph, case.utterance, [hypothesis])[0]
        means.append(density.mean())
        covs.append(density.covariance())
    core = np.asarray(covs, dtype=np.float64)
    return Densities(np.asarray(means, dtype=np.float64), core, core, np.zeros(len(core)))


def baseline_grounders() -> dict[str, Grounder]:
    """The hand-written baselines of `app.grounding.geometric`."""
    from app.grounding.geometric import FixedGrounder, GeometricGrounder

    return {"geometric": GeometricGrounder(), "fixed_0.1m": FixedGrounder()}


# --- the training loop --------------------------------------------------------------------------------------


def lr_at(step: int, total_steps: int, cfg: OptimConfig) -> float:
    """Linear warmup, then cosine decay from lr to lr * min_lr_ratio."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    progress = min((step - cfg.warmup_steps) / max(total_steps - cfg.warmup_steps, 1), 1.0)
    return cfg.lr * (cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def _optimizer(model: LanguageSensorModel, opt: OptimConfig) -> torch.optim.Optimizer:
    """AdamW; no weight decay on biases, norms and embeddings; the relation prior at prior_lr_scale x lr."""
    groups: dict[str, list[torch.nn.Parameter]] = {"decay": [], "no_decay": [], "prior": []}
    for name, param in model.named_parameters():
        if name.startswith("relation_prior."):
            groups["prior"].append(param)
        elif param.dim() >= 2 and "emb" not in name:
            groups["decay"].append(param)
        else:
            groups["no_decay"].append(param)
    settings = {
        "decay": (opt.weight_decay, 1.0),
        "no_decay": (0.0, 1.0),
        "prior": (0.0, opt.prior_lr_scale),
    }
    return torch.optim.AdamW(
        [
            {"params": params, "weight_decay": settings[k][0], "lr_scale": settings[k][1]}
            for k, params in groups.items()
            if params
        ],
        lr=opt.lr,
    )


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(config: TrainConfig, out_dir: Path) -> dict[str, Any]:
    """Train, keep the checkpoint of lowest calib NLL, calibrate it on calib, write it and its report."""
    from tqdm import tqdm

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    opt = config.optim
    seed_everything(opt.seed)
    torch.set_num_threads(opt.threads)
    write_config(config, out_dir)
    (out_dir / "history.jsonl").write_text("", encoding="utf-8")  # this run's validations only

    t0 = time.perf_counter()
    splits = _load_splits(config)
    cache = _embedding_cache(config, out_dir)
    packed = {name: PackedSamples(split.samples, cache) for name, split in splits.items()}
    cache.save()
    prep_s = time.perf_counter() - t0
    log.info("data: %s (prepared in %.0f s)", {n: len(s.samples) for n, s in splits.items()}, prep_s)

    model = LanguageSensorModel(config.model)
    optimizer = _optimizer(model, opt)
    train_set = packed["train"]
    steps_per_epoch = math.ceil(len(train_set) / opt.batch_size)
    total_steps = steps_per_epoch * opt.epochs
    generator = torch.Generator().manual_seed(opt.seed)
    best: dict[str, Any] = {"nll": math.inf, "step": -1}
    best_state: dict[str, torch.Tensor] = {}
    train_s, seen, step = 0.0, 0, 0
    bar = tqdm(total=total_steps, desc="train", unit="step", dynamic_ncols=True)
    for epoch in range(opt.epochs):
        order = torch.randperm(len(train_set), generator=generator)
        for start in range(0, len(train_set), opt.batch_size):
            tick = time.perf_counter()
            model.train()
            for group in optimizer.param_groups:
                group["lr"] = group["lr_scale"] * lr_at(step, total_steps, opt)
            batch = train_set.batch(order[start : start + opt.batch_size])
            assert batch.target is not None  # load_split gives every sample a target
            loss = model.loss(model(batch), batch.target)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), opt.grad_clip)
            optimizer.step()
            train_s += time.perf_counter() - tick
            seen += len(batch.relation)
            step += 1
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.3f}", samples_s=f"{seen / train_s:.0f}", epoch=epoch)
            if step % opt.eval_every_steps == 0 or start + opt.batch_size >= len(train_set):
                record = _validate(model, packed, splits, opt.eval_batch_size)
                record.update(step=step, epoch=epoch, train_loss=loss.item(), samples_per_s=seen / train_s)
                with (out_dir / "history.jsonl").open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps(record) + "\n")
                bar.write(_format_record(record))
                if record["calib"]["nll_all"] < best["nll"]:
                    best = {"nll": record["calib"]["nll_all"], "step": step, "epoch": epoch}
                    best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    bar.close()
    model.load_state_dict(best_state)

    calibration = _calibrate(model, packed["calib"], splits["calib"], config)
    training = {
        "data": {n: {"samples": len(s.samples), "skipped_cases": s.skipped} for n, s in splits.items()},
        "files": asdict(config.data),
        "optim": asdict(opt),
        "steps": step,
        "best": best,
        "train_seconds": round(train_s, 1),
        "prepare_seconds": round(prep_s, 1),
        "train_samples_per_second": round(seen / train_s, 1),
        "torch_threads": torch.get_num_threads(),
        "parameters": sum(p.numel() for p in model.parameters()),
    }
    save_checkpoint(
        model,
        out_dir,
        extra={
            "version": config.version,
            "calibration": calibration,
            "text_encoder": {"name": "sentence-transformers/all-MiniLM-L6-v2", "sha256": MINILM_SHA256},
            "training": training,
        },
    )
    report = evaluate_checkpoint(out_dir, config, splits=splits, packed=packed)
    report["training"] = training
    write_report(report, out_dir)
    return report


def _calibrate(
    model: LanguageSensorModel, packed: PackedSamples, calib: Split, config: TrainConfig
) -> dict[str, Any]:
    """The calibration of `model` fitted on the `calib` split as the config says (`fit_calibration`)."""
    return fit_calibration(
        predict(model, packed, calib.samples, config.optim.eval_batch_size),
        calib.targets,
        calib.groups,
        config.calibration_prior_cases,
        config.calibration_margin,
        config.calibration_margins,
        config.calibration_tail_floor,
        config.calibration_fit,
    )


def recalibrate(model_dir: Path, config: TrainConfig, out_dir: Path) -> dict[str, Any]:
    """The checkpoint in `model_dir` with its calibration fitted anew on the config's calib split (its
    margin and prior), written to `out_dir` with its report and the config: what a change of the calibration
    costs without training again."""
    model, meta = load_checkpoint(Path(model_dir))
    config = with_checkpoint_model(config, model.cfg)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    write_config(config, Path(out_dir))
    splits = _load_splits(config, include_train=False)
    cache = _embedding_cache(config, Path(out_dir))
    packed = {name: PackedSamples(split.samples, cache) for name, split in splits.items()}
    cache.save()
    calibration = _calibrate(model, packed["calib"], splits["calib"], config)
    extra = {k: v for k, v in meta.items() if k != "model"} | {
        "calibration": calibration,
        "version": config.version,
    }
    save_checkpoint(model, Path(out_dir), extra=extra)
    report = evaluate_checkpoint(Path(out_dir), config, splits=splits, packed=packed)
    report["training"] = meta.get("training")
    write_report(report, Path(out_dir))
    return report


def with_checkpoint_model(config: TrainConfig, cfg: LSMConfig) -> TrainConfig:
    """`config` with the checkpoint's model configuration: its weights read features made as that one says
    (the text input, the objects kept, the region margins), whatever the given config's model section
    holds; a difference is logged."""
    given, own = asdict(config.model), asdict(cfg)
    if given != own:
        differing = sorted(k for k, v in own.items() if given.get(k) != v)
        log.warning("model section unlike the checkpoint's in %s: the checkpoint's is used", differing)
    return replace(config, model=cfg)


def evaluate_checkpoint(
    model_dir: Path,
    config: TrainConfig,
    splits: dict[str, Split] | None = None,
    packed: dict[str, PackedSamples] | None = None,
    cache_dir: Path | None = None,
) -> dict[str, Any]:
    """The saved checkpoint (calibrated and raw) and the baselines on every split but train.

    Without `splits`/`packed` the config's files are read, with text embeddings cached in
    `config.data.embedding_cache` or else `cache_dir`/embeddings.npz.
    """
    model, meta = load_checkpoint(Path(model_dir))
    if splits is None or packed is None:
        config = with_checkpoint_model(config, model.cfg)
        splits = _load_splits(config, include_train=False)
        cache = _embedding_cache(config, Path(cache_dir) if cache_dir is not None else None)
        packed = {name: PackedSamples(split.samples, cache) for name, split in splits.items()}
        cache.save()
    baselines = baseline_grounders()
    report: dict[str, Any] = {
        "version": meta.get("version"),
        "calibration": meta.get("calibration"),
        "splits": {},
    }
    for name, split in splits.items():
        if name == "train":
            continue
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        raw = predict(model, packed[name], split.samples, config.optim.eval_batch_size)
        calibrated = apply_calibration(raw, split.groups, meta.get("calibration", {}))
        methods = {
            "lsm": summarize(calibrated, split, rng),
            "lsm_uncalibrated": summarize(raw, split, None),
        }
        objects = np.flatnonzero(np.asarray(split.groups) != REGION_KEY)
        for label, grounder in baselines.items():
            methods[label] = summarize(ground_cases(grounder, split.cases), split, None, objects)
        report["splits"][name] = methods
    return report


def _load_splits(config: TrainConfig, include_train: bool = True) -> dict[str, Split]:
    data, cfg = config.data, config.model
    excluded = tuple(data.exclude_sources)
    splits = {}
    if include_train:
        splits["train"] = load_split(
            "train",
            data.train,
            cfg,
            data.max_train_cases,
            exclude_sources=excluded,
            region_rate=data.region_rate,
            resting_on=data.resting_on,  # the train split only: every evaluation scores the cases' own labels
        )
    calib = data.calib or data.val_seen
    assert calib is not None  # TrainConfig.from_dict checks it
    splits["calib"] = load_split(
        "calib", calib, cfg, keep_cases=True, exclude_sources=excluded, region_rate=data.region_rate
    )
    if data.val_seen and data.calib:
        splits["val_seen"] = load_split(
            "val_seen",
            data.val_seen,
            cfg,
            keep_cases=True,
            exclude_sources=excluded,
            region_rate=data.region_rate,
        )
    if data.val_unseen:
        splits["val_unseen"] = load_split(
            "val_unseen", data.val_unseen, cfg, keep_cases=True, region_rate=data.region_rate
        )
    for name, path in data.reports.items():
        splits[name] = load_split(name, path, cfg, keep_cases=True)
    return splits


def _embedding_cache(config: TrainConfig, out_dir: Path | None) -> EmbeddingCache:
    path = Path(config.data.embedding_cache) if config.data.embedding_cache else None
    if path is None and out_dir is not None:
        path = out_dir / "embeddings.npz"
    # float32 always: these embeddings are what the model is trained on (and they are cached to disk).
    return EmbeddingCache(path, MINILM_SHA256, lambda: TextEncoder(precision="float32").encode)


def _validate(
    model: LanguageSensorModel, packed: dict[str, PackedSamples], splits: dict[str, Split], batch_size: int
) -> dict[str, Any]:
    """calib's NLL over every sample (`nll_all`, what selects the checkpoint) and each report split's
    summary of its object hypotheses."""
    record: dict[str, Any] = {}
    for name, split in splits.items():
        if name == "train":
            continue
        densities = predict(model, packed[name], split.samples, batch_size)
        summary = summarize(densities, split, None)
        record[name] = summary["overall"] | {
            "anees_per_relation": {r: v["anees"] for r, v in summary["per_relation"].items()},
            "nll_all": float(np.mean(densities.nll(split.targets))),
        }
    return record


def _format_record(record: dict[str, Any]) -> str:
    parts = [f"step {record['step']} epoch {record['epoch']} loss {record['train_loss']:.3f}"]
    for name, r in record.items():
        if isinstance(r, dict) and "rmse" in r:
            parts.append(f"{name}: rmse {r['rmse']:.3f} nll {r['nll_mean']:.3f} anees {r['anees']:.2f}")
    return " | ".join(parts)


def write_config(config: TrainConfig, out_dir: Path) -> None:
    """`train_config.json`: the configuration that made the checkpoint in `out_dir` (and its calibration)."""
    (out_dir / "train_config.json").write_text(json.dumps(asdict(config), indent=2) + "\n", encoding="utf-8")


def write_report(report: dict[str, Any], out_dir: Path) -> None:
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    (out_dir / "metrics.md").write_text(format_report(report), encoding="utf-8")


def format_report(report: dict[str, Any]) -> str:
    """Markdown tables: one per split, rows = method x (overall, relations, sources)."""
    lines = []
    for split, methods in report["splits"].items():
        lines += [
            f"### {split}",
            "",
            "| method | group | n | RMSE (m) | NLL (nats) | uniform NLL | better than uniform | "
            "ANEES (90% over rooms) | 0.9 HDR coverage |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for method, summary in methods.items():
            rows = [("all", summary["overall"]), *sorted(summary["per_relation"].items())]
            rows += [(f"source {k}", v) for k, v in sorted(summary["per_source"].items())]
            if len(summary["per_source"]) > 1:
                rows += [(f"source {k}", v) for k, v in sorted(summary.get("per_source_group", {}).items())]
            rows += [(f"convention {k}", v) for k, v in sorted(summary.get("per_convention", {}).items())]
            for group, s in rows:
                if not s.get("n"):
                    continue
                coverage = s.get("coverage", {}).get("0.9")
                low, high = s.get("anees_ci90") or (None, None)
                anees = f"{s['anees']:.2f}" + ("" if low is None else f" ({low:.2f}-{high:.2f})")
                cells = [
                    method,
                    group,
                    str(s["n"]),
                    f"{s['rmse']:.3f}",
                    f"{s['nll_mean']:.2f}",
                    f"{s['uniform_nll']:.2f}",
                    f"{s['better_than_uniform']:.2f}",
                    anees,
                    "" if coverage is None else f"{coverage:.3f}",
                ]
                lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


__all__ = [
    "DataConfig",
    "Densities",
    "OptimConfig",
    "TrainConfig",
    "evaluate_checkpoint",
    "fit_calibration",
    "load_split",
    "predict",
    "recalibrate",
    "train",
    "write_report",
]
