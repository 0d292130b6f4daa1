"""Grounding cases from layouts (ScanNet scans, AI2-THOR rooms, synthetic rooms), relations from their boxes.

The builder turns layouts (`app.data.layouts`) into maps: every room alone, and houses of several rooms of
one source (`app.data.houses`). For every map it picks target objects, removes each target from the scene
graph (and nothing else), lists the target's true relations to the remaining objects by one relation
convention (`app.data.conventions`: vlmap, Sr3D or VLA-3D, drawn per target; Sr3D only for targets it would
refer to), and emits a bounded number of (target, relation, anchor(s)) cases with an utterance in that
convention's style (`app.data.templates`). Targets are any object but the room's shell (doors, windows and
tables as well as mugs), less the fragments of their class (`fragment_ids`).

With `relocate_fraction` > 0 a share of the train targets is first moved to another resting place of its
room (`app.data.relocate`), so that where a target rests follows no one source's habits.

Relations are computed once per target, over the whole map, from the clean boxes in the layout's frame.
A case's map may then be shown moved (any yaw, offset and floor height), with box noise, missing objects
and another dataset's raw labels (`app.data.augment`, `app.data.label_vocabularies`): the relations stay
those of the clean layout, which a rigid motion leaves true and a reconstruction's errors do not change.

Splits, by whole rooms (ScanNet rescans "sceneXXXX_YY" of one room XXXX stay together), per source:

* `val_unseen`: a seeded ~`unseen_fraction` of the rooms, never trained on; single rooms, canonical frame.
* `calib`: a further seeded ~`calib_fraction` of the rooms, in neither train nor val_unseen, built with the
  shifted settings (`CALIB_SHIFT`: continuous yaw, heavier noise, raw labels more often; houses of calib
  rooms; all conventions), for checkpoint selection and post-hoc calibration.
* `val_seen`: held-out targets (~`val_seen_fraction`) of the training rooms, canonical frame.
* `train`: the other targets of the training rooms, alone and in houses; each case in the canonical frame
  (augmentation 0) and `augment` times more as a shifted map (`TRAIN_SHIFT`, augmentation 1..K).

`meta["source"]` stays the layout's source, so leave-one-source-out training can filter on it.
"""

from __future__ import annotations

import json
import zlib
from collections import Counter, defaultdict
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.data.augment import (
    CALIB_SHIFT,
    IDENTITY,
    NO_NOISE,
    TRAIN_SHIFT,
    FrameMotion,
    Shift,
    observed_objects,
    random_motion,
    random_noise,
    without_noise,
    without_raw_labels,
    without_yaw,
)
from app.data.cases import CaseHypothesis, CaseTarget, GroundingCase
from app.data.conventions import Convention, groundings, sr3d_context_ok, sr3d_in_center, sr3d_next_to
from app.data.houses import MapLayout, draw_houses, join_rooms, room_map
from app.data.label_vocabularies import NATIVE, renamed_labels, vocabulary_of
from app.data.layouts import (
    LayoutScene,
    is_grounding_target,
    is_target_candidate,
    read_ai2thor,
    read_scannet,
    read_synthetic,
    room_key,
    split_camel_case,
    thor_placement_relation,
)
from app.data.relocate import relocated
from app.data.templates import render_sr3d, render_utterance, render_vla3d
from app.errors import InvalidInput
from app.files import atomic_write
from app.grounding.box_relations import TrueReading
from app.grounding.relations import Relation
from app.scene_graph.model import Region, SceneGraph, SceneObject

__all__ = [
    "SOURCES",
    "SPLITS",
    "BuildConfig",
    "BuildSummary",
    "LayoutScene",
    "build_cases",
    "calib_rooms",
    "fragment_ids",
    "is_grounding_target",
    "is_target_candidate",
    "read_ai2thor",
    "read_scannet",
    "read_synthetic",
    "room_key",
    "split_camel_case",
    "thor_placement_relation",
    "unseen_rooms",
    "write_build",
]

SPLITS = ("train", "val_seen", "val_unseen", "calib")
SOURCES = ("scannet", "ai2thor", "synthetic")

# Targets whose box volume is below this fraction of their label's median volume are fragments (see
# `fragment_ids`); the median needs at least FRAGMENT_MIN_COUNT instances of the label.
FRAGMENT_VOLUME_RATIO = 0.2
FRAGMENT_MIN_COUNT = 10
# Targets whose relations are computed per map (a seeded draw): enough for the per-map cap on cases, and
# a bound on the cost of a house's hundreds of objects.
MAX_EVALUATED_TARGETS = 80
# How often each convention is drawn for a target it applies to.
CONVENTION_WEIGHTS = {Convention.VLMAP: 0.4, Convention.SR3D: 0.3, Convention.VLA3D: 0.3}


