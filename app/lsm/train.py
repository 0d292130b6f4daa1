"""Train the LSM on grounding cases, select on val_seen, calibrate on val_seen, report on both val splits.

The true grounding of a case is `hypotheses[0]`; the label is `target.position`. val_unseen is evaluated
and reported at every validation but never used to pick a checkpoint or fit the calibration.

Outputs in `--out`: `model.safetensors` + `config.json` (the shippable checkpoint, calibration included),
`metrics.json` / `metrics.md` (LSM before and after calibration and the baselines, overall and per
relation), `history.jsonl` (one line per validation) and `embeddings.npz` (the frozen text embeddings).
"""

from __future__ import annotations

import json
import logging
import math
import random
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from app.data.cases import GroundingCase, read_cases
from app.evaluation.metrics import gaussian_summary, nees
from app.grounding.hypotheses import Hypothesis
from app.grounding.interfaces import Grounder
from app.grounding.relations import Relation
from app.lsm.features import EmbeddingCache, PackedSamples, Sample, make_sample
from app.lsm.grounder import calibration_scale
from app.lsm.model import RELATION_INDEX, LanguageSensorModel, LSMConfig, load_checkpoint, save_checkpoint
from app.lsm.text_encoder import MINILM_SHA256, TextEncoder

log = logging.getLogger(__name__)
RELATION_NAMES = {index: relation.value for relation, index in RELATION_INDEX.items()}


@dataclass
class DataConfig:
    train: str
    val_seen: str
    val_unseen: str | None = None
    max_train_cases: int | None = None  # first N cases of the train file (for quick runs)
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
        return cls(
            data=DataConfig(**values["data"]),
            model=LSMConfig.from_dict(values.get("model", {})),
            optim=OptimConfig(**values.get("optim", {})),
            version=str(values.get("version", "dev")),
            calibration_prior_cases=float(values.get("calibration_prior_cases", 50.0)),
        )

    @classmethod
    def from_yaml(cls, path: Path) -> TrainConfig:
        import yaml

        return cls.from_dict(yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {})


@dataclass
class Split:
    """Featurised cases of one file (plus the cases themselves for the baselines, on validation splits)."""

    name: str
    samples: list[Sample]
    relations: list[str]
    cases: list[GroundingCase]
    skipped: int


def load_split(
    name: str, path: str, cfg: LSMConfig, limit: int | None = None, keep_cases: bool = False
) -> Split:
    """Cases with a ground-truth hypothesis whose anchors exist -> samples; the others count as skipped."""
    samples: list[Sample] = []
    relations: list[str] = []
    cases: list[GroundingCase] = []
    skipped = 0
    for case in read_cases(path):
        if limit is not None and len(samples) >= limit:
            break
        truth = case.hypotheses[0] if case.hypotheses else None
        known = {o.id for o in case.scene_graph.objects}
        if truth is None or not set(truth.anchor_ids) <= known:
            skipped += 1
            continue
        samples.append(
            make_sample(
                case.scene_graph, truth.anchor_ids, truth.relation, case.utterance, cfg, case.target.position
            )
        )
        relations.append(truth.relation.value)
        if keep_cases:
            cases.append(case)
    if not samples:
        msg = (
            f"{path}: no usable grounding cases (need hypotheses[0] with anchors present in the scene graph)"
        )
        raise ValueError(msg)
    return Split(name, samples, relations, cases, skipped)


