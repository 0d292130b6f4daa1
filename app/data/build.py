"""Grounding cases from real layouts (ScanNet scans, AI2-THOR rooms), with relations computed from real boxes.

For every scene the builder picks target objects, removes each target from the scene graph (and nothing else),
lists the target's true relations to the remaining objects (`app.data.relations`), and emits a bounded number
of (target, relation, anchor(s)) cases with a templated utterance (`app.data.templates`).

* ScanNet: every relation comes from the boxes.
* AI2-THOR: on/in come from the simulator's `parent_receptacles` (the receptacles an object really sits on
  or in), mapped to "on" or "in" by receptacle type (`THOR_RECEPTACLE_RELATION`); the other relations come
  from the boxes. "On the floor" placements are dropped (the floor is never an anchor). A parent id missing
  from the scene falls back to its base object when the id names a part ("Sink|...|SinkBasin" -> "Sink|..."),
  else the placement is skipped; both are counted in the summary.

Splits: `val_unseen` holds whole scenes never seen in training, a seeded ~`unseen_fraction` of the rooms of
each source (ScanNet rescans "sceneXXXX_YY" of one room XXXX stay together); `val_seen` holds held-out targets
of the training scenes; `train` the rest, augmented by K rigid motions of the whole scene. The motions turn
the scene about z by a multiple of 90 degrees (so axis-aligned boxes stay axis-aligned, with x/y sizes swapped
on odd quarter turns, and no object needs a yaw) and shift it in the floor plane; relations are invariant.
"""

from __future__ import annotations

import json
import re
import zlib
from collections import Counter, defaultdict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.data.cases import CaseHypothesis, CaseTarget, GroundingCase
from app.data.relations import Grounding, is_structure, label_set, true_groundings
from app.data.templates import render_utterance
from app.errors import InvalidInput
from app.grounding.relations import Relation
from app.scene_graph.model import Region, SceneGraph, SceneObject

SPLITS = ("train", "val_seen", "val_unseen")
SOURCES = ("scannet", "ai2thor")

# Boxes thinner than this (two AI2-THOR objects have a zero side) are widened to it.
MIN_SIZE = 0.01
# Targets are small or medium: footprint sides and height at most these (metres).
TARGET_MAX_SIDE = 1.5
TARGET_MAX_HEIGHT = 2.0
# A ScanNet object counts as portable ("I left my ...") when no side exceeds this.
PORTABLE_MAX_SIDE = 0.6
# Targets whose box volume is below this fraction of their label's median volume are fragments (see
# `fragment_ids`); the median needs at least FRAGMENT_MIN_COUNT instances of the label.
FRAGMENT_VOLUME_RATIO = 0.2
FRAGMENT_MIN_COUNT = 10
# Largest floor-plane shift of an augmentation (metres, per axis).
AUGMENT_MAX_SHIFT = 5.0

# Built-in fixtures and parts of furniture: real objects, and fine anchors, but not what people look for.
FIXTURES = label_set(
    "kitchen cabinets, kitchen cabinet, cabinet, cabinets, bathroom cabinet, counter, kitchen counter, "
    "countertop, bathroom vanity, shower, bathtub, bathtub basin, sink, sink basin, toilet, radiator, "
    "whiteboard, blackboard, bulletin board, board, closet, wardrobe closet, refrigerator, fridge, "
    "stove, oven, range hood, dishwasher, shower curtain rod, closet rod, fireplace, drawer, shelf, "
    "stove burner, stove knob, faucet, shower head, towel holder, hand towel holder, "
    "toilet paper hanger, light switch, bathroom stall, mailboxes, water heater, washing machine, "
    "clothes dryer, bar, ledge, windowsill"
)