def _stable_seed(seed: int, *parts: str) -> list[int]:
    return [seed, *(zlib.crc32(p.encode("utf-8")) for p in parts)]


def _rooms_by_source(scenes: Iterable[LayoutScene]) -> dict[str, list[str]]:
    by_source: dict[str, set[str]] = defaultdict(set)
    for s in scenes:
        by_source[s.source].add(room_key(s.source, s.scene_id))
    return {source: sorted(keys) for source, keys in sorted(by_source.items())}


def _check_fraction(fraction: float, name: str) -> None:
    if not 0.0 <= fraction <= 1.0:
        msg = f"{name.replace('_', ' ')} must lie in [0, 1], got {fraction}"
        raise InvalidInput(msg, name)


def unseen_rooms(scenes: Iterable[LayoutScene], fraction: float, seed: int) -> set[str]:
    """Room keys held out as `val_unseen`: per source, round(fraction * rooms) of them, drawn by the seed."""
    _check_fraction(fraction, "unseen_fraction")
    chosen: set[str] = set()
    for source, ordered in _rooms_by_source(scenes).items():
        rng = np.random.default_rng(_stable_seed(seed, "unseen", source))
        n = round(fraction * len(ordered))
        chosen.update(ordered[i] for i in rng.permutation(len(ordered))[:n])
    return chosen


def calib_rooms(scenes: Iterable[LayoutScene], fraction: float, seed: int, exclude: set[str]) -> set[str]:
    """Room keys of the `calib` split: per source, round(fraction * rooms) of the rooms not in `exclude`."""
    _check_fraction(fraction, "calib_fraction")
    chosen: set[str] = set()
    for source, ordered in _rooms_by_source(scenes).items():
        free = [k for k in ordered if k not in exclude]
        rng = np.random.default_rng(_stable_seed(seed, "calib", source))
        n = min(round(fraction * len(ordered)), len(free))
        chosen.update(free[i] for i in rng.permutation(len(free))[:n])
    return chosen


@dataclass(frozen=True)
class BuildConfig:
    seed: int = 0
    augment: int = 3
    max_cases_per_scene: int = 40
    cases_per_target: int = 3
    unseen_fraction: float = 0.15
    val_seen_fraction: float = 0.1
    calib_fraction: float = 0.1
    conventions: tuple[Convention, ...] = tuple(Convention)
    # Houses per room of a split's pool (train, calib); 0: no houses.
    house_fraction: float = 0.6
    continuous_yaw: bool = True
    box_noise: bool = True
    raw_labels: bool = True
    # Targets of every size (`is_grounding_target`), or only small and medium movable ones.
    all_targets: bool = True
    # Share of the train targets moved to another resting place of their region first (`app.data.relocate`).
    relocate_fraction: float = 0.0

    def __post_init__(self) -> None:
        # Checked here, not where the fractions are first used: `write_build` would by then have begun to
        # replace the previous build's files.
        for name in ("unseen_fraction", "val_seen_fraction", "calib_fraction", "relocate_fraction"):
            _check_fraction(getattr(self, name), name)

    def shift(self, split: str) -> Shift | None:
        """How the split's shifted maps are drawn; None for the canonical frame only."""
        base = {"train": TRAIN_SHIFT, "calib": CALIB_SHIFT}.get(split)
        if base is None:
            return None
        if not self.continuous_yaw:
            base = without_yaw(base)
        if not self.box_noise:
            base = without_noise(base)
        if not self.raw_labels:
            base = without_raw_labels(base)
        return base


def _nested_counter() -> defaultdict[str, defaultdict[str, Counter[str]]]:
    return defaultdict(lambda: defaultdict(Counter))


