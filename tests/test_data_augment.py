"""Frames and reconstruction errors of shifted maps (`app.data.augment`), raw label vocabularies, and the
invariance of every convention's relations under the frame changes (fixture rooms of tests/resources/data)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from app.data.augment import (
    CALIB_SHIFT,
    TRAIN_SHIFT,
    BoxNoise,
    FrameMotion,
    observed_objects,
    random_motion,
    random_noise,
)
from app.data.conventions import Convention, groundings
from app.data.label_vocabularies import renamed_labels
from app.data.layouts import read_ai2thor, read_scannet
from app.grounding.box_relations import Box, is_on
from app.scene_graph.model import Region, SceneObject

DATA = Path(__file__).parent / "resources" / "data"


@pytest.fixture(scope="module")
def rooms():
    return read_scannet(DATA / "scannet_scenes.jsonl") + read_ai2thor(DATA / "ai2thor_scenes.jsonl")


def _moved(objects: list[SceneObject], motion: FrameMotion) -> list[SceneObject]:
    """The objects moved exactly (no rounding, no noise)."""
    centres, sizes, yaws = motion.boxes(
        np.array([o.center for o in objects]), np.array([o.size for o in objects]), np.zeros(len(objects))
    )
    return [
        o.model_copy(update={"center": c.tolist(), "size": s.tolist(), "yaw": float(w)})
        for o, c, s, w in zip(objects, centres, sizes, yaws, strict=True)
    ]


def _in_box_frame(objects: list[SceneObject]) -> list[SceneObject]:
    """A map whose boxes share one yaw, turned back by that yaw (read from the boxes themselves)."""
    (yaw,) = {round(o.yaw, 12) for o in objects}
    back = FrameMotion(-yaw, (0.0, 0.0, 0.0), yawed_boxes=True)
    centres = back.points(np.array([o.center for o in objects])).round(9)
    return [
        o.model_copy(update={"center": c.tolist(), "yaw": 0.0}) for o, c in zip(objects, centres, strict=True)
    ]


def _all_groundings(convention: Convention, objects: list[SceneObject], volume: float) -> set:
    out = set()
    for target in objects:
        others = [o for o in objects if o.id != target.id]
        out |= {(target.id, g) for g in groundings(convention, target, others, region_volume=volume)}
    return out


@pytest.mark.parametrize("convention", list(Convention))
def test_relations_are_invariant_under_the_frame_changes(rooms, convention):
    """Compute every target's relations on the original room and on the moved one: quarter turns, any
    offset and floor height leave boxes axis-aligned and every relation as it was; after a continuous yaw
    the yawed boxes, read in their own frame, give the same relations again."""
    for room in rooms:
        volume = float(np.prod(room.region.size))
        expected = _all_groundings(convention, room.objects, volume)
        assert expected
        for quarter in range(4):
            motion = FrameMotion(0.5 * math.pi * quarter, (12.5, -7.25, 3.5), yawed_boxes=False)
            assert _all_groundings(convention, _moved(room.objects, motion), volume) == expected
        turned = _moved(room.objects, FrameMotion(0.7, (3.1, -2.2, -1.5), yawed_boxes=True))
        assert _all_groundings(convention, _in_box_frame(turned), volume) == expected


def test_frame_motion_keeps_yawed_boxes_or_writes_their_bounding_box():
    table = SceneObject(id="t", label="table", center=[1.0, 0.0, 0.4], size=[1.2, 0.6, 0.8])
    mug = SceneObject(id="m", label="mug", center=[1.2, 0.1, 0.85], size=[0.1, 0.1, 0.1])
    for yawed in (True, False):
        motion = FrameMotion(math.radians(30), (1.0, 2.0, 3.0), yawed_boxes=yawed)
        moved_table, moved_mug = _moved([table, mug], motion)
        gap = np.linalg.norm(np.subtract(moved_mug.center, moved_table.center))
        assert gap == pytest.approx(np.linalg.norm(np.subtract(mug.center, table.center)))
        assert moved_table.center[2] == pytest.approx(3.4)
        c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
        aabb = [c * 1.2 + s * 0.6, s * 1.2 + c * 0.6, 0.8]
        if yawed:
            assert moved_table.size == [1.2, 0.6, 0.8] and moved_table.yaw == pytest.approx(math.radians(30))
            assert (2 * moved_table.half_extent).tolist() == pytest.approx(aabb)
        else:
            assert moved_table.size == pytest.approx(aabb) and moved_table.yaw == 0.0
    quarter = FrameMotion(0.5 * math.pi, (2.0, -1.0, 0.0), yawed_boxes=True)
    assert quarter.quarter_turns == 1
    (turned,) = _moved([table], quarter)
    assert turned.center == [2.0, 0.0, 0.4] and turned.size == [0.6, 1.2, 0.8] and turned.yaw == 0.0
    assert is_on(Box.of(_moved([mug], quarter)[0]), Box.of(turned))
    region = Region(id="0", name="room", center=[0.0, 0.0, 1.0], size=[4.0, 2.0, 2.0])
    moved_region = FrameMotion(math.radians(30), (0.0, 0.0, 0.0), yawed_boxes=True).region(region)
    assert moved_region.size == pytest.approx([c * 4 + s * 2, s * 4 + c * 2, 2.0], abs=1e-4)


def test_box_noise_and_missing_objects_stay_within_their_bounds(rooms):
    room = rooms[0]
    rng = np.random.default_rng(5)
    for shift in (TRAIN_SHIFT, CALIB_SHIFT):
        for _ in range(20):
            noise = random_noise(shift, rng)
            assert shift.center_jitter[0] <= noise.center_jitter <= shift.center_jitter[1]
            assert shift.size_noise[0] <= noise.size_noise <= shift.size_noise[1]
            keep = frozenset(o.id for o in room.objects[:3])
            objects, dropped = observed_objects(
                room.objects,
                motion=FrameMotion(0.0, (0.0, 0.0, 0.0), yawed_boxes=False),
                noise=noise,
                drop_fraction=0.2,
                keep=keep,
                labels={},
                rng=rng,
            )
            assert dropped == math.floor(0.2 * (len(room.objects) - 3)) == len(room.objects) - len(objects)
            assert keep <= {o.id for o in objects}
            by_id = {o.id: o for o in room.objects}
            for o in objects:
                source = by_id[o.id]
                assert np.all(np.abs(np.subtract(o.center, source.center)) <= noise.center_jitter + 1e-4)
                ratio = np.divide(o.size, source.size)
                assert np.all(ratio >= 1 - noise.size_noise - 1e-3) and np.all(
                    ratio <= 1 + noise.size_noise + 1e-3
                )
    same = BoxNoise(0.05, 0.1).apply(np.zeros((4, 3)), np.ones((4, 3)), np.random.default_rng(1))
    again = BoxNoise(0.05, 0.1).apply(np.zeros((4, 3)), np.ones((4, 3)), np.random.default_rng(1))
    assert all(np.array_equal(a, b) for a, b in zip(same, again, strict=True))


def test_random_frames_cover_yaws_offsets_and_floor_heights():
    rng = np.random.default_rng(0)
    motions = [random_motion(TRAIN_SHIFT, rng) for _ in range(400)]
    continuous = [m for m in motions if m.quarter_turns is None]
    assert 0.4 < len(continuous) / len(motions) < 0.8
    assert {m.quarter_turns for m in motions if m.quarter_turns is not None} == {0, 1, 2, 3}
    assert min(m.offset[2] for m in motions) < -1.0 and max(m.offset[2] for m in motions) > 4.0
    assert max(abs(m.offset[0]) for m in motions) > 10.0
    assert {m.yawed_boxes for m in continuous} == {True, False}
    assert all(random_motion(CALIB_SHIFT, rng).quarter_turns is None for _ in range(50))


def test_raw_label_vocabularies(rooms):
    scannet = rooms[0]
    labels = {o.id: o.label for o in scannet.objects}
    renamed = renamed_labels("scannet", labels, scannet.raw_labels)
    assert {labels[i]: v for i, v in renamed.items()} == {"trash can": "garbage bin", "doorframe": "door"}
    kitchen = next(r for r in rooms if r.scene_id == "kitchens_13")
    thor = renamed_labels("ai2thor", {o.id: o.label for o in kitchen.objects}, kitchen.raw_labels)
    counter = next(o.id for o in kitchen.objects if o.label == "countertop")
    assert thor[counter] == "CounterTop" and next(o.id for o in kitchen.objects if o.label == "mug") in thor