# How an AI2-THOR receptacle holds what it carries. Types absent from the table default to "on".
_THOR_CONTAINING = (
    "Fridge Cabinet Drawer Microwave Box GarbageCan BathtubBasin SinkBasin Safe LaundryHamper Pot Pan Bowl "
    "Cup Mug Kettle CoffeeMachine Toaster"
)
_THOR_SUPPORTING = (
    "CounterTop DiningTable CoffeeTable SideTable Desk Shelf ShelvingUnit Dresser Bed Sofa ArmChair Chair "
    "Stool Ottoman Footstool TVStand Toilet TowelHolder HandTowelHolder ToiletPaperHanger StoveBurner Plate "
    "DogBed Sink Bathtub"
)
THOR_RECEPTACLE_RELATION: dict[str, Relation] = {
    **dict.fromkeys(_THOR_CONTAINING.split(" "), Relation.IN),
    **dict.fromkeys(_THOR_SUPPORTING.split(" "), Relation.ON),
}
THOR_ROOM_NAMES = {
    "kitchens": "kitchen",
    "living_rooms": "living room",
    "bedrooms": "bedroom",
    "bathrooms": "bathroom",
    "robothor": "apartment",
}
# Compound words that CamelCase splitting would tear apart.
_THOR_LABEL_OVERRIDES = {
    "CounterTop": "countertop",
    "BasketBall": "basketball",
    "KeyChain": "keychain",
    "TableTopDecor": "tabletop decor",
    "ArmChair": "armchair",
}
_CAMEL_WORD = re.compile(r"[A-Z]+(?![a-z])|[A-Z][a-z]*|[a-z]+|\d+")
_SCANNET_ROOM = re.compile(r"^(scene\d{4})_\d{2}$")


def split_camel_case(object_type: str) -> str:
    """An AI2-THOR object type as words: "DiningTable" -> "dining table", "TVStand" -> "tv stand"."""
    if object_type in _THOR_LABEL_OVERRIDES:
        return _THOR_LABEL_OVERRIDES[object_type]
    return " ".join(w.lower() for w in _CAMEL_WORD.findall(object_type))


def thor_placement_relation(receptacle_type: str) -> Relation:
    """IN for receptacles that enclose (Fridge, Drawer, SinkBasin, ...), ON for those that support."""
    return THOR_RECEPTACLE_RELATION.get(receptacle_type, Relation.ON)


def room_key(source: str, scene_id: str) -> str:
    """The physical room of a scene: rescans "scene0010_00" and "scene0010_01" share "scannet/scene0010"."""
    match = _SCANNET_ROOM.match(scene_id) if source == "scannet" else None
    return f"{source}/{match.group(1) if match else scene_id}"


def is_target_candidate(label: str, size: Sequence[float]) -> bool:
    """Small or medium, movable-looking objects: no structure, no fixture, not too big."""
    text = label.strip().lower()
    if is_structure(text) or text in FIXTURES:
        return False
    return max(size[0], size[1]) <= TARGET_MAX_SIDE and size[2] <= TARGET_MAX_HEIGHT


@dataclass
class LayoutScene:
    """One real layout, normalised: objects in one region, known placements, candidate targets."""

    source: str
    scene_id: str
    region: Region
    objects: list[SceneObject]
    # target id -> {anchor id: ON or IN}; None where on/in must come from the boxes (ScanNet).
    placements: dict[str, dict[str, Relation]] | None
    portable: frozenset[str]
    targets: list[str]
    notes: Counter[str] = field(default_factory=Counter)


def _box_values(raw: dict[str, Any], where: str) -> tuple[list[float], list[float]]:
    try:
        center = [float(v) for v in raw["center"]]
        size = [max(float(v), MIN_SIZE) for v in raw["size"]]
    except (KeyError, TypeError, ValueError) as exc:
        msg = f"object without a usable center/size: {exc}"
        raise InvalidInput(msg, where) from exc
    if len(center) != 3 or len(size) != 3:
        msg = "center and size need three values"
        raise InvalidInput(msg, where)
    return center, size