@dataclass
class BuildSummary:
    """What the builder wrote: counts per split x source x relation (and x convention), ambiguity histogram,
    maps, skip notes."""

    counts: dict[str, dict[str, Counter[str]]] = field(
        default_factory=lambda: {s: {src: Counter() for src in SOURCES} for s in SPLITS}
    )
    by_convention: dict[str, defaultdict[str, defaultdict[str, Counter[str]]]] = field(
        default_factory=lambda: {s: _nested_counter() for s in SPLITS}
    )
    ambiguity: dict[str, Counter[int]] = field(default_factory=lambda: {s: Counter() for s in SPLITS})
    scenes: dict[str, Counter[str]] = field(default_factory=lambda: {s: Counter() for s in SPLITS})
    maps: dict[str, Counter[str]] = field(default_factory=lambda: {s: Counter() for s in SPLITS})
    notes: Counter[str] = field(default_factory=Counter)

    def total(self, split: str) -> int:
        return sum(sum(c.values()) for c in self.counts[split].values())

    def relation_totals(self) -> Counter[str]:
        out: Counter[str] = Counter()
        for split in SPLITS:
            for c in self.counts[split].values():
                out.update(c)
        return out

    def add(self, split: str, case: GroundingCase) -> None:
        source = case.meta["source"]
        relation = case.hypotheses[0].relation.value if case.hypotheses else "none"
        self.counts[split][source][relation] += 1
        self.by_convention[split][source][case.meta["convention"]][relation] += 1
        self.ambiguity[split][int(case.meta["ambiguity"])] += 1

    def to_json(self) -> dict[str, Any]:
        return {
            "cases": {s: self.total(s) for s in SPLITS},
            "counts": {
                s: {src: dict(sorted(c.items())) for src, c in by_src.items()}
                for s, by_src in self.counts.items()
            },
            "counts_by_convention": {
                s: {
                    src: {conv: dict(sorted(c.items())) for conv, c in sorted(by_conv.items())}
                    for src, by_conv in sorted(by_src.items())
                }
                for s, by_src in self.by_convention.items()
            },
            "ambiguity_histogram": {
                s: {str(k): v for k, v in sorted(c.items())} for s, c in self.ambiguity.items()
            },
            "scenes": {s: dict(sorted(c.items())) for s, c in self.scenes.items()},
            "maps": {s: dict(c) for s, c in self.maps.items()},
            "notes": dict(sorted(self.notes.items())),
        }


def _ambiguity(anchor_ids: Sequence[str], objects: Sequence[SceneObject]) -> int:
    labels = Counter(o.label for o in objects)
    by_id = {o.id: o.label for o in objects}
    return max(labels[by_id[a]] for a in anchor_ids)


class _Balancer:
    """Chooses which relations a target contributes: the least-emitted ones so far, ties broken at random."""

    def __init__(self) -> None:
        self.emitted: Counter[Relation] = Counter()

    def choose(self, available: Iterable[Relation], k: int, rng: np.random.Generator) -> list[Relation]:
        options = list(available)
        keys = rng.random(len(options))
        order = sorted(range(len(options)), key=lambda i: (self.emitted[options[i]], keys[i]))
        picked = [options[i] for i in order[:k]]
        self.emitted.update(picked)
        return picked


@dataclass
class _Candidate:
    target: SceneObject
    split: str
    convention: Convention
    others: list[SceneObject]
    by_relation: dict[Relation, list[TrueReading]]
    relocated: bool = False


def _draw_convention(
    target: SceneObject, others: Sequence[SceneObject], config: BuildConfig, rng: np.random.Generator
) -> Convention | None:
    """A convention for the target, by CONVENTION_WEIGHTS over those that would refer to it."""
    options = [c for c in config.conventions if c is not Convention.SR3D or sr3d_context_ok(target, others)]
    if not options:
        return None
    weights = np.array([CONVENTION_WEIGHTS[c] for c in options])
    return options[int(rng.choice(len(options), p=weights / weights.sum()))]


def _utterance(
    convention: Convention,
    relation: Relation,
    target: SceneObject,
    anchors: Sequence[SceneObject],
    others: Sequence[SceneObject],
    portable: bool,
    rng: np.random.Generator,
) -> str:
    labels = tuple(a.label for a in anchors)
    if convention is Convention.SR3D:
        next_to = relation is Relation.CLOSEST and sr3d_next_to(target, anchors[0], others)
        in_center = relation is Relation.BETWEEN and sr3d_in_center(target, anchors[0], anchors[1])
        return render_sr3d(relation, target.label, labels, rng, next_to=next_to, in_center=in_center)
    if convention is Convention.VLA3D:
        return render_vla3d(relation, target.label, labels, rng)
    return render_utterance(relation, target.label, labels, rng, portable=portable)


def _target_box(target: SceneObject, motion: FrameMotion) -> SceneObject:
    """The target's (noise-free) box in the moved frame."""
    centre, size, yaw = motion.boxes(
        np.array([target.center]), np.array([target.size]), np.array([target.yaw])
    )
    return target.model_copy(
        update={"center": centre[0].tolist(), "size": size[0].tolist(), "yaw": float(yaw[0])}
    )


