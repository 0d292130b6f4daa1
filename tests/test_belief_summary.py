"""The posterior summary against brute force over every voxel, and on real ScanNet and AI2-THOR rooms."""

from __future__ import annotations

import itertools
import json
import math
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.belief import summary as summary_module
from app.belief.grid import VoxelGrid
from app.belief.session import new_session
from app.belief.summary import (
    ON_MARGIN_M,
    PosteriorSummary,
    cached_place_index,
    is_room_structure,
    summarize,
    support_heights,
)
from app.grounding.box_relations import INTERNAL_SUPPORT_MIN_HEIGHT, ON_MIN_BOTTOM_FRACTION, ON_SINK_TOLERANCE
from app.grounding.mixture import Gaussian, GaussianMixture
from app.scene_graph.model import SceneGraph, SceneObject

RESOURCES = Path(__file__).parent / "resources"


def brute_force(
    grid: VoxelGrid, lang: np.ndarray, vis: np.ndarray, sg: SceneGraph, on_margin: float
) -> dict[str, Any]:
    """Every statistic from the full posterior; each voxel's place is the smallest support place holding it
    (structure only where no object's does), found by testing every voxel centre against every place."""
    s = lang.astype(np.float64) + vis.astype(np.float64)
    p = np.exp(s - s.max())
    p /= p.sum()
    centres = grid.centers()
    mean = p @ centres
    diff = centres - mean
    nonzero = p > 0
    inside = []
    for obj in sg.objects:
        heights = support_heights(obj, on_margin)
        if heights is None:
            inside.append(np.zeros(grid.n_voxels, dtype=bool))
            continue
        c, sn = math.cos(obj.yaw), math.sin(obj.yaw)
        d = centres - np.asarray(obj.center)
        local_x, local_y = c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]
        half = 0.5 * np.asarray(obj.size)
        mask = (
            (np.abs(local_x) <= half[0])
            & (np.abs(local_y) <= half[1])
            & (centres[:, 2] >= heights[0])
            & (centres[:, 2] <= heights[1])
        )
        if not mask.any():
            flat, ok = grid.locate(np.asarray(obj.center)[None, :])
            if ok[0]:
                mask[flat[0]] = True
        inside.append(mask)
    shell = [is_room_structure(obj.label) for obj in sg.objects]
    priority = sorted(range(len(sg.objects)), key=lambda i: (shell[i], int(inside[i].sum()), i))
    owner = np.full(grid.n_voxels, -1)
    for i in reversed(priority):
        owner[inside[i]] = i
    masses = {obj.id: float(p[owner == i].sum()) for i, obj in enumerate(sg.objects)}
    regions = {}
    for reg in sg.regions:
        half = 0.5 * np.asarray(reg.size)
        in_region = np.all(np.abs(centres - np.asarray(reg.center)) <= half, axis=1)
        regions[reg.id] = float(p[in_region].sum())
    return {
        "p": p,
        "mean": mean,
        "cov": (diff * p[:, None]).T @ diff,
        "entropy": float(-np.sum(p[nonzero] * np.log(p[nonzero]))),
        "objects": {obj.id: masses[obj.id] for obj, sh in zip(sg.objects, shell, strict=True) if not sh},
        "structure": {obj.id: masses[obj.id] for obj, sh in zip(sg.objects, shell, strict=True) if sh},
        "elsewhere": float(p[owner < 0].sum()),
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
            {"id": "11", "label": "floor", "center": [1.8, 0.5, -0.05], "size": [3.8, 2.2, 0.1]},
            {"id": "12", "label": "wall", "center": [1.8, 1.55, 1.2], "size": [3.8, 0.1, 2.4]},
            {
                "id": "13",
                "label": "nightstand",
                "center": [0.2, 1.2, 0.3],
                "size": [0.4, 0.4, 0.6],
                "yaw": 0.3,
            },
            {
                "id": "14",
                "label": "drawer",
                "center": [0.2, 1.2, 0.45],
                "size": [0.36, 0.36, 0.2],
                "yaw": 0.3,
            },
            {"id": "15", "label": "door", "center": [3.0, 1.5, 1.0], "size": [0.9, 0.05, 2.0]},
            {"id": "16", "label": "lamp", "center": [0.25, 1.2, 0.8], "size": [0.2, 0.2, 0.4]},
        ],
    }
)