def _extent_region(name: str, objects: Sequence[SceneObject]) -> Region:
    lo = np.min([o.min_corner for o in objects], axis=0)
    hi = np.max([o.max_corner for o in objects], axis=0)
    return Region(id="0", name=name, center=(0.5 * (lo + hi)).tolist(), size=(hi - lo).tolist())


def _read_jsonl(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    with path.open(encoding="utf-8") as fh:
        for number, line in enumerate(fh, start=1):
            if line.strip():
                yield number, json.loads(line)


def read_scannet(path: str | Path) -> list[LayoutScene]:
    """ScanNet scenes (`scannet_train_scenes.jsonl`): boxes only; on/in will come from the boxes."""
    scenes = []
    for number, raw in _read_jsonl(Path(path)):
        objects = []
        for k, o in enumerate(raw["objects"]):
            center, size = _box_values(o, f"{path}:{number}:objects[{k}]")
            label = str(o["label"]).strip().lower()
            objects.append(SceneObject(id=str(o["id"]), label=label, center=center, size=size, region_id="0"))
        if not objects:
            continue
        portable = frozenset(
            o.id for o in objects if max(o.size) <= PORTABLE_MAX_SIDE and not is_structure(o.label)
        )
        scenes.append(
            LayoutScene(
                source="scannet",
                scene_id=str(raw["scene_id"]),
                region=_extent_region("room", objects),
                objects=objects,
                placements=None,
                portable=portable,
                targets=[o.id for o in objects if is_target_candidate(o.label, o.size)],
            )
        )
    return scenes


def _thor_placements(
    raw_objects: list[dict[str, Any]], notes: Counter[str]
) -> dict[str, dict[str, Relation]]:
    types = {str(o["id"]): str(o["label"]) for o in raw_objects}
    placements: dict[str, dict[str, Relation]] = {}
    for o in raw_objects:
        found: dict[str, Relation] = {}
        for parent in o.get("parent_receptacles") or []:
            parent = str(parent)
            part = parent.rsplit("|", 1)[-1]
            if parent in types:
                anchor, kind = parent, types[parent]
            elif parent.count("|") >= 4 and part.isalpha() and parent.rsplit("|", 1)[0] in types:
                # "Sink|x|y|z|SinkBasin" without its basin object: the sink itself, held the basin's way.
                anchor, kind = parent.rsplit("|", 1)[0], part
                notes["placement_parent_resolved_to_base"] += 1
            else:
                notes["placement_parent_missing"] += 1
                continue
            if types[anchor] == "Floor":
                notes["placement_on_floor_dropped"] += 1
                continue
            found[anchor] = thor_placement_relation(kind)
        if found:
            placements[str(o["id"])] = found
    return placements


def read_ai2thor(path: str | Path) -> list[LayoutScene]:
    """AI2-THOR rooms (`ai2thor_scenes.jsonl`): CamelCase types become words; parents give on/in."""
    scenes = []
    for number, raw in _read_jsonl(Path(path)):
        room_type = str(raw.get("room_type", ""))
        notes: Counter[str] = Counter()
        objects = []
        for k, o in enumerate(raw["objects"]):
            center, size = _box_values(o, f"{path}:{number}:objects[{k}]")
            label = split_camel_case(str(o["label"]))
            objects.append(SceneObject(id=str(o["id"]), label=label, center=center, size=size, region_id="0"))
        if not objects:
            continue
        region_name = THOR_ROOM_NAMES.get(room_type, room_type.replace("_", " ").rstrip("s") or "room")
        scenes.append(
            LayoutScene(
                source="ai2thor",
                scene_id=str(raw["scene_id"]),
                region=_extent_region(region_name, objects),
                objects=objects,
                placements=_thor_placements(raw["objects"], notes),
                portable=frozenset(str(o["id"]) for o in raw["objects"] if o.get("pickupable")),
                targets=[o.id for o in objects if is_target_candidate(o.label, o.size)],
                notes=notes,
            )
        )
    return scenes


# --- splits and rigid motions -------------------------------------------------------------------------------


def _stable_seed(seed: int, *parts: str) -> list[int]:
    return [seed, *(zlib.crc32(p.encode("utf-8")) for p in parts)]


def unseen_rooms(scenes: Iterable[LayoutScene], fraction: float, seed: int) -> set[str]:
    """Room keys held out as `val_unseen`: per source, round(fraction * rooms) of them, drawn by the seed."""
    if not 0.0 <= fraction <= 1.0:
        msg = f"unseen fraction must lie in [0, 1], got {fraction}"
        raise InvalidInput(msg, "unseen_fraction")
    by_source: dict[str, set[str]] = defaultdict(set)
    for s in scenes:
        by_source[s.source].add(room_key(s.source, s.scene_id))
    chosen: set[str] = set()
    for source, keys in sorted(by_source.items()):
        ordered = sorted(keys)
        rng = np.random.default_rng(_stable_seed(seed, "unseen", source))
        n = round(fraction * len(ordered))
        chosen.update(ordered[i] for i in rng.permutation(len(ordered))[:n])
    return chosen


@dataclass(frozen=True)
class RigidMotion:
    """Turn about z by `quarter_turns` x 90 degrees, then shift by (dx, dy)."""

    quarter_turns: int
    shift_xy: tuple[float, float]

    def point(self, p: Sequence[float]) -> list[float]:
        x, y, z = p
        for _ in range(self.quarter_turns % 4):
            x, y = -y, x
        return [x + self.shift_xy[0], y + self.shift_xy[1], z]

    def size(self, s: Sequence[float]) -> list[float]:
        dx, dy, dz = s
        return [dy, dx, dz] if self.quarter_turns % 2 else [dx, dy, dz]

    def object(self, o: SceneObject) -> SceneObject:
        return o.model_copy(update={"center": self.point(o.center), "size": self.size(o.size)})

    def region(self, r: Region) -> Region:
        return r.model_copy(update={"center": self.point(r.center), "size": self.size(r.size)})


def random_motion(rng: np.random.Generator) -> RigidMotion:
    shift = rng.uniform(-AUGMENT_MAX_SHIFT, AUGMENT_MAX_SHIFT, size=2)
    return RigidMotion(int(rng.integers(4)), (float(shift[0]), float(shift[1])))


def move_case(case: GroundingCase, motion: RigidMotion) -> GroundingCase:
    """The same case with its whole scene (graph and target) moved rigidly."""
    graph = case.scene_graph.model_copy(
        update={
            "objects": [motion.object(o) for o in case.scene_graph.objects],
            "regions": [motion.region(r) for r in case.scene_graph.regions],
        }
    )
    size = motion.size(case.target.size) if case.target.size is not None else None
    target = case.target.model_copy(update={"position": motion.point(case.target.position), "size": size})
    return case.model_copy(update={"scene_graph": graph, "target": target})


# --- the builder --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BuildConfig:
    seed: int = 0
    augment: int = 2
    max_cases_per_scene: int = 40
    cases_per_target: int = 3
    unseen_fraction: float = 0.15
    val_seen_fraction: float = 0.1


@dataclass
class BuildSummary:
    """What the builder wrote: counts per split x source x relation, ambiguity histogram, skip notes."""

    counts: dict[str, dict[str, Counter[str]]] = field(
        default_factory=lambda: {s: {src: Counter() for src in SOURCES} for s in SPLITS}
    )
    ambiguity: dict[str, Counter[int]] = field(default_factory=lambda: {s: Counter() for s in SPLITS})
    scenes: dict[str, Counter[str]] = field(default_factory=lambda: {s: Counter() for s in SPLITS})
    notes: Counter[str] = field(default_factory=Counter)

    def total(self, split: str) -> int:
        return sum(sum(c.values()) for c in self.counts[split].values())

    def relation_totals(self) -> Counter[str]:
        out: Counter[str] = Counter()
        for split in SPLITS:
            for c in self.counts[split].values():
                out.update(c)
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "cases": {s: self.total(s) for s in SPLITS},
            "counts": {
                s: {src: dict(sorted(c.items())) for src, c in by_src.items()}
                for s, by_src in self.counts.items()
            },
            "ambiguity_histogram": {
                s: {str(k): v for k, v in sorted(c.items())} for s, c in self.ambiguity.items()
            },
            "scenes": {s: dict(c) for s, c in self.scenes.items()},
            "notes": dict(sorted(self.notes.items())),
        }