def _case(
    layout: MapLayout,
    candidate: _Candidate,
    grounding: TrueReading,
    utterance: str,
    augmentation: int,
    shift: Shift | None,
    renamed: Mapping[str, str],
    rng: np.random.Generator,
) -> GroundingCase:
    """The case of one grounding: in the canonical frame (`shift` None) or on a map drawn from the shift."""
    target = candidate.target
    vocabulary = NATIVE
    labels: Mapping[str, str] = {}
    if shift is None:
        motion, noise, drop = IDENTITY, NO_NOISE, 0.0
        objects, dropped = candidate.others, 0
        regions = layout.regions
    else:
        motion, noise = random_motion(shift, rng), random_noise(shift, rng)
        drop = float(rng.uniform(*shift.drop_fraction))
        if renamed and rng.random() < shift.raw_label_probability:
            labels = renamed
            vocabulary = vocabulary_of(layout.source)
        objects, dropped = observed_objects(
            candidate.others,
            motion=motion,
            noise=noise,
            drop_fraction=drop,
            keep=frozenset(grounding.anchor_ids),
            labels=labels,
            rng=rng,
        )
        regions = [motion.region(r) for r in layout.regions]
    moved = _target_box(target, motion)
    relation = grounding.relation
    anchors = "+".join(grounding.anchor_ids)
    case_id = "/".join(
        (layout.source, layout.map_id, target.id, candidate.convention.value, relation.value, anchors)
    )
    return GroundingCase(
        case_id=case_id if augmentation == 0 else f"{case_id}/aug{augmentation}",
        scene_graph=SceneGraph(regions=regions, objects=objects),
        utterance=utterance,
        target=CaseTarget(
            label=labels.get(target.id, target.label),
            position=moved.center,
            size=(2.0 * moved.half_extent).tolist(),
        ),
        hypotheses=[CaseHypothesis(anchor_ids=list(grounding.anchor_ids), relation=relation)],
        meta={
            "source": layout.source,
            "scene_id": layout.map_id,
            "target_id": target.id,
            "ambiguity": _ambiguity(grounding.anchor_ids, objects),
            "augmentation": augmentation,
            "convention": candidate.convention.value,
            "relocated": candidate.relocated,
            "scene_ids": list(layout.scene_ids),
            "rooms": len(layout.scene_ids),
            "floors": layout.floors,
            "target_region_id": target.region_id,
            "target_name": target.label,
            "target_box": {"center": moved.center, "size": moved.size, "yaw": moved.yaw},
            "frame": motion.to_json(),
            "noise": {**noise.to_json(), "drop_fraction": round(drop, 4), "dropped": dropped},
            "label_vocabulary": vocabulary,
        },
    )


def _moved(
    target: SceneObject,
    split: str,
    others: Sequence[SceneObject],
    region: Region | None,
    fraction: float,
    rng: np.random.Generator,
    notes: Counter[str],
) -> SceneObject | None:
    """A train target, drawn with probability `fraction`, at another resting place of its region
    (`relocated`); None for every other target and where no place is found."""
    if split != "train" or rng.random() >= fraction:
        return None
    moved = relocated(target, others, region, rng)
    notes["targets_relocated" if moved is not None else "targets_without_a_place_to_move_to"] += 1
    return moved


