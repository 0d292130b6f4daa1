"""Experiment (not shipped): where a leave-one-source-out fold's per-relation cells go wrong, whether the band
could be told from sampling noise on these rooms, and three post-hoc changes of the served density.

    python docs/experiments/fold_diagnostics.py dump FOLD_DIR OUT.npz
    python docs/experiments/fold_diagnostics.py floor OUT.npz LEFT_SOURCE
    python docs/experiments/fold_diagnostics.py axes OUT.npz LEFT_SOURCE
    python docs/experiments/fold_diagnostics.py variants WOA.npz WOS.npz

`dump` predicts the fold's raw densities on its calib split and on val_unseen (the training report's samples,
region samples included) and keeps each sample's map box. Every other command refits the fold's own rule on
calib (NEES-consistent scale per relation, shrunk to the pooled one with 50 cases' weight, tail floor 0.1,
margin 1.31, "above" 1.0), which reproduces the report's cells, and scores val_unseen by source.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

LO, HI = 2.5, 3.5
MARGIN, MARGINS, FLOOR, PRIOR = 1.31, {"above": 1.0}, 0.1, 50.0
Data = dict[str, np.ndarray]


def dump(fold: str, out: str) -> None:
    from app.data.cases import read_cases
    from app.grounding.mixture import map_box
    from app.lsm.features import PackedSamples
    from app.lsm.model import load_checkpoint
    from app.training.lsm import TrainConfig, _embedding_cache, _load_splits, _takes_region, predict

    config = TrainConfig.from_dict(json.loads((Path(fold) / "train_config.json").read_text()))
    config.data.reports = {}
    model, _ = load_checkpoint(Path(fold))
    splits = _load_splits(config, include_train=False)
    cache = _embedding_cache(config, None)
    arrays: dict[str, np.ndarray] = {}
    for name, path, excluded in (
        ("calib", config.data.calib, tuple(config.data.exclude_sources)),
        ("val_unseen", config.data.val_unseen, ()),
    ):
        split = splits[name]
        d = predict(model, PackedSamples(split.samples, cache), split.samples, 256)
        lows, highs = [], []
        for case in read_cases(str(path)):  # load_split's filter, one box per sample
            truth = case.hypotheses[0] if case.hypotheses else None
            known = {o.id for o in case.scene_graph.objects}
            if str(case.meta.get("source")) in excluded or truth is None or not set(truth.anchor_ids) <= known:
                continue
            box = map_box(case.scene_graph)
            for _ in range(2 if _takes_region(case.case_id, config.data.region_rate) else 1):
                lows.append(box.low)
                highs.append(box.high)
        assert len(lows) == len(split.samples)
        parts = {"mu": d.means, "C": d.core, "T": d.tail, "a": d.weights, "y": split.targets}
        parts |= {"lo": np.array(lows), "hi": np.array(highs), "groups": np.array(split.groups)}
        parts |= {"sources": np.array(split.sources), "rooms": np.array(split.rooms)}
        arrays |= {f"{name}/{k}": v for k, v in parts.items()}
    cache.save()
    np.savez(out, **arrays)


def load(path: str, split: str) -> Data:
    z = np.load(path)
    return {k.split("/", 1)[1]: z[k] for k in z.files if k.startswith(split + "/")}


def take(d: Data, mask: np.ndarray) -> Data:
    return {k: v[mask] for k, v in d.items()}


def nees(d: Data, c: np.ndarray, eps: float = 0.0) -> np.ndarray:
    """NEES of the moment-matched (1 - eps) [(1 - a') N(mu, c C) + a' N(mu, c T)] + eps U(map box)."""
    a = (d["a"] + (1 - d["a"]) * FLOOR)[:, None, None]
    gauss = c[:, None, None] * ((1 - a) * d["C"] + a * d["T"])
    centre, var = 0.5 * (d["lo"] + d["hi"]), (d["hi"] - d["lo"]) ** 2 / 12
    mean = (1 - eps) * d["mu"] + eps * centre
    second = (1 - eps) * (gauss + np.einsum("si,sj->sij", d["mu"], d["mu"]))
    second += eps * (var[:, :, None] * np.eye(3) + np.einsum("si,sj->sij", centre, centre))
    cov = second - np.einsum("si,sj->sij", mean, mean)
    r = d["y"] - mean
    out: np.ndarray = np.einsum("si,si->s", r, np.linalg.solve(cov, r[..., None])[..., 0])
    return out


def nll(d: Data, c: np.ndarray, eps: float = 0.0) -> np.ndarray:
    a = d["a"] + (1 - d["a"]) * FLOOR

    def log_normal(cov: np.ndarray) -> np.ndarray:
        chol = np.linalg.cholesky(cov)
        z = np.linalg.solve(chol, (d["y"] - d["mu"])[..., None])[..., 0]
        half_logdet = np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(1)
        out: np.ndarray = -0.5 * (z**2).sum(1) - half_logdet - 1.5 * math.log(2 * math.pi)
        return out

    core = log_normal(c[:, None, None] * d["C"]) + np.log1p(-a)
    tail = log_normal(c[:, None, None] * d["T"]) + np.log(a)
    gauss = np.logaddexp(core, tail) + math.log1p(-eps)
    if eps == 0:
        return -gauss
    inside = np.all((d["y"] >= d["lo"]) & (d["y"] <= d["hi"]), axis=1)
    box = np.where(inside, math.log(eps) - np.log(np.prod(d["hi"] - d["lo"], axis=1)), -np.inf)
    out: np.ndarray = -np.logaddexp(gauss, box)
    return out


def consistent_scale(d: Data, eps: float) -> float:
    """The c with ANEES 3 (closed form without a box, where NEES scales as 1 / c; else bisection on log c)."""
    if eps == 0:
        return float(nees(d, np.ones(len(d["y"]))).mean()) / 3.0
    lo, hi = -8.0, 6.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if nees(d, np.full(len(d["y"]), math.exp(mid)), eps).mean() > 3.0:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def served_scales(cal: Data, groups: np.ndarray, eps: float = 0.0, margin: float = MARGIN) -> np.ndarray:
    pooled = consistent_scale(cal, eps)
    scale = {}
    for g in sorted(set(cal["groups"].tolist())):
        mask = cal["groups"] == g
        n = int(mask.sum())
        own = consistent_scale(take(cal, mask), eps)
        shrunk = math.exp((n * math.log(own) + PRIOR * math.log(pooled)) / (n + PRIOR))
        scale[g] = MARGINS.get(g, margin) * shrunk
    return np.array([scale.get(g, margin * pooled) for g in groups])


def cells(values: np.ndarray, d: Data, source: str) -> dict[str, float]:
    """Mean of `values` per relation (n >= 50) of one source, and "all" over its object hypotheses."""
    mine = d["sources"] == source
    out = {"all": float(values[mine & (d["groups"] != "region")].mean())}
    for g in sorted(set(d["groups"][mine].tolist())):
        mask = mine & (d["groups"] == g)
        if mask.sum() >= 50:
            out[g] = float(values[mask].mean())
    return out


def floor(path: str, left: str, draws: int = 4000) -> None:
    """Each cell's 90% interval over rooms, and how often a model whose every cell has ANEES 3 (the cell's
    NEES rescaled to mean 3, rooms resampled jointly for all cells) shows every cell inside the band."""
    cal, vu = load(path, "calib"), load(path, "val_unseen")
    values = nees(vu, served_scales(cal, vu["groups"]))
    mine = vu["sources"] == left
    rooms, groups, values = vu["rooms"][mine], vu["groups"][mine], values[mine]
    names = sorted(set(rooms.tolist()))
    room = np.searchsorted(names, rooms)
    keys = [g for g in sorted(set(groups.tolist())) if (groups == g).sum() >= 50]
    sums, counts = np.zeros((len(keys), len(names))), np.zeros((len(keys), len(names)))
    for k, g in enumerate(keys):
        np.add.at(sums[k], room[groups == g], values[groups == g])
        np.add.at(counts[k], room[groups == g], 1)
    rng = np.random.default_rng(0)
    weights = np.stack([np.bincount(rng.integers(0, len(names), len(names)), minlength=len(names))
                        for _ in range(draws)])  # (D, R)
    observed = (weights @ sums.T) / (weights @ counts.T)  # (D, K)
    ideal = observed * 3.0 / (sums.sum(1) / counts.sum(1))
    inside = (ideal >= LO) & (ideal <= HI)
    print(f"{left} left out: {len(names)} rooms")
    for k, g in enumerate(keys):
        lo, hi = np.quantile(observed[:, k], [0.05, 0.95])
        verdict = "out" if hi < LO or lo > HI else "in" if lo >= LO and hi <= HI else "either"
        print(f"  {g:9s} n {int(counts[k].sum()):4d}  ANEES {sums[k].sum() / counts[k].sum():.2f}  "
              f"90% {lo:.2f}-{hi:.2f} [{verdict}]  P(in band | ANEES 3) {inside[:, k].mean():.2f}")
    print(f"  P(all {len(keys)} cells in band | every cell at ANEES 3) = {inside.all(1).mean():.2f}")


def axes(path: str, left: str) -> None:
    """Per relation: NEES, its horizontal part (per axis) and vertical part, predicted sd and RMS error."""
    cal, vu = load(path, "calib"), load(path, "val_unseen")
    c = served_scales(cal, vu["groups"])
    a = (vu["a"] + (1 - vu["a"]) * FLOOR)[:, None, None]
    cov = c[:, None, None] * ((1 - a) * vu["C"] + a * vu["T"])
    r = vu["y"] - vu["mu"]
    full = nees(vu, c)
    z = r[:, 2] ** 2 / cov[:, 2, 2]
    xy = np.einsum("si,si->s", r[:, :2], np.linalg.solve(cov[:, :2, :2], r[:, :2, None])[..., 0]) / 2
    own = next(s for s in set(vu["sources"].tolist()) if s != left)
    print("relation  | source   n  NEES  xy/axis  z   sd_z rms_z sd_xy rms_xy (m)")
    for g in sorted(set(vu["groups"].tolist())):
        for s in (left, own):
            m = (vu["sources"] == s) & (vu["groups"] == g)
            if m.sum() < 50:
                continue
            sd_xy = np.sqrt((cov[m, 0, 0] + cov[m, 1, 1]) / 2).mean()
            print(f"{g:9s} | {s[:7]:7s} {m.sum():4d} {full[m].mean():5.2f} {xy[m].mean():5.2f} {z[m].mean():5.2f} "
                  f"{np.sqrt(cov[m, 2, 2]).mean():5.2f} {np.sqrt((r[m, 2] ** 2).mean()):5.2f} {sd_xy:5.2f} "
                  f"{np.sqrt((r[m, :2] ** 2).sum(1).mean() / 2):5.2f}")


def _vertical(d: Data, change: Callable[[np.ndarray], np.ndarray]) -> Data:
    """The densities with every covariance's z row and column times sqrt(change(var_z) / var_z)."""
    out = dict(d)
    for k in ("C", "T"):
        cov = d[k].copy()
        f = np.sqrt(change(cov[:, 2, 2]) / cov[:, 2, 2])
        cov[:, 2, :] *= f[:, None]
        cov[:, :, 2] *= f[:, None]
        out[k] = cov
    return out