def _ambiguity(anchor_ids: tuple[str, ...], objects: Sequence[SceneObject]) -> int:
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


def _scene_cases(
    scene: LayoutScene,
    split_of_target: dict[str, str],
    config: BuildConfig,
    balancer: _Balancer,
    notes: Counter[str],
) -> Iterator[tuple[str, GroundingCase]]:
    """(split, case) pairs of one scene, originals up to the cap; train ones are also moved K times.

    Targets whose available relations are the rarest so far go first, so the cap cuts the common ones.
    """
    rng = np.random.default_rng(_stable_seed(config.seed, "scene", scene.source, scene.scene_id))
    by_id = {o.id: o for o in scene.objects}
    motions = [random_motion(rng) for _ in range(config.augment)]
    candidates = []
    for target_id, split in split_of_target.items():
        others = [o for o in scene.objects if o.id != target_id]
        placements = None if scene.placements is None else scene.placements.get(target_id, {})
        by_relation: dict[Relation, list[Grounding]] = defaultdict(list)
        for g in true_groundings(by_id[target_id], others, placements):
            by_relation[g.relation].append(g)
        if not by_relation:
            notes["targets_without_relation"] += 1
            continue
        candidates.append((target_id, split, others, by_relation))
    # A stable sort keeps the shuffled order among equally rare targets.
    candidates.sort(key=lambda c: min(balancer.emitted[r] for r in c[3]))
    emitted = 0
    for target_id, split, others, by_relation in candidates:
        budget = min(config.cases_per_target, config.max_cases_per_scene - emitted)
        if budget <= 0:
            break
        target = by_id[target_id]
        for relation in balancer.choose(by_relation, budget, rng):
            options = by_relation[relation]
            chosen = options[int(rng.integers(len(options)))]
            anchors = tuple(by_id[a].label for a in chosen.anchor_ids)
            case = GroundingCase(
                case_id="/".join(
                    (scene.source, scene.scene_id, target_id, relation.value, "+".join(chosen.anchor_ids))
                ),
                scene_graph=SceneGraph(regions=[scene.region], objects=others),
                utterance=render_utterance(
                    relation, target.label, anchors, rng, portable=target_id in scene.portable
                ),
                target=CaseTarget(label=target.label, position=list(target.center), size=list(target.size)),
                hypotheses=[CaseHypothesis(anchor_ids=list(chosen.anchor_ids), relation=relation)],
                meta={
                    "source": scene.source,
                    "scene_id": scene.scene_id,
                    "target_id": target_id,
                    "ambiguity": _ambiguity(chosen.anchor_ids, others),
                    "augmentation": 0,
                },
            )
            emitted += 1
            yield split, case
            if split != "train":
                continue
            for index, motion in enumerate(motions, start=1):
                update = {
                    "case_id": f"{case.case_id}/aug{index}",
                    "meta": {**case.meta, "augmentation": index},
                }
                yield split, move_case(case, motion).model_copy(update=update)