def _map_cases(
    layout: MapLayout,
    split_of_target: Mapping[str, str],
    config: BuildConfig,
    balancers: Mapping[Convention, _Balancer],
    notes: Counter[str],
) -> Iterator[tuple[str, GroundingCase]]:
    """(split, case) pairs of one map, up to `max_cases_per_scene` groundings; train ones also `augment`
    times on shifted maps, calib ones only on a shifted map.

    Targets whose available relations are the rarest so far (in their convention) go first, so the cap cuts
    the common ones.
    """
    rng = np.random.default_rng(_stable_seed(config.seed, "map", layout.source, layout.map_id))
    # Its own stream, so that relocating leaves every other draw of the map as it was.
    moves = np.random.default_rng(_stable_seed(config.seed, "relocate", layout.source, layout.map_id))
    by_id = {o.id: o for o in layout.objects}
    volumes = {r.id: float(np.prod(r.size)) for r in layout.regions}
    regions = {r.id: r for r in layout.regions}
    candidates = []
    for target_id in list(split_of_target)[:MAX_EVALUATED_TARGETS]:
        target = by_id[target_id]
        others = [o for o in layout.objects if o.id != target_id]
        placements = None if layout.placements is None else layout.placements.get(target_id, {})
        region = regions.get(target.region_id or "")
        moved = _moved(
            target, split_of_target[target_id], others, region, config.relocate_fraction, moves, notes
        )
        if moved is not None:
            # The source's placements are where it stood; on/in now come from the boxes.
            target, placements = moved, None
        convention = _draw_convention(target, others, config, rng)
        if convention is None:
            notes["targets_outside_every_convention"] += 1
            continue
        by_relation: dict[Relation, list[TrueReading]] = defaultdict(list)
        found = groundings(
            convention,
            target,
            others,
            placements=placements,
            region_volume=volumes.get(target.region_id or ""),
        )
        for g in found:
            by_relation[g.relation].append(g)
        if not by_relation:
            notes[f"targets_without_relation_{convention.value}"] += 1
            continue
        candidates.append(
            _Candidate(target, split_of_target[target_id], convention, others, by_relation, moved is not None)
        )
    # A stable sort keeps the shuffled order among equally rare targets.
    candidates.sort(key=lambda c: min(balancers[c.convention].emitted[r] for r in c.by_relation))
    renamed = renamed_labels(layout.source, {o.id: o.label for o in layout.objects}, layout.raw_labels)
    emitted = 0
    for candidate in candidates:
        budget = min(config.cases_per_target, config.max_cases_per_scene - emitted)
        if budget <= 0:
            break
        target, split = candidate.target, candidate.split
        for relation in balancers[candidate.convention].choose(candidate.by_relation, budget, rng):
            options = candidate.by_relation[relation]
            chosen = options[int(rng.integers(len(options)))]
            anchors = [by_id[a] for a in chosen.anchor_ids]
            portable = target.id in layout.portable
            utterance = _utterance(
                candidate.convention, relation, target, anchors, candidate.others, portable, rng
            )
            emitted += 1
            shift = config.shift(split)
            if split == "calib" and shift is not None:
                yield split, _case(layout, candidate, chosen, utterance, 0, shift, renamed, rng)
                continue
            yield split, _case(layout, candidate, chosen, utterance, 0, None, renamed, rng)
            if split == "train" and shift is not None:
                for index in range(1, config.augment + 1):
                    yield split, _case(layout, candidate, chosen, utterance, index, shift, renamed, rng)


def fragment_ids(scenes: Sequence[LayoutScene]) -> set[tuple[str, str, str]]:
    """(source, scene id, object id) of objects that are fragments of their class: box volume below
    FRAGMENT_VOLUME_RATIO x the median volume of the label in that source (labels with >= FRAGMENT_MIN_COUNT
    instances). ScanNet has partly segmented instances (a 30 cm "chair" floating at 1.2 m, its back seen over
    a table) whose centre is not where the object is; they are never targets."""
    volumes: dict[tuple[str, str], list[float]] = defaultdict(list)
    for scene in scenes:
        for o in scene.objects:
            volumes[scene.source, o.label].append(float(np.prod(o.size)))
    medians = {k: float(np.median(v)) for k, v in volumes.items() if len(v) >= FRAGMENT_MIN_COUNT}
    out = set()
    for scene in scenes:
        for o in scene.objects:
            median = medians.get((scene.source, o.label))
            if median is not None and float(np.prod(o.size)) < FRAGMENT_VOLUME_RATIO * median:
                out.add((scene.source, scene.scene_id, o.id))
    return out


def _assign_targets(scene: LayoutScene, room_split: str, config: BuildConfig) -> dict[str, str]:
    """Target id -> split, in the (seeded, shuffled) order targets are used. `room_split` is "train" for a
    training room (whose held-out targets go to val_seen), else the room's split."""
    rng = np.random.default_rng(_stable_seed(config.seed, "targets", scene.source, scene.scene_id))
    if config.all_targets:
        targets = [o.id for o in scene.objects if is_grounding_target(o.label)]
    else:
        targets = list(scene.targets)
    order = [targets[i] for i in rng.permutation(len(targets))]
    if room_split != "train":
        return dict.fromkeys(order, room_split)
    held = round(config.val_seen_fraction * len(order))
    return {t: ("val_seen" if k < held else "train") for k, t in enumerate(order)}


def _house_targets(
    house: MapLayout, split: str, splits: Mapping[tuple[str, str], str], rng: np.random.Generator
) -> dict[str, str]:
    """House object id -> split for the rooms' targets of `split`, in a seeded order."""
    ids = [i for i, origin in house.origin.items() if splits.get(origin) == split]
    return {ids[k]: split for k in rng.permutation(len(ids)).tolist()}