def predict(
    model: LanguageSensorModel, packed: PackedSamples, batch_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Uncalibrated means (S, 3) and covariances (S, 3, 3), float64."""
    model.eval()
    means, covs = [], []
    with torch.inference_mode():
        for start in range(0, len(packed), batch_size):
            out = model(packed.batch(slice(start, start + batch_size)))
            means.append(out.mean.double().numpy())
            covs.append(out.covariance.double().numpy())
    return np.concatenate(means), np.concatenate(covs)


def summarize(
    means: np.ndarray, covs: np.ndarray, targets: np.ndarray, relations: list[str]
) -> dict[str, Any]:
    """Overall and per-relation `gaussian_summary`."""
    rel = np.asarray(relations)
    per_relation = {
        r: gaussian_summary(means[rel == r], covs[rel == r], targets[rel == r])
        for r in sorted(set(relations))
    }
    return {"overall": gaussian_summary(means, covs, targets), "per_relation": per_relation}


def fit_calibration(
    means: np.ndarray, covs: np.ndarray, targets: np.ndarray, relations: list[str], prior_cases: float = 50.0
) -> dict[str, Any]:
    """Covariance scales c_r such that Sigma <- c_r Sigma brings ANEES to 3 (NEES scales as 1/c).

    c = ANEES / 3 over all cases; c_r = (n_r ANEES_r + k ANEES) / (3 (n_r + k)): each relation's own ANEES,
    shrunk towards the pooled one as if k = `prior_cases` more cases had the pooled value, so that a relation
    with few calibration cases (e.g. 41 "in" cases in val_seen) does not get a noisy scale.
    """
    per_case = nees(means, covs, targets)
    rel = np.asarray(relations)
    pooled = float(np.mean(per_case))
    per_relation, counts = {}, {}
    for r in sorted(set(relations)):
        values = per_case[rel == r]
        counts[r] = len(values)
        per_relation[r] = float((values.sum() + prior_cases * pooled) / (3.0 * (len(values) + prior_cases)))
    return {
        "method": "covariance scale per relation, c_r = ANEES_r / 3 on val_seen shrunk to the pooled ANEES",
        "prior_cases": prior_cases,
        "overall": pooled / 3.0,
        "per_relation": per_relation,
        "cases": counts,
    }


def apply_calibration(covs: np.ndarray, relations: list[str], calibration: dict[str, Any]) -> np.ndarray:
    scales = np.array([calibration_scale(calibration, Relation(r)) for r in relations])
    return covs * scales[:, None, None]


def ground_cases(grounder: Grounder, cases: list[GroundingCase]) -> tuple[np.ndarray, np.ndarray]:
    """Any grounder's Gaussian for each case's ground-truth hypothesis."""
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
    return np.asarray(means, dtype=np.float64), np.asarray(covs, dtype=np.float64)


def baseline_grounders() -> dict[str, Grounder]:
    """The hand-written baselines of `app.grounding.geometric`, when that module is present."""
    try:
        from app.grounding.geometric import FixedGrounder, GeometricGrounder
    except ImportError:
        log.warning("app.grounding.geometric is not importable: the report has no baselines")
        return {}
    return {"geometric": GeometricGrounder(), "fixed_0.1m": FixedGrounder()}


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
    """Train, keep the best val_seen NLL checkpoint, calibrate it on val_seen, write it and its report."""
    from tqdm import tqdm

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    opt = config.optim
    seed_everything(opt.seed)
    torch.set_num_threads(opt.threads)
    (out_dir / "train_config.json").write_text(json.dumps(asdict(config), indent=2) + "\n", encoding="utf-8")

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
    history, best = [], {"nll": math.inf, "step": -1}
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
                history.append(record)
                with (out_dir / "history.jsonl").open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps(record) + "\n")
                bar.write(_format_record(record))
                if record["val_seen"]["nll_mean"] < best["nll"]:
                    best = {"nll": record["val_seen"]["nll_mean"], "step": step, "epoch": epoch}
                    best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    bar.close()
    model.load_state_dict(best_state)

    seen_split = splits["val_seen"]
    means, covs = predict(model, packed["val_seen"], opt.eval_batch_size)
    calibration = fit_calibration(
        means, covs, _targets(seen_split), seen_split.relations, config.calibration_prior_cases
    )
    training = {
        "data": {n: {"cases": len(s.samples), "skipped": s.skipped} for n, s in splits.items()},
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


def evaluate_checkpoint(
    model_dir: Path,
    config: TrainConfig,
    splits: dict[str, Split] | None = None,
    packed: dict[str, PackedSamples] | None = None,
    cache_dir: Path | None = None,
) -> dict[str, Any]:
    """The saved checkpoint (raw and calibrated) and the baselines on val_seen and val_unseen.

    Without `splits`/`packed` the validation files of `config` are read, with text embeddings cached in
    `config.data.embedding_cache` or else `cache_dir`/embeddings.npz.
    """
    model, meta = load_checkpoint(Path(model_dir))
    if splits is None or packed is None:
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
    for name in ("val_seen", "val_unseen"):
        if name not in splits:
            continue
        split = splits[name]
        targets = _targets(split)
        means, covs = predict(model, packed[name], config.optim.eval_batch_size)
        methods = {
            "lsm": summarize(
                means,
                apply_calibration(covs, split.relations, meta.get("calibration", {})),
                targets,
                split.relations,
            ),
            "lsm_uncalibrated": summarize(means, covs, targets, split.relations),
        }
        for label, grounder in baselines.items():
            b_means, b_covs = ground_cases(grounder, split.cases)
            methods[label] = summarize(b_means, b_covs, targets, split.relations)
        report["splits"][name] = methods
    return report


def _load_splits(config: TrainConfig, include_train: bool = True) -> dict[str, Split]:
    data, cfg = config.data, config.model
    splits = {}
    if include_train:
        splits["train"] = load_split("train", data.train, cfg, limit=data.max_train_cases)
    splits["val_seen"] = load_split("val_seen", data.val_seen, cfg, keep_cases=True)
    if data.val_unseen:
        splits["val_unseen"] = load_split("val_unseen", data.val_unseen, cfg, keep_cases=True)
    return splits


def _embedding_cache(config: TrainConfig, out_dir: Path | None) -> EmbeddingCache:
    path = Path(config.data.embedding_cache) if config.data.embedding_cache else None
    if path is None and out_dir is not None:
        path = out_dir / "embeddings.npz"
    # float32 always: these embeddings are what the model is trained on (and they are cached to disk).
    return EmbeddingCache(path, MINILM_SHA256, lambda: TextEncoder(precision="float32").encode)


def _targets(split: Split) -> np.ndarray:
    return np.stack([s.target for s in split.samples if s.target is not None]).astype(np.float64)


def _validate(
    model: LanguageSensorModel, packed: dict[str, PackedSamples], splits: dict[str, Split], batch_size: int
) -> dict[str, Any]:
    record: dict[str, Any] = {}
    for name in ("val_seen", "val_unseen"):
        if name in packed:
            means, covs = predict(model, packed[name], batch_size)
            summary = summarize(means, covs, _targets(splits[name]), splits[name].relations)
            record[name] = summary["overall"] | {
                "anees_per_relation": {r: v["anees"] for r, v in summary["per_relation"].items()}
            }
    return record


def _format_record(record: dict[str, Any]) -> str:
    parts = [f"step {record['step']} epoch {record['epoch']} loss {record['train_loss']:.3f}"]
    for name in ("val_seen", "val_unseen"):
        if name in record:
            r = record[name]
            parts.append(f"{name}: rmse {r['rmse']:.3f} nll {r['nll_mean']:.3f} anees {r['anees']:.2f}")
    return " | ".join(parts)


def write_report(report: dict[str, Any], out_dir: Path) -> None:
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    (out_dir / "metrics.md").write_text(format_report(report), encoding="utf-8")


def format_report(report: dict[str, Any]) -> str:
    """Markdown tables: one per split, rows = method x (overall, relations), RMSE / NLL / ANEES."""
    lines = []
    for split, methods in report["splits"].items():
        lines += [
            f"### {split}",
            "",
            "| method | relation | n | RMSE (m) | NLL (nats) | ANEES |",
            "|---|---|---|---|---|---|",
        ]
        for method, summary in methods.items():
            rows = [("all", summary["overall"]), *sorted(summary["per_relation"].items())]
            for relation, s in rows:
                cells = [
                    method,
                    relation,
                    str(s["n"]),
                    f"{s['rmse']:.3f}",
                    f"{s['nll_mean']:.2f}",
                    f"{s['anees']:.2f}",
                ]
                lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)
