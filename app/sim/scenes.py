"""Simulation scenes and episodes, from the project's real layouts, grounding-case files and VLA-3D folders.

An episode is one search: a full scene (every object, the target included: the voxel world is built from
it), the target, the scene graph the service is given (the same scene without the target), and the
utterance when one comes with it. Sources:

- raw layouts (`scannet_train_scenes.jsonl`, `ai2thor_scenes.jsonl`), read by `app.data.build` so that
  labels, box sizes and target candidates match the grounding cases built from the same files; these carry
  no utterances (the runner takes them from case files);
- grounding-case files (`app.data.cases`): the case's scene graph lacks the target, which is put back as an
  object built from `target` (label, position, size);
- VLA-3D scene folders, read by `app.scene_graph.vla3d.load_vla3d_scene`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_MAX_VOXELS, DEFAULT_VOXEL_SIZE_M, VoxelGrid
from app.data.cases import GroundingCase, read_cases
from app.errors import InvalidInput, InvalidSceneGraph, NotFound
from app.scene_graph.model import SceneGraph, SceneObject
from app.sim.world import RobotBody, SemanticVoxelWorld

#: Box of a case target whose size the case does not give (metres).
DEFAULT_TARGET_SIZE = (0.2, 0.2, 0.2)
#: Case sources whose utterances people wrote (Nr3D, ScanRefer); every other source's are templates (Sr3D's,
#: the case builder's, VLA-3D's). A case's `meta["language"]` ("human" or "templated") overrides this.
HUMAN_SOURCES = frozenset({"nr3d", "scanrefer"})
LANGUAGES = ("human", "templated")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Episode:
    """One search for one target in one scene."""

    episode_id: str
    source: str
    scene_id: str
    scene: SceneGraph  # every object, the target included
    target: SceneObject
    service_graph: SceneGraph  # `scene` without the target: what the service is told
    utterance: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def service_grid(
        self,
        voxel_size: float = DEFAULT_VOXEL_SIZE_M,
        margin: float = DEFAULT_MARGIN_M,
        max_voxels: int = DEFAULT_MAX_VOXELS,
    ) -> VoxelGrid:
        """The grid a belief session opened with `service_graph` and these settings lives on."""
        graph = self.service_graph
        return VoxelGrid.around(graph, voxel_size=voxel_size, margin=margin, max_voxels=max_voxels)

    @property
    def language(self) -> str | None:
        """Who wrote the utterance: "human" or "templated" (`HUMAN_SOURCES`), None without one."""
        if not self.utterance:
            return None
        given = self.meta.get("language")
        if given in LANGUAGES:
            return str(given)
        return "human" if self.source in HUMAN_SOURCES else "templated"

    def world(
        self, grid: VoxelGrid | None = None, *, robot: RobotBody | None = None, floor_z: float | None = None
    ) -> SemanticVoxelWorld:
        """The voxel world of the full scene on `grid`, by default `service_grid()`, so that observed flat
        indices are the service's. Target voxels outside that grid are dropped, as the service cannot hold
        them either."""
        grid = grid or self.service_grid()
        return SemanticVoxelWorld(grid, self.scene.objects, robot=robot, floor_z=floor_z)


@dataclass(frozen=True)
class SimScene:
    """A full layout and the objects that make sensible search targets in it."""

    source: str
    scene_id: str
    graph: SceneGraph
    candidate_target_ids: tuple[str, ...]

    def episode(self, target_id: str, utterance: str | None = None) -> Episode:
        """The episode searching this scene for object `target_id`."""
        try:
            target = self.graph.object(target_id)
        except KeyError:
            msg = f"scene {self.scene_id!r} has no object {target_id!r}"
            raise NotFound(msg) from None
        others = [o for o in self.graph.objects if o.id != target_id]
        return Episode(
            episode_id=f"{self.source}/{self.scene_id}/{target_id}",
            source=self.source,
            scene_id=self.scene_id,
            scene=self.graph,
            target=target,
            service_graph=self.graph.model_copy(update={"objects": others}),
            utterance=utterance,
        )


def load_layout_scenes(path: str | Path, scene_ids: Iterable[str] | None = None) -> list[SimScene]:
    """Scenes of a raw layout file (ScanNet, AI2-THOR or synthetic JSONL, told apart by AI2-THOR's
    "room_type" and the synthetic rooms' "room" field), in file order; only those named in `scene_ids` when
    given (NotFound if one is missing)."""
    from app.data import build

    path = Path(path)
    with path.open(encoding="utf-8") as fh:
        first = next((line for line in fh if line.strip()), None)
    if first is None:
        msg = f"{path} holds no scene"
        raise InvalidInput(msg, "path")
    fields = json.loads(first)
    if "room_type" in fields:
        layouts = build.read_ai2thor(path)
    elif "room" in fields:
        layouts = build.read_synthetic(path)
    else:
        layouts = build.read_scannet(path)
    if scene_ids is not None:
        wanted = list(dict.fromkeys(scene_ids))
        by_id = {layout.scene_id: layout for layout in layouts}
        missing = [s for s in wanted if s not in by_id]
        if missing:
            msg = f"{path} has no scene {missing[0]!r}"
            raise NotFound(msg)
        layouts = [by_id[s] for s in wanted]
    return [
        SimScene(
            source=layout.source,
            scene_id=layout.scene_id,
            graph=SceneGraph(regions=[layout.region], objects=layout.objects),
            candidate_target_ids=tuple(layout.targets),
        )
        for layout in layouts
    ]


def load_vla3d_scenes(folder: str | Path, scene_names: Iterable[str] | None = None) -> list[SimScene]:
    """VLA-3D scenes of a folder (all it holds, or those named), targets chosen as for the grounding cases.

    Of a whole folder, a scene whose files cannot be read is skipped with a warning, as
    `app.data.vla3d_statements.convert_vla3d` skips it, rather than ending the run; a scene named that
    cannot be read is an error.
    """
    from app.data.build import is_target_candidate
    from app.scene_graph.vla3d import list_vla3d_scenes, load_vla3d_scene

    names = list_vla3d_scenes(folder) if scene_names is None else list(scene_names)
    scenes = []
    for name in names:
        try:
            graph = load_vla3d_scene(folder, name)
        except InvalidSceneGraph as exc:
            if scene_names is not None:
                raise
            log.warning("skipping VLA-3D scene %s: %s", name, exc)
            continue
        candidates = tuple(o.id for o in graph.objects if is_target_candidate(o.label, o.size))
        scenes.append(SimScene(source="vla3d", scene_id=name, graph=graph, candidate_target_ids=candidates))
    return scenes


def episode_from_case(case: GroundingCase) -> Episode:
    """The case's scene with its target put back as an object (id from `meta["target_id"]` when free)."""
    taken = {o.id for o in case.scene_graph.objects}
    target_id = str(case.meta.get("target_id", "target"))
    base, k = target_id, 1
    while target_id in taken:
        target_id, k = f"{base}_{k}", k + 1
    target = SceneObject(
        id=target_id,
        label=case.target.label,
        center=list(case.target.position),
        size=list(case.target.size or DEFAULT_TARGET_SIZE),
    )
    scene = case.scene_graph.model_copy(update={"objects": [*case.scene_graph.objects, target]})
    return Episode(
        episode_id=case.case_id,
        source=str(case.meta.get("source", "cases")),
        scene_id=str(case.meta.get("scene_id", case.case_id)),
        scene=scene,
        target=target,
        service_graph=case.scene_graph,
        utterance=case.utterance,
        meta=dict(case.meta),
    )


def episodes_from_cases(path: str | Path) -> Iterator[Episode]:
    """One episode per case of a grounding-case JSONL file, in order."""
    for case in read_cases(path):
        yield episode_from_case(case)
