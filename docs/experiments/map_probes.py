"""Experiment (not shipped): the map's own objects as probes of the LSM's calibration on that map.

Each of up to 32 objects of a case's map (seeded per map) is hidden in turn; its relations to the rest are
computed by a convention drawn as `vlmap data build` draws them, one reading per relation, plus a region
hypothesis; the calibrated LSM grounds each and its NEES against the hidden object's centre is kept. A
map's factor per relation is the ratio of its probes' NEES to those of the calib split's maps (geometric or
arithmetic mean), shrunk to the map's pooled ratio with `k1` probes and that to 1 with `k0`; the case's
NEES is divided by it (NEES scales exactly as 1 / c under Sigma <- c Sigma).

    python docs/experiments/map_probes.py probe MODEL_DIR CASES.jsonl OUT.jsonl
    python docs/experiments/map_probes.py score REF_PROBES.jsonl PER_CASE.jsonl PROBES.jsonl

PER_CASE.jsonl is `vlmap eval static --proposer gt`'s per_case.jsonl of the same cases and model.
"""

from __future__ import annotations

import json
import sys
import zlib
from collections import defaultdict
from pathlib import Path

import numpy as np

from app.data.conventions import Convention, groundings, sr3d_context_ok
from app.data.layouts import is_grounding_target
from app.evaluation.metrics import nees
from app.grounding.relations import Relation
from app.lsm.features import PackedSamples, make_sample
from app.lsm.grounder import REGION_KEY, LSMGrounder, calibration_scale
from app.scene_graph.model import SceneGraph

WEIGHTS = {Convention.VLMAP: 0.4, Convention.SR3D: 0.3, Convention.VLA3D: 0.3}  # as the builder's


def probes(graph: SceneGraph, rng: np.random.Generator, max_targets: int = 32) -> list[tuple]:
    objects = graph.objects
    candidates = [o for o in objects if is_grounding_target(o.label)]
    volumes = {r.id: float(np.prod(r.size)) for r in graph.regions}
    out = []
    for k in rng.permutation(len(candidates))[:max_targets]:
        target = candidates[k]
        others = [o for o in objects if o.id != target.id]
        options = [c for c in WEIGHTS if c is not Convention.SR3D or sr3d_context_ok(target, others)]
        w = np.array([WEIGHTS[c] for c in options])
        convention = options[int(rng.choice(len(options), p=w / w.sum()))]
        by_relation = defaultdict(list)
        for g in groundings(convention, target, others, region_volume=volumes.get(target.region_id or "")):
            by_relation[g.relation].append(g)
        hidden = SceneGraph(regions=graph.regions, objects=others)
        relations = list(by_relation)
        rng.shuffle(relations)
        for relation in relations:
            g = by_relation[relation][int(rng.integers(len(by_relation[relation])))]
            out.append((hidden, g.anchor_ids, relation, target, None))
        if graph.regions:
            out.append((hidden, (), Relation.IN, target, target.region_id))
    return out


def probe_nees(grounder: LSMGrounder, graph: SceneGraph) -> tuple[list[str], np.ndarray]:
    rng = np.random.default_rng([0, zlib.crc32(graph.model_dump_json().encode())])
    found = probes(graph, rng)
    cfg = grounder.model.cfg
    samples = [make_sample(h, a, r, o.label, cfg, region_id=reg) for h, a, r, o, reg in found]
    out = grounder.inference(PackedSamples(samples, grounder.encoder.encode))
    keys = [r.value if a else REGION_KEY for _, a, r, _, _ in found]
    scales = np.array([calibration_scale(grounder.calibration, k) for k in keys])
    densities = grounder._densities(samples, out, scales)
    means = np.array([d.mean() for d in densities])
    covariances = np.array([d.covariance() for d in densities])
    return keys, nees(means, covariances, np.array([o.center for _, _, _, o, _ in found]))


def probe(model_dir: str, cases: str, out: str) -> None:
    from app.data.cases import read_cases

    grounder = LSMGrounder.load(Path(model_dir))
    with Path(out).open("w", encoding="utf-8") as fh:
        for case in read_cases(cases):
            keys, values = probe_nees(grounder, case.scene_graph)
            fh.write(json.dumps({"case_id": case.case_id, "keys": keys, "nees": values.tolist()}) + "\n")


def _read(path: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rows = (json.loads(line) for line in Path(path).open(encoding="utf-8"))
    return {d["case_id"]: (np.array(d["keys"]), np.array(d["nees"])) for d in rows}


def factor(keys: np.ndarray, values: np.ndarray, ref: dict, stat: str, k0: float, k1: float, key: str) -> float:
    if stat == "geo":
        d = np.log(values) - np.array([ref[k][1] for k in keys])
        agg = lambda m: float(d[m].mean())  # noqa: E731
    else:
        d = values / np.array([ref[k][0] for k in keys])
        agg = lambda m: float(np.log(d[m].mean()))  # noqa: E731
    n = len(d)
    pooled = n * agg(np.ones(n, bool)) / (n + k0)
    own = keys == key
    if not own.any():
        return float(np.exp(pooled))
    return float(np.exp((own.sum() * agg(own) + k1 * pooled) / (own.sum() + k1)))


def score(ref_path: str, per_case: str, probes_path: str) -> None:
    ref_rows = _read(ref_path)
    keys = np.concatenate([k for k, _ in ref_rows.values()])
    values = np.concatenate([v for _, v in ref_rows.values()])
    ref = {k: (values[keys == k].mean(), np.log(values[keys == k]).mean()) for k in set(keys.tolist())}
    found = _read(probes_path)
    cases = [json.loads(line) for line in Path(per_case).open(encoding="utf-8")]
    relation = np.array([c["relation"] for c in cases])
    served = np.array([c["lsm"]["nees"] for c in cases])
    for stat, k0, k1 in [("none", 0, 0), ("geo", 10, 5), ("geo", 1e9, 5), ("mean", 10, 5), ("mean", 1e9, 2)]:
        f = np.ones(len(cases))
        if stat != "none":
            f = np.array([factor(*found[c["case_id"]], ref, stat, k0, k1, c["relation"]) for c in cases])
        v = served / f
        cells = {r: v[relation == r].mean() for r in sorted(set(relation)) if (relation == r).sum() >= 50}
        print(f"{stat} k0={k0:g} k1={k1:g}: ANEES {v.mean():.2f}, " + ", ".join(f"{r} {x:.2f}" for r, x in cells.items()))


if __name__ == "__main__":
    {"probe": probe, "score": score}[sys.argv[1]](*sys.argv[2:])