def fragment_ids(scenes: Sequence[LayoutScene]) -> set[tuple[str, str, str]]:
    """(source, scene id, object id) of targets that are fragments of their class: box volume below
    FRAGMENT_VOLUME_RATIO x the median volume of the label in that source (labels with >= FRAGMENT_MIN_COUNT
    instances). ScanNet has partly segmented instances (a 30 cm "chair" floating at 1.2 m, its back seen over
    a table) whose centre is not where the object is."""
    volumes: dict[tuple[str, str], list[float]] = defaultdict(list)
    for scene in scenes:
        for o in scene.objects:
            volumes[scene.source, o.label].append(float(np.prod(o.size)))
    medians = {k: float(np.median(v)) for k, v in volumes.items() if len(v) >= FRAGMENT_MIN_COUNT}
    out = set()
    for scene in scenes:
        by_id = {o.id: o for o in scene.objects}
        for target_id in scene.targets:
            o = by_id[target_id]
            median = medians.get((scene.source, o.label))
            if median is not None and float(np.prod(o.size)) < FRAGMENT_VOLUME_RATIO * median:
                out.add((scene.source, scene.scene_id, target_id))
    return out


def _assign_targets(scene: LayoutScene, unseen: bool, config: BuildConfig) -> dict[str, str]:
    """Target id -> split, in the (seeded, shuffled) order targets are used."""
    rng = np.random.default_rng(_stable_seed(config.seed, "targets", scene.source, scene.scene_id))
    order = [scene.targets[i] for i in rng.permutation(len(scene.targets))]
    if unseen:
        return dict.fromkeys(order, "val_unseen")
    held = round(config.val_seen_fraction * len(order))
    return {t: ("val_seen" if k < held else "train") for k, t in enumerate(order)}