def build_cases(
    scenes: Sequence[LayoutScene],
    config: BuildConfig,
    progress: bool = False,
    notes: Counter[str] | None = None,
    maps: Mapping[str, Counter[str]] | None = None,
) -> Iterator[tuple[str, GroundingCase]]:
    """All (split, case) pairs: rooms in (source, scene id) order, then the train houses, then the calib
    houses; deterministic for a seed.

    `notes` (if given) counts what was skipped: scene-reading notes, fragments, targets without any true
    relation; `maps` (if given) counts the rooms and houses built per split.
    """
    notes = Counter() if notes is None else notes
    unseen = unseen_rooms(scenes, config.unseen_fraction, config.seed)
    calib = calib_rooms(scenes, config.calib_fraction, config.seed, unseen)
    fragments = fragment_ids(scenes)
    ordered = sorted(scenes, key=lambda s: (s.source, s.scene_id))
    room_splits: dict[str, str] = {}
    target_splits: dict[tuple[str, str], str] = {}
    plans: list[tuple[str, MapLayout | list[LayoutScene], dict[str, str] | None]] = []
    for scene in ordered:
        notes.update(scene.notes)
        key = room_key(scene.source, scene.scene_id)
        room_split = "val_unseen" if key in unseen else "calib" if key in calib else "train"
        room_splits[scene.scene_id] = room_split
        split_of_target = _assign_targets(scene, room_split, config)
        for target_id in [t for t in split_of_target if (scene.source, scene.scene_id, t) in fragments]:
            del split_of_target[target_id]
            notes["targets_dropped_as_fragments"] += 1
        target_splits.update({(scene.scene_id, t): s for t, s in split_of_target.items()})
        plans.append((room_split, room_map(scene), split_of_target))
    for split in ("train", "calib"):
        pool = [s for s in ordered if room_splits[s.scene_id] == split]
        rng = np.random.default_rng(_stable_seed(config.seed, "houses", split))
        count = round(config.house_fraction * len(pool))
        plans.extend((split, rooms, None) for rooms in draw_houses(pool, count, rng))
    balancers = {c: _Balancer() for c in Convention}
    steps: Iterable[tuple[str, MapLayout | list[LayoutScene], dict[str, str] | None]] = plans
    if progress:
        from tqdm import tqdm

        steps = tqdm(plans, desc="maps", unit="map")
    houses: Counter[str] = Counter()
    for split, plan, room_targets in steps:
        if isinstance(plan, MapLayout):
            layout, split_of_target = plan, room_targets or {}
        else:
            map_id = f"house-{split}-{houses[split]}"
            houses[split] += 1
            house_rng = np.random.default_rng(_stable_seed(config.seed, map_id))
            layout = join_rooms(plan, map_id, house_rng)
            split_of_target = _house_targets(layout, split, target_splits, house_rng)
        if maps is not None:
            maps[split]["houses" if layout.is_house else "rooms"] += 1
        yield from _map_cases(layout, split_of_target, config, balancers, notes)


def write_build(
    scenes: Sequence[LayoutScene], out_dir: str | Path, config: BuildConfig, progress: bool = False
) -> BuildSummary:
    """Write train/val_seen/val_unseen/calib JSONL and summary.json into `out_dir`; returns the summary.

    The previous build's files are replaced only once every case is written (`app.files.atomic_write`): a
    build that fails or is stopped leaves them as they were.
    """
    out = Path(out_dir)
    summary = BuildSummary()
    seen_scenes: dict[str, set[tuple[str, str]]] = {s: set() for s in SPLITS}
    with ExitStack() as files:
        # Entered first so that it is replaced last, after the split files it describes.
        summary_file = files.enter_context(atomic_write(out / "summary.json"))
        handles = {s: files.enter_context(atomic_write(out / f"{s}.jsonl")) for s in SPLITS}
        for split, case in build_cases(scenes, config, progress, summary.notes, summary.maps):
            handles[split].write(case.model_dump_json(exclude_none=True))
            handles[split].write("\n")
            summary.add(split, case)
            seen_scenes[split].add((case.meta["source"], case.meta["scene_id"]))
        for split, pairs in seen_scenes.items():
            summary.scenes[split].update(source for source, _ in pairs)
        payload = {"config": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}}
        summary_file.write(json.dumps({**payload, **summary.to_json()}, indent=2) + "\n")
    return summary