def variants(woa: str, wos: str) -> None:
    """The served rule and three changes, each refitted on calib: a uniform over the map box with weight eps
    in every hypothesis's density; the vertical variance times k; the vertical sd at least s metres."""
    changes: list[tuple[str, float, Callable[[Data], Data]]] = [("as served", 0.0, lambda d: d)]
    changes += [(f"box eps {e}", e, lambda d: d) for e in (0.05, 0.1, 0.2)]
    changes += [(f"var_z x {k}", 0.0, lambda d, k=k: _vertical(d, lambda v: k * v)) for k in (2.0, 4.0)]
    changes += [(f"sd_z >= {s}", 0.0, lambda d, s=s: _vertical(d, lambda v: np.maximum(v, s * s)))
                for s in (0.2, 0.3, 0.4)]
    for label, eps, change in changes:
        row = [label]
        for path, left in ((woa, "ai2thor"), (wos, "scannet")):
            cal, vu = change(load(path, "calib")), change(load(path, "val_unseen"))
            c = served_scales(cal, vu["groups"], eps)
            anees, nlls = cells(nees(vu, c, eps), vu, left), cells(nll(vu, c, eps), vu, left)
            own = next(s for s in set(vu["sources"].tolist()) if s != left)
            home = cells(nees(vu, c, eps), vu, own)
            out = [f"{g} {v:.2f}" for g, v in anees.items() if g != "all" and not LO <= v <= HI]
            n_home = sum(1 for g, v in home.items() if g != "all" and not LO <= v <= HI)
            row.append(f"{left} left out: ANEES {anees['all']:.2f}, NLL {nlls['all']:.3f}, {len(out)} out "
                       f"({', '.join(out)}); own rooms {n_home} out")
        print(" | ".join(row))


if __name__ == "__main__":
    commands: dict[str, Callable[..., None]] = {"dump": dump, "floor": floor, "axes": axes, "variants": variants}
    commands[sys.argv[1]](*sys.argv[2:])