def build_cases(
    scenes: Sequence[LayoutScene],
    config: BuildConfig,
    progress: bool = False,
    notes: Counter[str] | None = None,
) -> Iterator[tuple[str, GroundingCase]]:
    """All (split, case) pairs, scene by scene in (source, scene id) order; deterministic for a seed.

    `notes` (if given) counts what was skipped: scene-reading notes and targets without any true relation.
    """
    notes = Counter() if notes is None else notes
    unseen = unseen_rooms(scenes, config.unseen_fraction, config.seed)
    fragments = fragment_ids(scenes)
    ordered = sorted(scenes, key=lambda s: (s.source, s.scene_id))
    balancer = _Balancer()
    if progress:
        from tqdm import tqdm

        ordered = tqdm(ordered, desc="scenes", unit="scene")
    for scene in ordered:
        notes.update(scene.notes)
        is_unseen = room_key(scene.source, scene.scene_id) in unseen
        split_of_target = _assign_targets(scene, is_unseen, config)
        for target_id in [t for t in split_of_target if (scene.source, scene.scene_id, t) in fragments]:
            del split_of_target[target_id]
            notes["targets_dropped_as_fragments"] += 1
        yield from _scene_cases(scene, split_of_target, config, balancer, notes)


def write_build(
    scenes: Sequence[LayoutScene], out_dir: str | Path, config: BuildConfig, progress: bool = False
) -> BuildSummary:
    """Write train/val_seen/val_unseen JSONL and summary.json into `out_dir`; returns the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = BuildSummary()
    seen_scenes: dict[str, set[tuple[str, str]]] = {s: set() for s in SPLITS}
    handles = {s: (out / f"{s}.jsonl").open("w", encoding="utf-8") for s in SPLITS}
    try:
        for split, case in build_cases(scenes, config, progress, summary.notes):
            handles[split].write(case.model_dump_json(exclude_none=True))
            handles[split].write("\n")
            source = case.meta["source"]
            relation = case.hypotheses[0].relation.value if case.hypotheses else "none"
            summary.counts[split][source][relation] += 1
            summary.ambiguity[split][int(case.meta["ambiguity"])] += 1
            seen_scenes[split].add((source, case.meta["scene_id"]))
    finally:
        for fh in handles.values():
            fh.close()
    for split, pairs in seen_scenes.items():
        summary.scenes[split].update(source for source, _ in pairs)
    payload = {"config": config.__dict__, **summary.to_json()}
    (out / "summary.json").write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
    return summary