def off_lattice_grid() -> VoxelGrid:
    """A 0.1 m grid around SCENE whose voxel centres lie off the centimetre lattice of the boxes' faces: no
    centre lies on a face, where rounding would decide whether it is inside."""
    around = VoxelGrid.around(SCENE, voxel_size=0.1, margin=0.3)
    shifted = tuple(float(v) for v in np.add(around.origin, [0.013, 0.027, 0.011]))
    return VoxelGrid((shifted[0], shifted[1], shifted[2]), around.shape, around.voxel_size)


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
    grid = off_lattice_grid()
    assert grid.n_voxels > 10 * 1024  # several top-k blocks
    lang = np.minimum(rng.normal(0, lang_std, grid.n_voxels), 0).astype(np.float32)
    vis = (rng.uniform(-10, 12, grid.n_voxels) + vis_offset).astype(np.float32)
    summary = summarize(grid, lang, vis, SCENE, top_k=7, max_places=20, on_margin=0.3)
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
    assert {m.id: m.mass for m in summary.structure} == pytest.approx(ref["structure"], rel=1e-5, abs=1e-9)
    assert summary.mass_elsewhere == pytest.approx(ref["elsewhere"], rel=1e-5, abs=1e-9)
    assert {m.id: m.mass for m in summary.regions} == pytest.approx(ref["regions"], rel=1e-5, abs=1e-9)
    for places in (summary.objects, summary.structure, summary.regions):
        masses = [m.mass for m in places]
        assert masses == sorted(masses, reverse=True)
    total = sum(m.mass for m in summary.objects) + sum(m.mass for m in summary.structure)
    assert total + summary.mass_elsewhere == pytest.approx(1.0, abs=1e-6)  # each voxel in one place at most
    assert ref["objects"]["9"] > 0  # the key is smaller than a voxel: it gets the voxel containing it
    assert ref["objects"]["14"] > 0 and ref["objects"]["15"] == 0  # a drawer holds things, a door does not


