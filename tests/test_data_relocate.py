"""Relocated targets (`app.data.relocate`): where a moved target may rest, and the builder's use of it
(train targets only, relations recomputed from the boxes at the new place)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from app.data.build import BuildConfig, build_cases, read_ai2thor, read_scannet
from app.data.conventions import Convention, holds
from app.data.houses import room_map
from app.data.layouts import PORTABLE_MAX_SIDE
from app.data.relocate import MAX_OVERLAP, SUPPORT_MAX_HEIGHT, floor_height, relocated
from app.grounding.box_relations import FLOOR_CEILING, Box, TrueReading, volume_overlap
from app.scene_graph.model import Region, SceneObject
from app.vocabulary import in_classes

DATA = Path(__file__).parent / "resources" / "data"


@pytest.fixture(scope="module")
def layouts():
    return [
        room_map(s)
        for s in read_scannet(DATA / "scannet_scenes.jsonl") + read_ai2thor(DATA / "ai2thor_scenes.jsonl")
    ]


def obj(id_: str, label: str, center: list[float], size: list[float]) -> SceneObject:
    return SceneObject(id=id_, label=label, center=center, size=size, region_id="0")


ROOM = Region(id="0", name="room", center=[2.0, 2.0, 1.5], size=[4.0, 4.0, 3.0])


def test_a_moved_target_rests_on_the_floor_or_on_a_top_inside_its_region_and_inside_nothing(layouts):
    rng = np.random.default_rng(0)
    on_floor = on_top = 0
    for layout in layouts:
        region = layout.regions[0]
        # Only portable targets move: each is put down three times, at three places drawn.
        for target in [o for o in layout.objects for _ in range(3)]:
            others = [o for o in layout.objects if o.id != target.id]
            moved = relocated(target, others, region, rng)
            if moved is None:
                continue
            assert (moved.label, moved.size, moved.id) == (target.label, target.size, target.id)
            low, high = moved.min_corner, moved.max_corner
            floor = floor_height(others)
            solid = [o for o in others if not in_classes(o.label, FLOOR_CEILING)]
            tops = [o for o in solid if abs(float(o.max_corner[2]) - float(low[2])) < 1e-9]
            if abs(float(low[2]) - floor) < 1e-9:
                on_floor += 1
                region_lo = np.asarray(region.center) - np.asarray(region.size) / 2
                region_hi = np.asarray(region.center) + np.asarray(region.size) / 2
                assert np.all(low[:2] >= region_lo[:2] - 1e-9) and np.all(high[:2] <= region_hi[:2] + 1e-9)
                supports: list[SceneObject] = []
            else:
                on_top += 1
                supports = [
                    o
                    for o in tops
                    if np.all(low[:2] >= o.min_corner[:2] - 1e-9)
                    and np.all(high[:2] <= o.max_corner[:2] + 1e-9)
                ]
                assert supports, "a target off the floor rests on a top that holds its whole footprint"
                assert min(float(o.max_corner[2]) for o in supports) - floor <= SUPPORT_MAX_HEIGHT + 1e-9
            # Inside no other box (the support it rests on may touch it).
            for o in solid:
                if o in supports:
                    continue
                share = float(volume_overlap(Box.of(moved), Box.of(o)) / np.prod(high - low))
                assert share <= MAX_OVERLAP + 1e-9, (layout.map_id, target.label, o.label)
    assert on_floor > 20 and on_top > 20


def test_the_floor_is_the_lowest_furniture_bottom_not_the_floor_slab():
    objects = [
        obj("f", "floor", [2, 2, -0.05], [4, 4, 0.1]),
        obj("t", "table", [1, 1, 0.4], [1, 1, 0.8]),
        obj("c", "chair", [3, 3, 0.45], [0.5, 0.5, 0.9]),
    ]
    assert floor_height(objects) == pytest.approx(0.0)


def test_a_mug_goes_on_the_table_top_or_the_floor_and_never_on_the_wardrobe():
    mug = obj("m", "mug", [0.5, 0.5, 1.0], [0.1, 0.1, 0.12])
    others = [
        obj("t", "table", [1.0, 1.0, 0.4], [1.0, 1.0, 0.8]),
        obj("w", "wardrobe", [3.5, 3.5, 1.1], [0.8, 0.8, 2.2]),
    ]
    rng = np.random.default_rng(1)
    heights = set()
    for _ in range(200):
        moved = relocated(mug, others, ROOM, rng)
        assert moved is not None
        heights.add(round(float(moved.min_corner[2]), 6))
        if moved.min_corner[2] > 0.5:
            assert np.all(moved.min_corner[:2] >= 0.5) and np.all(moved.max_corner[:2] <= 1.5)
    assert heights == {0.0, 0.8}  # the wardrobe's top (2.2 m) is too high to leave a mug on


def test_windows_doors_and_fixtures_hold_nothing_and_doors_are_not_put_down():
    """Their boxes have tops, but a keyboard on a door or a chair on a window is no place a person uses."""
    mug = obj("m", "mug", [0.5, 0.5, 1.0], [0.1, 0.1, 0.12])
    fixtures = [
        obj("w", "window", [2.0, 3.9, 1.2], [1.2, 0.3, 1.2]),
        obj("d", "door", [3.9, 2.0, 1.0], [0.3, 0.9, 2.0]),
        obj("f", "faucet", [1.0, 3.8, 0.9], [0.3, 0.3, 0.2]),
        obj("p", "bathroom stall", [0.3, 3.0, 1.0], [0.3, 1.5, 2.0]),
    ]
    rng = np.random.default_rng(2)
    for _ in range(100):
        moved = relocated(mug, fixtures, ROOM, rng)
        assert moved is not None and moved.min_corner[2] == pytest.approx(0.0)  # the floor only
    door = obj("x", "door", [1.0, 1.0, 1.0], [0.9, 0.1, 2.0])
    assert relocated(door, [obj("t", "table", [1.0, 1.0, 0.4], [1.0, 1.0, 0.8])], ROOM, rng) is None


def test_no_place_is_found_for_a_target_wider_than_its_room():
    sofa = obj("s", "sofa", [1, 1, 0.4], [5.0, 1.0, 0.8])
    others = [obj("t", "table", [1.0, 1.0, 0.4], [1.0, 1.0, 0.8])]
    assert relocated(sofa, others, ROOM, np.random.default_rng(0)) is None


CONFIG = BuildConfig(seed=3, augment=1, max_cases_per_scene=30, unseen_fraction=0.3, calib_fraction=0.3)


@pytest.fixture(scope="module")
def scenes():
    return read_scannet(DATA / "scannet_scenes.jsonl") + read_ai2thor(DATA / "ai2thor_scenes.jsonl")


def test_only_train_targets_move_and_their_relations_hold_where_they_now_rest(scenes):
    plain = list(build_cases(scenes, CONFIG))
    moved = list(build_cases(scenes, dataclasses.replace(CONFIG, relocate_fraction=1.0)))
    assert not any(c.meta["relocated"] for _, c in plain)
    # Held-out targets stay where their source put them, in the same rooms.
    for split in ("val_seen", "val_unseen", "calib"):
        held = [c for s, c in moved if s == split]
        assert held and not any(c.meta["relocated"] for c in held)
        assert {c.meta["scene_id"] for c in held} == {c.meta["scene_id"] for s, c in plain if s == split}
    train = [c for s, c in moved if s == "train"]
    relocated_cases = [c for c in train if c.meta["relocated"]]
    # Every target a person puts down (no side over PORTABLE_MAX_SIDE) moves; a door or a table stays.
    movable = [c for c in train if c.target.size is None or max(c.target.size) <= PORTABLE_MAX_SIDE]
    assert len(relocated_cases) > 0.7 * len(movable) > 0  # a crowded room may have no place left
    assert all(max(c.target.size or [0.0]) <= PORTABLE_MAX_SIDE for c in relocated_cases)
    originals = {
        (c.meta["scene_id"], c.meta["target_id"]): c.target.position for s, c in plain if s == "train"
    }
    changed = 0
    for case in relocated_cases:
        key = (case.meta["scene_id"], case.meta["target_id"])
        changed += key in originals and originals[key] != case.target.position
        if case.meta["augmentation"] != 0:
            continue
        hyp = case.hypotheses[0]
        target = SceneObject(
            id="__t__", label=case.target.label, center=case.target.position, size=case.target.size
        )
        volume = float(np.prod(case.scene_graph.region(case.meta["target_region_id"]).size))
        reading = TrueReading(hyp.relation, tuple(hyp.anchor_ids))
        # AI2-THOR's on/in too come from the boxes once the target has left its receptacle.
        assert holds(Convention(case.meta["convention"]), reading, target, case.scene_graph.objects, volume)
    # The builder balances relations over the build, so some moved targets have no plain twin to compare.
    assert changed > 0.7 * len(relocated_cases)
