"""Houses: rooms of one source joined into a multi-room (and sometimes two-storey) map, on the fixture rooms
of tests/resources/data."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from app.data.conventions import Convention, groundings
from app.data.houses import FLOOR_HEIGHT, HOUSE_MAX_ROOMS, draw_houses, join_rooms
from app.data.layouts import read_ai2thor, read_scannet, room_key
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph
from app.vocabulary import same_class

DATA = Path(__file__).parent / "resources" / "data"


@pytest.fixture(scope="module")
def scannet():
    return read_scannet(DATA / "scannet_scenes.jsonl")


@pytest.fixture(scope="module")
def thor():
    return read_ai2thor(DATA / "ai2thor_scenes.jsonl")


def _overlap(a, b) -> float:
    lo = np.maximum(np.subtract(a.center, np.divide(a.size, 2)), np.subtract(b.center, np.divide(b.size, 2)))
    hi = np.minimum(np.add(a.center, np.divide(a.size, 2)), np.add(b.center, np.divide(b.size, 2)))
    return float(np.prod(np.clip(hi - lo, 0.0, None)))


def _check_house(house, rooms) -> None:
    graph = SceneGraph(regions=house.regions, objects=house.objects)  # validates ids and region references
    assert [r.id for r in graph.regions] == [str(k) for k in range(len(rooms))]
    assert len(house.objects) == sum(len(r.objects) for r in rooms)
    for a, b in itertools.combinations(house.regions, 2):
        assert _overlap(a, b) < 1e-9, (a, b)  # side by side, touching at most
    for o in house.objects:
        region = graph.region(o.region_id)
        lo = np.subtract(region.center, np.divide(region.size, 2)) - 1e-3
        hi = np.add(region.center, np.divide(region.size, 2)) + 1e-3
        assert np.all(o.min_corner >= lo) and np.all(o.max_corner <= hi), o.id
        scene_id, original = house.origin[o.id]
        assert o.id == f"{o.region_id}:{original}" and scene_id == rooms[int(o.region_id)].scene_id
    for k, room in enumerate(rooms):
        size = next(r.size for r in house.regions if r.id == str(k))
        assert sorted(size[:2]) == pytest.approx(sorted(room.region.size[:2]), abs=1e-3)  # a quarter turn


def test_rooms_stand_side_by_side_without_overlaps_one_region_each(scannet):
    for seed in range(8):
        house = join_rooms(scannet, "house-test-0", np.random.default_rng(seed))
        _check_house(house, scannet)
        assert [r.name for r in house.regions] == ["room 1", "room 2", "room 3"]
        assert house.is_house and house.placements is None


def test_a_second_floor_stands_above_the_first_floors_rooms(scannet):
    floors = []
    for seed in range(40):
        house = join_rooms(scannet, "house-test-0", np.random.default_rng(seed))
        _check_house(house, scannet)
        floors.append(house.floors)
        if house.floors == 2:
            bottoms = sorted(r.center[2] - r.size[2] / 2 for r in house.regions)
            assert bottoms[0] == pytest.approx(0.0, abs=1e-6)
            upper = bottoms[-1]
            assert FLOOR_HEIGHT[0] <= upper <= FLOOR_HEIGHT[1]
            ground = [r for r in house.regions if r.center[2] - r.size[2] / 2 < 1.0]
            assert all(r.center[2] + r.size[2] / 2 < upper for r in ground)
    assert set(floors) == {1, 2}


def test_ai2thor_houses_keep_room_types_and_placements(thor):
    house = join_rooms(thor, "house-test-0", np.random.default_rng(0))
    _check_house(house, thor)
    assert sorted(r.name for r in house.regions) == ["bedroom", "kitchen"]
    ids = {o.id for o in house.objects}
    assert house.placements
    for target, anchors in house.placements.items():
        assert target in ids and set(anchors) <= ids
    assert house.portable <= ids and set(house.raw_labels) == ids
    apple = (
        "1:Apple|-00.74|+01.14|-01.55"
        if thor[1].scene_id == "kitchens_13"
        else "0:Apple|-00.74|+01.14|-01.55"
    )
    fridge = next(o.id for o in house.objects if o.label == "fridge")
    assert house.placements[apple] == {fridge: Relation.IN}
    with pytest.raises(ValueError, match="one source"):
        join_rooms(
            [thor[0], next(iter(read_scannet(DATA / "scannet_scenes.jsonl")))], "x", np.random.default_rng(0)
        )


def test_relations_of_a_house_reach_across_its_rooms(scannet):
    """A house of two copies of one room: every chair has look-alikes in the other room, and closest /
    farthest are decided among all of them."""
    twin = dataclasses.replace(scannet[0], scene_id="scene1089_00")
    house = join_rooms([scannet[0], twin], "house-test-0", np.random.default_rng(3))
    chairs = [o for o in house.objects if same_class(o.label, "chair")]
    assert {o.region_id for o in chairs} == {"0", "1"}
    checked = 0
    for target in chairs:
        others = [o for o in house.objects if o.id != target.id]
        rivals = [c for c in chairs if c.id != target.id]
        for grounding in groundings(Convention.VLMAP, target, others):
            if grounding.relation is not Relation.FARTHEST:
                continue
            anchor = next(o for o in others if o.id == grounding.anchor_ids[0])
            mine = np.linalg.norm(np.subtract(target.center, anchor.center))
            assert mine > max(np.linalg.norm(np.subtract(c.center, anchor.center)) for c in rivals)
            checked += 1
    assert checked  # farther than every chair of both rooms, for some chair and anchor


def test_draw_houses_takes_distinct_rooms_of_one_source_within_the_limits(scannet, thor):
    rescans = [dataclasses.replace(s, scene_id=s.scene_id[:-2] + "01") for s in scannet]
    extra = [dataclasses.replace(s, scene_id=f"{s.room_type}_{90 + k}") for k, s in enumerate(thor * 3)]
    apartment = dataclasses.replace(thor[0], scene_id="robothor_1", room_type="robothor")
    pool = scannet + rescans + thor + extra + [apartment]
    houses = draw_houses(pool, 60, np.random.default_rng(0))
    assert len(houses) == 60
    for rooms in houses:
        assert 2 <= len(rooms) <= HOUSE_MAX_ROOMS and len({r.source for r in rooms}) == 1
        keys = [room_key(r.source, r.scene_id) for r in rooms]
        assert len(set(keys)) == len(keys)  # never two scans of one room
        types = [r.room_type for r in rooms]
        assert "robothor" not in types
        assert types.count("kitchens") <= 1 and types.count("bedrooms") <= 3
    assert {rooms[0].source for rooms in houses} == {"scannet", "ai2thor"}
    assert draw_houses(pool, 60, np.random.default_rng(0)) == houses
    assert draw_houses(scannet[:1], 5, np.random.default_rng(0)) == []