def test_places_summed_by_sub_box_match_brute_force(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a budget of 100 listed voxels most places are summed over their sub-boxes, some with a
    mask of the voxels they own (the floor under the furniture, the nightstand around its drawer)."""
    monkeypatch.setattr(summary_module, "_INDEXED_VOXELS", 100)
    monkeypatch.setattr(summary_module, "_place_cache", OrderedDict())
    grid = off_lattice_grid()
    index = cached_place_index(grid, SCENE)
    summed = {index.supports[i].id: index.supports[i] for i in index.summed.tolist()}
    assert {"11", "13"} <= summed.keys() and len(index.indexed) > 0
    assert summed["11"].mask is not None and summed["13"].mask is not None  # others own some of their voxels
    rng = np.random.default_rng(5)
    lang = np.minimum(rng.normal(0, 3.0, grid.n_voxels), 0).astype(np.float32)
    vis = rng.uniform(-10, 12, grid.n_voxels).astype(np.float32)
    summary = summarize(grid, lang, vis, SCENE, max_places=20)
    ref = brute_force(grid, lang, vis, SCENE, on_margin=ON_MARGIN_M)
    assert {m.id: m.mass for m in summary.objects} == pytest.approx(ref["objects"], rel=1e-5, abs=1e-9)
    assert {m.id: m.mass for m in summary.structure} == pytest.approx(ref["structure"], rel=1e-5, abs=1e-9)
    assert summary.mass_elsewhere == pytest.approx(ref["elsewhere"], rel=1e-5, abs=1e-9)


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
    assert as_dict["structure"][0]["label"] == "floor"
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


def ai2thor_scene() -> tuple[SceneGraph, dict[str, dict[str, Any]]]:
    raw = json.loads((RESOURCES / "belief" / "ai2thor_living_rooms_01.json").read_text(encoding="utf-8"))
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


def _object(label: str, bottom: float = 0.0, height: float = 0.6) -> SceneObject:
    return SceneObject(id="x", label=label, center=[0.0, 0.0, bottom + height / 2], size=[0.5, 0.5, height])


def test_support_places_follow_the_label_classes() -> None:
    margin = ON_MARGIN_M
    assert support_heights(_object("nightstand")) == pytest.approx((0.0, 0.6 + margin))  # inside and on top
    assert support_heights(_object("Kitchen_Cabinets")) == pytest.approx((0.0, 0.6 + margin))
    assert support_heights(_object("drawer")) == pytest.approx((0.0, 0.6))  # a part: inside it, nothing on it
    table = support_heights(_object("table", height=0.75))
    assert table == pytest.approx((0.75 - ON_SINK_TOLERANCE, 0.75 + margin))  # its top, not under it
    thin = support_heights(_object("coffee table", height=0.3))
    assert thin == pytest.approx((ON_MIN_BOTTOM_FRACTION * 0.3, 0.3 + margin))  # never below half its height
    assert support_heights(_object("bed")) == pytest.approx((INTERNAL_SUPPORT_MIN_HEIGHT, 0.6 + margin))
    assert support_heights(_object("door")) is None
    assert support_heights(_object("knob")) is None
    assert support_heights(_object("floor", bottom=-0.1, height=0.1)) == pytest.approx((-0.1, margin))
    shell = ("floor", "Floors", "wall", "closet wall", "ceiling", "pillar", "partition")
    assert all(is_room_structure(label) for label in shell)
    assert not any(is_room_structure(label) for label in ("door", "window", "table", "nightstand", "object"))


def scannet_room() -> SceneGraph:
    """ScanNet scene0590_00: 60 objects, two nightstands by the bed, a lamp on one, a 0.46 m thick floor."""
    raw = json.loads((RESOURCES / "scenes" / "scannet_scene0590_00.json").read_text(encoding="utf-8"))
    return SceneGraph.model_validate(raw)


def test_keys_on_a_nightstand_count_for_the_nightstand_and_the_floor_under_structure() -> None:
    scene = scannet_room()
    nightstand = next(o for o in scene.objects if o.id == "1")
    top = nightstand.center[2] + nightstand.size[2] / 2
    session = new_session("robot", scene, "keys")
    keys = np.array([nightstand.center[0], nightstand.center[1], top + 0.05])
    session.belief.apply_utterance(
        GaussianMixture.from_components([1.0], [Gaussian(keys, np.diag([0.08, 0.08, 0.04]) ** 2)])
    )
    summary = session.summary(max_places=100)
    # The floor's box plus the "on" margin covers the nightstand's top (that mass made the floor lead), and
    # the lamp on the nightstand stands in it too.
    p = np.exp(session.belief.lang.astype(np.float64) + session.belief.vis)
    p3 = (p / p.sum()).reshape(session.grid.shape)
    index = cached_place_index(session.grid, scene)
    by_id = {place.id: place for place in index.objects}
    assert p3[by_id["9"].slices].sum() > 0.8  # 9: the floor
    assert summary.objects[0].id == "1" and summary.objects[0].mass > 0.8, summary.describe(4)
    assert not any(is_room_structure(m.label) for m in summary.objects)
    assert next(m for m in summary.objects if m.id == "3").mass < 0.1  # 3: the lamp on it
    floor = next(m for m in summary.structure if m.label == "floor")
    assert floor.mass < 0.05
    total = sum(m.mass for m in (*summary.objects, *summary.structure)) + summary.mass_elsewhere
    assert total == pytest.approx(1.0, abs=1e-6)


def test_an_utterance_about_the_nightstand_puts_the_nightstands_first(
    client: TestClient, scene_graph_dict: dict[str, Any]
) -> None:
    sid = client.post("/v1/sessions", json={"robot_id": "r1", "scene_graph": scene_graph_dict}).json()["id"]
    utterance = {"utterance": "I left my keys on the nightstand"}
    summary = client.post(f"/v1/sessions/{sid}/utterances", json=utterance).json()["belief"]["summary"]
    assert {m["label"] for m in summary["objects"][:2]} == {"nightstand"}, summary["objects"][:4]
    assert summary["objects"][0]["mass"] + summary["objects"][1]["mass"] > 0.7
    assert all(not is_room_structure(m["label"]) for m in summary["objects"])
    assert {"floor", "wall"} <= {m["label"] for m in summary["structure"]}
    assert 0 <= summary["mass_elsewhere"] < 0.2
    polled = client.get(f"/v1/sessions/{sid}/belief").json()["summary"]
    assert polled["structure"] == summary["structure"]


# A dresser with three drawers (boxes inside its box), a lamp on it, on a floor, by a wall.
DRESSER = SceneGraph.model_validate(
    {
        "objects": [
            {"id": "f", "label": "floor", "center": [0.0, 0.0, -0.05], "size": [3.0, 3.0, 0.1]},
            {"id": "w", "label": "wall", "center": [0.0, 0.62, 1.2], "size": [3.0, 0.1, 2.4]},
            {"id": "d", "label": "dresser", "center": [0.0, 0.3, 0.45], "size": [1.0, 0.5, 0.9]},
            {"id": "d1", "label": "drawer", "center": [0.0, 0.3, 0.17], "size": [0.9, 0.45, 0.24]},
            {"id": "d2", "label": "drawer", "center": [0.0, 0.3, 0.44], "size": [0.9, 0.45, 0.24]},
            {"id": "d3", "label": "drawer", "center": [0.0, 0.3, 0.71], "size": [0.9, 0.45, 0.24]},
            {"id": "l", "label": "lamp", "center": [0.35, 0.35, 1.1], "size": [0.2, 0.2, 0.4]},
        ]
    }
)


def _believe(scene: SceneGraph, point: list[float], std: list[float]) -> PosteriorSummary:
    session = new_session("robot", scene, "ring", voxel_size=0.04)
    session.belief.apply_utterance(
        GaussianMixture.from_components([1.0], [Gaussian(np.asarray(point), np.diag(std) ** 2)])
    )
    return session.summary(max_places=100)


def test_a_belief_inside_a_drawer_counts_for_the_drawer_and_one_on_top_for_the_dresser() -> None:
    inside = _believe(DRESSER, [0.0, 0.3, 0.44], [0.12, 0.06, 0.04])
    assert inside.objects[0].id == "d2" and inside.objects[0].mass > 0.8, inside.describe(4)
    assert inside.objects[1].id in ("d", "d1", "d3")
    on_top = _believe(DRESSER, [-0.2, 0.3, 0.95], [0.1, 0.06, 0.03])
    assert on_top.objects[0].id == "d" and on_top.objects[0].mass > 0.8, on_top.describe(4)
    assert next(m for m in on_top.objects if m.id == "d3").mass < 0.05  # nothing rests on a drawer
    assert next(m for m in on_top.structure if m.id == "f").mass < 0.01


def test_structure_is_reported_apart_and_the_masses_sum_to_one() -> None:
    on_floor = _believe(DRESSER, [-1.0, -0.8, 0.1], [0.1, 0.1, 0.05])
    assert [m.id for m in on_floor.structure][:1] == ["f"] and on_floor.structure[0].mass > 0.9
    assert {m.id for m in on_floor.objects} == {"d", "d1", "d2", "d3", "l"}  # structure is not among them
    assert all(m.mass < 0.01 for m in on_floor.objects)
    on_wall = _believe(DRESSER, [-1.0, 0.62, 1.5], [0.2, 0.02, 0.2])
    assert on_wall.structure[0].id == "w" and on_wall.structure[0].mass > 0.8
    uniform = summarize(
        grid := VoxelGrid.around(DRESSER, voxel_size=0.05),
        np.zeros(grid.n_voxels, dtype=np.float32),
        np.zeros(grid.n_voxels, dtype=np.float32),
        DRESSER,
        max_places=100,
    )
    masses = [m.mass for m in (*uniform.objects, *uniform.structure)]
    assert sum(masses) + uniform.mass_elsewhere == pytest.approx(1.0, abs=1e-6)
    assert 0 < uniform.mass_elsewhere < 1  # the air above the floor's margin is no place


def test_summary_dicts_round_trip_and_older_ones_still_read() -> None:
    summary = _believe(DRESSER, [0.0, 0.3, 0.44], [0.12, 0.06, 0.04])
    as_dict = summary.to_dict()
    assert json.loads(json.dumps(as_dict)) == as_dict
    assert PosteriorSummary.from_dict(as_dict) == summary
    older = {k: v for k, v in as_dict.items() if k not in ("structure", "mass_elsewhere")}
    read = PosteriorSummary.from_dict(older)
    assert read.structure == () and read.mass_elsewhere == 0.0 and read.objects == summary.objects
