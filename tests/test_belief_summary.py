"""The posterior summary against brute force over every voxel, and on a real AI2-THOR room."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from app.belief.grid import VoxelGrid
from app.belief.session import new_session
from app.belief.summary import cached_place_index, summarize
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph

RESOURCES = Path(__file__).parent / "resources" / "belief"


def brute_force(grid: VoxelGrid, lang: np.ndarray, vis: np.ndarray, sg: SceneGraph, on_margin: float) -> dict:
    s = lang.astype(np.float64) + vis.astype(np.float64)
    p = np.exp(s - s.max())
    p /= p.sum()
    centres = grid.centers()
    mean = p @ centres
    diff = centres - mean
    nonzero = p > 0
    objects = {}
    for obj in sg.objects:
        c, sn = math.cos(obj.yaw), math.sin(obj.yaw)
        d = centres - np.asarray(obj.center)
        local_x, local_y = c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]
        half = 0.5 * np.asarray(obj.size)
        inside = (
            (np.abs(local_x) <= half[0])
            & (np.abs(local_y) <= half[1])
            & (d[:, 2] >= -half[2])
            & (d[:, 2] <= half[2] + on_margin)
        )
        if not inside.any():
            flat, ok = grid.locate(np.asarray(obj.center)[None, :])
            inside = np.zeros(grid.n_voxels, dtype=bool)
            if ok[0]:
                inside[flat[0]] = True
        objects[obj.id] = float(p[inside].sum())
    regions = {}
    for reg in sg.regions:
        half = 0.5 * np.asarray(reg.size)
        inside = np.all(np.abs(centres - np.asarray(reg.center)) <= half, axis=1)
        regions[reg.id] = float(p[inside].sum())
    return {
        "p": p,
        "mean": mean,
        "cov": (diff * p[:, None]).T @ diff,
        "entropy": float(-np.sum(p[nonzero] * np.log(p[nonzero]))),
        "objects": objects,
        "regions": regions,
    }


SCENE = SceneGraph.model_validate(
    {
        "regions": [
            {"id": "kitchen", "name": "kitchen", "center": [1.0, 0.6, 1.0], "size": [1.6, 1.4, 2.0]},
            {"id": "hall", "name": "hall", "center": [2.6, 0.6, 1.0], "size": [1.5, 1.4, 2.0]},
        ],
        "objects": [
            {"id": "7", "label": "table", "center": [0.8, 0.5, 0.35], "size": [0.9, 0.6, 0.7]},
            {"id": "8", "label": "counter", "center": [2.3, 0.7, 0.45], "size": [1.1, 0.5, 0.9], "yaw": 0.6},
            {"id": "9", "label": "key", "center": [1.53, 1.04, 0.71], "size": [0.02, 0.03, 0.01]},
            {"id": "10", "label": "shelf", "center": [3.4, -0.1, 1.2], "size": [0.8, 0.6, 2.0]},
        ],
    }
)


@pytest.mark.parametrize(
    ("seed", "lang_std", "vis_offset"),
    [
        (0, 3.0, 0.0),  # the layers' default clamps: exp without a shift
        (1, 3.0, 0.0),
        (2, 3.0, 80.0),  # log-weights up to 92, where float32 exp overflows: exp(s - peak)
        (3, 60.0, 0.0),  # a range wider than 80 nats: exp(max(s - peak, -80))
    ],
)
def test_summary_matches_brute_force(seed: int, lang_std: float, vis_offset: float) -> None:
    rng = np.random.default_rng(seed)
    grid = VoxelGrid.around(SCENE, voxel_size=0.1, margin=0.3)
    assert grid.n_voxels > 10 * 1024  # several top-k blocks
    lang = np.minimum(rng.normal(0, lang_std, grid.n_voxels), 0).astype(np.float32)
    vis = (rng.uniform(-10, 12, grid.n_voxels) + vis_offset).astype(np.float32)
    summary = summarize(grid, lang, vis, SCENE, top_k=7, max_places=10, on_margin=0.3)
    ref = brute_force(grid, lang, vis, SCENE, on_margin=0.3)
    p = ref["p"]
    order = np.argsort(-p, kind="stable")[:7]
    assert [v.index for v in summary.top_voxels] == order.tolist()
    assert summary.map_voxel.index == int(np.argmax(p))
    np.testing.assert_allclose([v.probability for v in summary.top_voxels], p[order], rtol=1e-5)
    np.testing.assert_allclose([v.center for v in summary.top_voxels], grid.centers(order), atol=1e-12)
    np.testing.assert_allclose(summary.mean, ref["mean"], atol=1e-5)
    np.testing.assert_allclose(summary.covariance, ref["cov"], rtol=1e-4, atol=1e-7)
    assert summary.entropy_nats == pytest.approx(ref["entropy"], rel=1e-5)
    assert summary.information_gain_nats == pytest.approx(math.log(grid.n_voxels) - ref["entropy"], abs=1e-4)
    assert {m.id: m.mass for m in summary.objects} == pytest.approx(ref["objects"], rel=1e-5, abs=1e-9)
    assert {m.id: m.mass for m in summary.regions} == pytest.approx(ref["regions"], rel=1e-5, abs=1e-9)
    masses = [m.mass for m in summary.objects]
    assert masses == sorted(masses, reverse=True)
    assert ref["objects"]["9"] > 0  # the key is smaller than a voxel: it gets the voxel containing it


def test_concentrated_posterior_far_from_the_origin_keeps_its_covariance() -> None:
    grid = VoxelGrid((41.0, -37.0, 0.0), (30, 20, 10), 0.1)
    lang = np.full(grid.n_voxels, -25.0, dtype=np.float32)
    centre = grid.centers(np.array([grid.ijk_to_flat(np.array([15, 10, 5]))]))[0]
    near = np.linalg.norm(grid.centers() - centre, axis=1) < 0.25
    lang[near] = -np.linalg.norm(grid.centers()[near] - centre, axis=1).astype(np.float32) * 10
    vis = np.zeros(grid.n_voxels, dtype=np.float32)
    summary = summarize(grid, lang, vis)
    ref = brute_force(grid, lang, vis, SceneGraph(), on_margin=0.0)
    np.testing.assert_allclose(summary.mean, ref["mean"], rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(summary.covariance, ref["cov"], rtol=1e-4, atol=1e-8)
    assert np.all(np.linalg.eigvalsh(np.array(summary.covariance)) > 0)


def test_uniform_belief_has_maximal_entropy_and_no_information() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (13, 11, 9), 0.2)
    zeros = np.zeros(grid.n_voxels, dtype=np.float32)
    summary = summarize(grid, zeros, zeros, top_k=5)
    assert summary.entropy_nats == pytest.approx(math.log(grid.n_voxels), rel=1e-6)
    assert summary.information_gain_nats == pytest.approx(0.0, abs=1e-5)
    assert len({v.index for v in summary.top_voxels}) == 5
    assert all(v.probability == pytest.approx(1 / grid.n_voxels) for v in summary.top_voxels)
    np.testing.assert_allclose(summary.mean, grid.centers().mean(axis=0), atol=1e-6)


def test_top_k_with_ties_across_blocks_returns_the_largest_values() -> None:
    grid = VoxelGrid((0.0, 0.0, 0.0), (40, 30, 10), 0.1)
    rng = np.random.default_rng(4)
    s = rng.choice(np.array([-3.0, -1.0, 0.0], dtype=np.float32), size=grid.n_voxels, p=[0.9, 0.0995, 0.0005])
    zeros = np.zeros(grid.n_voxels, dtype=np.float32)
    summary = summarize(grid, s, zeros, top_k=12)
    values = s[[v.index for v in summary.top_voxels]]
    assert np.array_equal(values, np.sort(s)[::-1][:12])
    assert len({v.index for v in summary.top_voxels}) == 12
    assert summarize(grid, s, zeros, top_k=grid.n_voxels + 5).top_voxels[-1].probability > 0  # k > N is fine


def test_describe_reads_like_the_brief() -> None:
    grid = VoxelGrid.around(SCENE, voxel_size=0.1, margin=0.3)
    lang = np.full(grid.n_voxels, -40.0, dtype=np.float32)
    on_table, on_counter = grid.locate(np.array([[0.8, 0.5, 0.8], [2.3, 0.7, 1.0]]))[0]
    lang[on_table], lang[on_counter] = math.log(2.0), 0.0
    summary = summarize(grid, lang, np.zeros_like(lang), SCENE)
    assert summary.describe(2) == "0.67 on table 7, 0.33 on counter 8"
    assert summary.regions[0].describe() == "0.67 in kitchen"
    as_dict = summary.to_dict()
    assert json.loads(json.dumps(as_dict)) == as_dict
    assert as_dict["objects"][0] == {
        "kind": "object",
        "id": "7",
        "label": "table",
        "mass": pytest.approx(2 / 3),
    }


def test_place_index_is_cached_per_grid_and_scene_content() -> None:
    grid = VoxelGrid.around(SCENE, voxel_size=0.1, margin=0.3)
    same = SceneGraph.model_validate(SCENE.model_dump())
    assert cached_place_index(grid, SCENE) is cached_place_index(grid, same)
    moved = SCENE.model_copy(update={"objects": SCENE.objects[:2]})
    assert cached_place_index(grid, moved) is not cached_place_index(grid, SCENE)


def ai2thor_scene() -> tuple[SceneGraph, dict[str, dict]]:
    raw = json.loads((RESOURCES / "ai2thor_living_rooms_01.json").read_text(encoding="utf-8"))
    keep = ("id", "label", "center", "size")
    objects = {o["id"]: o for o in raw["objects"]}
    return SceneGraph.model_validate({"objects": [{k: o[k] for k in keep} for o in raw["objects"]]}), objects


@pytest.mark.parametrize(
    "target_label", ["RemoteControl", "CreditCard", "KeyChain", "Watch", "Book", "Laptop", "Pillow", "Statue"]
)
def test_real_placements_put_the_mass_on_the_receptacle(target_label: str) -> None:
    """Take a placed object out of a real AI2-THOR room and believe in its position: its receptacle wins."""
    full, raw = ai2thor_scene()
    target = next(o for o in raw.values() if o["label"] == target_label)
    scene = full.model_copy(update={"objects": [o for o in full.objects if o.id != target["id"]]})
    session = new_session("robot", scene, target_label)
    tight = GaussianMixture.from_components(
        [1.0], [Gaussian(np.asarray(target["center"]), 0.05**2 * np.eye(3))]
    )
    session.belief.apply_utterance(tight)
    summary = session.summary()
    receptacles = {raw[r]["label"] for r in target["parent_receptacles"] if r in raw}
    assert summary.objects[0].label in receptacles, summary.describe(4)
    assert summary.objects[0].mass > 0.5


def test_segment_sums_match_a_loop_with_empty_segments_anywhere() -> None:
    from app.belief.summary import _segment_sums

    rng = np.random.default_rng(4)
    p = rng.random(50).astype(np.float32)
    lengths = [0, 3, 0, 0, 5, 1, 0]  # empty first, in the middle and last
    flat = rng.integers(0, 50, size=sum(lengths))
    bounds = np.cumsum([0, *lengths])
    expected = [p[flat[a:b]].astype(np.float64).sum() for a, b in itertools.pairwise(bounds)]
    np.testing.assert_allclose(_segment_sums(p, flat, bounds), expected, rtol=1e-12)
    assert _segment_sums(p, flat[:0], np.zeros(3, dtype=np.int64)).tolist() == [0.0, 0.0]
