"""Request and response bodies of the grounding API (shared by routes and the OpenAPI contract)."""

from __future__ import annotations

import base64
import json
from typing import TYPE_CHECKING, Annotated, Any, Literal

from fastapi import Query
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    GetJsonSchemaHandler,
    Strict,
    Tag,
    TypeAdapter,
)
from pydantic.config import JsonDict
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema

from app.belief.grid import DEFAULT_MARGIN_M, DEFAULT_VOXEL_SIZE_M
from app.belief.session import DEFAULT_FALSE_POSITIVE_RATE, DEFAULT_TRUE_POSITIVE_RATE, SensorModel
from app.grounding.relations import Relation
from app.scene_graph.model import Id, SceneGraph, Vec3
from app.sessions.service import GridRequest, NewSession
from app.settings import MAX_UTTERANCE_CHARS_CEILING

if TYPE_CHECKING:
    from app.belief.grid import VoxelGrid
    from app.belief.session import SessionInfo, UpdateResult
    from app.sessions.summaries import Belief, TopDown, UtteranceLog
    from app.stores.events import StoredEvent

#: Ceilings of the request lists that the service's configurable limits (`app.settings`) lie below: the
#: validator refuses a longer list before reading its items (`app.api.bodies`).
MAX_QUERY_POINTS_CEILING = 100_000
MAX_BATCH_CEILING = 4_000_000
MAX_LABEL_MAP_CEILING = 65_536
#: Characters of a class name, in a label map or an observation batch (JSON or msgpack).
MAX_LABEL_CHARS = 256


def _scene_graph_kind(value: Any) -> str:
    if isinstance(value, SceneGraph):
        return "native"
    if isinstance(value, dict) and isinstance(value.get("objects"), list):
        return "native"
    return "other"


class _AnyOf:
    """Writes a union's schema as anyOf. The callable discriminator makes pydantic write oneOf, but a
    native graph is also a JSON object, so under oneOf a validator would refuse every native graph."""

    def __get_pydantic_json_schema__(
        self, core: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        schema = handler(core)
        if "oneOf" in schema:
            schema["anyOf"] = schema.pop("oneOf")
        return schema


SceneGraphPayload = Annotated[
    Annotated[SceneGraph, Tag("native")] | Annotated[dict[str, Any], Tag("other")],
    Discriminator(_scene_graph_kind),
    _AnyOf(),
    Field(
        description=(
            "The map: a native SceneGraph, or another JSON scene-graph format that the service "
            "normalises (the region-grouped serialization, a Spark-DSG/Hydra JSON graph, or a VLA-3D "
            "bundle); see POST /v1/scene-graphs/normalize."
        )
    ),
]


class HypothesisIn(BaseModel):
    """A caller-supplied hypothesis: ground only this (anchor(s), relation)."""

    model_config = ConfigDict(extra="forbid")

    anchor_ids: list[Id] = Field(min_length=1, max_length=2)
    relation: Relation
    weight: float = Field(default=1.0, gt=0, allow_inf_nan=False)


class GroundOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    proposer: Literal["builtin", "llm"] = Field(
        default="builtin",
        description="Hypothesis proposer: built-in (offline) or the configured LLM endpoint.",
    )
    grounder: Literal["lsm", "geometric", "fixed", "scaffolded-llm", "llm-e2e"] | None = Field(
        default=None, description="Spatial grounder (default: the service's); see GET /v1/models."
    )
    hypotheses: list[HypothesisIn] | None = Field(
        default=None, min_length=1, max_length=5, description="Skip the proposer: ground these hypotheses."
    )


class GroundRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene_graph: SceneGraphPayload
    utterance: str = Field(
        min_length=1, max_length=MAX_UTTERANCE_CHARS_CEILING, examples=["I left my backpack on the table"]
    )
    options: GroundOptions | None = None
    query_points: list[Vec3] | None = Field(
        default=None,
        max_length=MAX_QUERY_POINTS_CEILING,
        fail_fast=True,
        description="Points (m) at which to return the mixture's log-density.",
    )


class TargetOut(BaseModel):
    label: str = Field(description="The target phrase read from the utterance (may be empty).")


class ParseOut(BaseModel):
    target: str
    relation: Relation
    relation_phrase: str
    anchor_phrases: list[str]
    region_phrase: str | None = None


class HypothesisOut(BaseModel):
    anchor_ids: list[str]
    relation: Relation
    region_id: str | None
    weight: float = Field(description="P(h | utterance, map); the weights sum to 1.")
    text: str


class ComponentOut(BaseModel):
    """One Gaussian term w_k N(x; mu_k, Sigma_k) of the mixture."""

    weight: float = Field(description="w_k: this Gaussian's share of the whole mixture's mass.")
    mean: list[float] = Field(min_length=3, max_length=3, description="mu_k (m), the scene graph's frame.")
    covariance: list[list[float]] = Field(description="Sigma_k: 3x3, symmetric positive definite (m^2).")
    hypothesis: int | None = Field(
        ge=0,
        description=(
            "Index in `hypotheses` of the hypothesis this Gaussian belongs to (a hypothesis's density may "
            "have several: a core and a wider tail); null for a Gaussian of no hypothesis, e.g. the broad "
            "prior of an utterance that was not grounded."
        ),
        examples=[0, None],
    )


class UniformBoxOut(BaseModel):
    """One uniform term v_b U(x; box_b) of the mixture: an axis-aligned box in the scene graph's frame."""

    weight: float = Field(description="v_b: this box's share of the whole mixture's mass.")
    low: list[float] = Field(min_length=3, max_length=3, description="The box's lower corner [x, y, z] (m).")
    high: list[float] = Field(
        min_length=3,
        max_length=3,
        description="The box's upper corner [x, y, z] (m), above `low` on each axis.",
    )


_MIXTURE_EXAMPLE: JsonDict = {
    "components": [
        {
            "weight": 0.45,
            "mean": [1.5, 0.5, 0.85],
            "covariance": [[0.04, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.0025]],
            "hypothesis": 0,
        },
        {
            "weight": 0.45,
            "mean": [-2.0, 1.0, 0.55],
            "covariance": [[0.04, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.0025]],
            "hypothesis": 1,
        },
    ],
    "uniform": [{"weight": 0.1, "low": [-4.5, -2.5, 0.0], "high": [4.5, 2.5, 2.4]}],
}


class MixtureOut(BaseModel):
    """The density of the target's position x (m, the scene graph's frame):

    p(x) = sum_k w_k N(x; mu_k, Sigma_k) + sum_b v_b U(x; box_b),

    with `components` the Gaussians (w_k, mu_k, Sigma_k) and `uniform` the boxes (v_b, box_b). The weights of
    the components and of the boxes together sum to one. U(x; box) = 1 / vol(box) inside the closed box
    [low, high] and 0 outside. A box carries a broad term exactly ("I may have misunderstood", a prior over a
    region or the whole map). `query_log_density` is log p(x) of this density, and a session's belief fuses
    exactly it: log(p(c_i) V) at every voxel centre c_i (V the voxel volume), the language layer bounding its
    span so that no voxel is ruled out for good.
    """

    model_config = ConfigDict(json_schema_extra={"examples": [_MIXTURE_EXAMPLE]})

    components: list[ComponentOut] = Field(description="The Gaussian terms (empty when boxes carry all).")
    uniform: list[UniformBoxOut] = Field(description="The uniform-box terms (empty when there are none).")


class ModelRef(BaseModel):
    name: str
    version: str


class GroundResponse(BaseModel):
    target: TargetOut
    parse: ParseOut
    grounded: bool = Field(description="False when no anchor matched: the mixture is then a broad prior.")
    reason: str | None = Field(default=None, description="Why the utterance could not be grounded.")
    hypotheses: list[HypothesisOut]
    mixture: MixtureOut
    query_log_density: list[float] | None = Field(default=None, description="log p(x) at each query point.")
    model: ModelRef
    timings_ms: dict[str, float]


class ModelInfo(BaseModel):
    name: str
    version: str
    config: dict[str, Any]
    checksum: str | None = Field(
        description="sha256 of the weights (or of the config for learning-free models)."
    )
    role: Literal["grounder", "proposer"]


class ModelsResponse(BaseModel):
    models: list[ModelInfo]


class HealthResponse(BaseModel):
    status: Literal["ok"]


class ReadyResponse(BaseModel):
    status: Literal["ready"]
    grounder: str


# --- sessions -------------------------------------------------------------------------------------------

ROBOT_ID_PATTERN = r"^[A-Za-z0-9._:\-]+$"
RobotId = Annotated[str, Field(min_length=1, max_length=128, pattern=ROBOT_ID_PATTERN)]


class PackedArray(BaseModel):
    """A numpy array on the msgpack wire: dtype (e.g. "<i4"), shape and the raw little-endian bytes."""

    dtype: Literal["<i4", "<i8", "<f4", "<f8", "<u4", "<u2", "<u1", "|u1"] = Field(
        description='numpy\'s dtype.str; "|u1" and "<u1" both name uint8.'
    )
    shape: list[Annotated[int, Field(ge=0)]]
    data: bytes


class GridSpec(BaseModel):
    """The voxel grid of a belief; bounds default to the scene graph's extent plus `margin`."""

    model_config = ConfigDict(extra="forbid")

    voxel_size: float = Field(
        default=DEFAULT_VOXEL_SIZE_M, ge=0.02, le=2.0, allow_inf_nan=False, description="Metres."
    )
    margin: float = Field(
        default=DEFAULT_MARGIN_M, ge=0.0, le=10.0, allow_inf_nan=False, description="Metres around the map."
    )
    min_corner: Vec3 | None = Field(default=None, description="Explicit lower corner (with max_corner).")
    max_corner: Vec3 | None = None


class SensorModelIn(BaseModel):
    """tp = P(label = target | target there), fp = P(label = target | target not there)."""

    model_config = ConfigDict(extra="forbid")

    tp: float = Field(default=DEFAULT_TRUE_POSITIVE_RATE, gt=0.0, lt=1.0)
    fp: float = Field(default=DEFAULT_FALSE_POSITIVE_RATE, gt=0.0, lt=1.0)


class SensorModelOverride(BaseModel):
    """One batch's tp and/or fp; a rate left out keeps the session's."""

    model_config = ConfigDict(extra="forbid")

    tp: float | None = Field(default=None, gt=0.0, lt=1.0)
    fp: float | None = Field(default=None, gt=0.0, lt=1.0)


LabelIdText = Annotated[str, Field(pattern=r"^[0-9]{1,10}$", description="A uint32 label id, in decimal.")]
ClassName = Annotated[str, Field(min_length=1, max_length=MAX_LABEL_CHARS)]
LabelName = Annotated[str, Field(max_length=MAX_LABEL_CHARS)]


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    robot_id: RobotId
    scene_graph: SceneGraphPayload
    grid: GridSpec | None = None
    target_label: str | None = Field(
        default=None,
        min_length=1,
        max_length=256,
        description="Target class; else the first utterance's target.",
    )
    sensor_model: SensorModelIn | None = None
    label_map: dict[LabelIdText, ClassName] | None = Field(
        default=None,
        max_length=MAX_LABEL_MAP_CEILING,
        fail_fast=True,
        description='Integer label id (as a string key) -> class name, e.g. {"7": "backpack"}.',
    )

    def request(self, scene_graph: SceneGraph) -> NewSession:
        """The use-case's request, with the body's scene graph resolved to `scene_graph`."""
        grid, sensor = self.grid or GridSpec(), self.sensor_model
        return NewSession(
            robot_id=self.robot_id,
            scene_graph=scene_graph,
            grid=GridRequest(grid.voxel_size, grid.margin, grid.min_corner, grid.max_corner),
            target_label=self.target_label or "",
            label_map=self.label_map,
            sensor_model=SensorModel(sensor.tp, sensor.fp) if sensor else None,
        )


class GridOut(BaseModel):
    min_corner: list[float]
    shape: list[int]
    voxel_size: float
    n_voxels: int

    @classmethod
    def of(cls, grid: VoxelGrid) -> GridOut:
        return cls(
            min_corner=list(grid.origin),
            shape=list(grid.shape),
            voxel_size=grid.voxel_size,
            n_voxels=grid.n_voxels,
        )


class SessionOut(BaseModel):
    id: str
    robot_id: str
    target_label: str | None
    version: int = Field(description="Belief version: grows by one with every acknowledged update.")
    created_at: float
    updated_at: float
    grid: GridOut | None = None

    @classmethod
    def of(cls, info: SessionInfo) -> SessionOut:
        return cls(
            id=info.id,
            robot_id=info.robot_id,
            target_label=info.target_label or None,
            version=info.version,
            created_at=info.created_at,
            updated_at=info.updated_at,
            grid=GridOut.of(info.grid),
        )


class SessionList(BaseModel):
    sessions: list[SessionOut]


class VoxelOut(BaseModel):
    index: int
    center: list[float]
    probability: float


class PlaceOut(BaseModel):
    kind: Literal["object", "region"]
    id: str
    label: str
    mass: float


class PosteriorSummaryOut(BaseModel):
    """Where the target is, according to the fused belief."""

    n_voxels: int
    map_voxel: VoxelOut
    top_voxels: list[VoxelOut]
    mean: list[float]
    covariance: list[list[float]]
    entropy_nats: float
    information_gain_nats: float = Field(description="KL(posterior || uniform) = log N - entropy.")
    objects: list[PlaceOut] = Field(
        description=(
            'Mass per scene-graph object, largest first ("0.62 on table 7"): the mass on its support '
            "place, where a target resting on it or kept in it would be (a table's top; a nightstand's or "
            "drawer's inside and top), each voxel counted for the smallest support place holding it. "
            "Structure (floors, walls, ceilings) is listed apart, in `structure`. (Earlier releases counted "
            "each object's whole box plus 0.3 m on top, floors and walls among them, so that the floor led.)"
        )
    )
    regions: list[PlaceOut] = Field(description="Mass per region (its box), largest first.")
    structure: list[PlaceOut] = Field(
        description=(
            "Mass on the room's structure (floors, walls, ceilings: each one's box plus 0.3 m on top), "
            "outside every object's support place, largest first."
        )
    )
    mass_elsewhere: float = Field(
        description=(
            "Mass in no object's support place nor on structure; with every object's and structure's mass "
            "it sums to one."
        )
    )


class BeliefOut(BaseModel):
    session_id: str
    version: int
    target_label: str | None
    summary: PosteriorSummaryOut

    @classmethod
    def of(cls, belief: Belief) -> BeliefOut:
        return cls(
            session_id=belief.session_id,
            version=belief.version,
            target_label=belief.target_label or None,
            summary=PosteriorSummaryOut.model_validate(belief.summary.to_dict()),
        )


class TopDownOut(BaseModel):
    """The posterior seen from above: its mass in each (x, y) column of voxels of the session's grid (summed
    over z), what a dashboard draws as a heat map. Cell (i, j) covers x in [x0 + i s, x0 + (i + 1) s) and y
    in [y0 + j s, y0 + (j + 1) s), with (x0, y0) = `min_corner` and s = `voxel_size`."""

    session_id: str
    version: int = Field(description='The belief version (the ETag: "v<version>").')
    min_corner: list[float] = Field(min_length=2, max_length=2, description="(x0, y0) of the grid (m).")
    voxel_size: float = Field(description="s (m).")
    shape: list[int] = Field(min_length=2, max_length=2, description="(nx, ny): cells along x and y.")
    max_mass: float = Field(description="The largest cell's mass.")
    mass: str = Field(
        description="base64 of nx * ny little-endian float32 masses, cell (i, j) at index i * ny + j; they "
        "sum to one."
    )

    @classmethod
    def of(cls, view: TopDown) -> TopDownOut:
        grid, mass = view.grid, view.mass
        return cls(
            session_id=view.session_id,
            version=view.version,
            min_corner=list(grid.origin[:2]),
            voxel_size=grid.voxel_size,
            shape=list(grid.shape[:2]),
            max_mass=float(mass.max()),
            mass=base64.b64encode(mass.astype("<f4").tobytes()).decode("ascii"),
        )


class ReadingOut(BaseModel):
    """One reading of an utterance, as its event recorded it."""

    text: str = Field(description='The reading, e.g. "on the table t1".')
    weight: float = Field(description="P(h | utterance, map): the weights of its readings sum to 1.")
    anchor_ids: list[str] = Field(description="The objects it is relative to (none: a region or the map).")


class UtteranceRecordOut(BaseModel):
    """An utterance sent to the session: what its event said (`UtteranceCause` of the push stream)."""

    event_id: str = Field(description="Its event's id on the push stream.")
    version: int = Field(description="The belief version after it (unchanged when it was not fused).")
    updated_at: float = Field(description="When it was fused or refused (Unix s).")
    utterance: str
    fused: bool
    reason: str | None
    named_target: str | None
    hypotheses: list[ReadingOut] | None = Field(
        description="Its readings with their weights, as grounded (null in an event of an older release)."
    )

    @classmethod
    def of(cls, event: StoredEvent) -> UtteranceRecordOut:
        fields = json.loads(event.data)
        cause = {key: value for key, value in fields["cause"].items() if key != "kind"}
        return cls.model_validate(
            {"event_id": event.stream_id, "version": event.version, "updated_at": fields["updated_at"]}
            | {"hypotheses": None}
            | cause
        )


class UtteranceHistoryOut(BaseModel):
    """The utterances among the session's retained events, oldest first: the last `VLMAP_EVENTS_HISTORY`
    events of every kind (observation batches among them), so at sensor rate only the recent ones."""

    session_id: str
    utterances: list[UtteranceRecordOut]
    complete: bool = Field(
        description="Whether the history reaches back to the session's creation (no older event was dropped)."
    )

    @classmethod
    def of(cls, log: UtteranceLog) -> UtteranceHistoryOut:
        utterances = [UtteranceRecordOut.of(event) for event in log.events]
        return cls(session_id=log.session_id, utterances=utterances, complete=log.complete)


class UtteranceIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    utterance: str = Field(min_length=1, max_length=MAX_UTTERANCE_CHARS_CEILING)
    options: GroundOptions | None = None


class UtteranceOut(BaseModel):
    """What fusing an utterance into a session did.

    An utterance whose target phrase names an object class other than the session's target class ("the mug is
    on the desk" while looking for keys) is not fused: `fused` is false, `reason` names both classes, the
    grounding is returned for inspection and the belief and its version are unchanged. A looser naming of
    the target's class ("my bag" for a backpack, "keys" for a keychain) and a phrase that names no object
    ("it", "something") fuse. An utterance that could not be grounded fuses only its broad prior
    (`grounding.grounded` false, `grounding.reason` why) and `reason` says so. While the session has no
    target class, the first utterance whose target phrase names one sets it.
    """

    grounding: GroundResponse
    belief: BeliefOut
    fused: bool = Field(description="Whether the utterance's mixture was added to the belief.")
    reason: str | None = Field(
        default=None,
        description=(
            "Why the utterance was not fused, or why only its broad prior was; null when its grounded "
            "mixture was fused."
        ),
        examples=[
            "the utterance's target 'mug' is not the session's target 'keys': not fused",
            "not grounded (no object in the scene graph matches 'spaceship'): the belief got only the "
            "broad prior",
        ],
    )

    @staticmethod
    def answer(grounding: GroundResponse, reason: str | None, fused: bool) -> bytes:
        """What the answer says besides the belief, remembered with an Idempotency-Key so that a retry
        repeats it (the verdict too: by the retry the session's target may have changed)."""
        return json.dumps(
            {"grounding": grounding.model_dump(mode="json"), "reason": reason, "fused": fused}
        ).encode()

    @staticmethod
    def first_answer(answer: bytes, fused: bool) -> tuple[GroundResponse, str | None, bool]:
        """Inverse of `answer`; `fused` stands for the verdict of an answer remembered without it."""
        first = json.loads(answer)
        return GroundResponse.model_validate(first["grounding"]), first["reason"], first.get("fused", fused)


# Strict: a JSON true or 1.0 is not the integer 1.
VoxelIndex = Annotated[
    int, Strict(), Field(ge=-(2**31), lt=2**31, description="Voxel index along one axis (int32).")
]
LabelId = Annotated[
    int, Strict(), Field(ge=0, lt=2**32, description="An id of the session's label map (uint32).")
]
LabelIds = Annotated[list[LabelId], Field(max_length=MAX_BATCH_CEILING, fail_fast=True)]
LabelNames = Annotated[list[LabelName], Field(max_length=MAX_BATCH_CEILING, fail_fast=True)]


class ObservationBatchJson(BaseModel):
    """Labelled voxels (or points) seen by the robot, for small batches; large ones go as msgpack."""

    model_config = ConfigDict(extra="forbid")

    stamp: float | None = Field(default=None, allow_inf_nan=False, description="Sensor time (s), echoed.")
    voxels: list[Annotated[list[VoxelIndex], Field(min_length=3, max_length=3)]] | None = Field(
        default=None,
        max_length=MAX_BATCH_CEILING,
        fail_fast=True,
        description="Voxel indices [i, j, k] in the session's grid.",
    )
    points: list[Vec3] | None = Field(
        default=None,
        max_length=MAX_BATCH_CEILING,
        fail_fast=True,
        description="Points (m) in the scene graph's frame.",
    )
    labels: LabelIds | LabelNames | None = Field(
        default=None,
        description="One label per voxel: class names (of the label map's, when the session has one), or "
        "integer ids of the label map.",
    )
    p_target: list[Annotated[float, Field(ge=0.0, le=1.0)]] | None = Field(
        default=None,
        max_length=MAX_BATCH_CEILING,
        fail_fast=True,
        description="Detector probability that each voxel holds the target (instead of labels).",
    )
    sensor_model: SensorModelOverride | None = Field(
        default=None,
        description="Overrides the session's for this batch; a rate left out keeps the session's.",
    )


class ObservationOut(BaseModel):
    version: int
    stamp: float | None
    voxels_updated: int
    voxels_outside: int = Field(description="Voxels or points outside the grid: counted and skipped.")
    belief: BeliefOut | None = Field(
        description="The posterior summary after this batch (null with summary=false)."
    )

    @classmethod
    def of(cls, result: UpdateResult, stamp: float | None, belief: Belief | None) -> ObservationOut:
        return cls(
            version=result.version,
            stamp=stamp,
            voxels_updated=result.voxels_updated,
            voxels_outside=result.voxels_outside,
            belief=BeliefOut.of(belief) if belief is not None else None,
        )


# Query parameters of the session routes.
RobotIdQuery = Annotated[
    str | None,
    Query(min_length=1, max_length=128, pattern=ROBOT_ID_PATTERN, description="Only this robot's sessions."),
]
WithSummaryQuery = Annotated[
    bool,
    Query(description="Return the posterior summary (false: just the version, for sensor-rate streams)."),
]
BeliefFormatQuery = Annotated[
    str, Query(pattern="^(summary|grid)$", description="summary (JSON) or grid (msgpack posterior).")
]
LayersQuery = Annotated[bool, Query(description="With format=grid: also the language and vision layers.")]
TopKQuery = Annotated[int, Query(ge=1, le=100, description="Top voxels in the summary.")]


def scene_graph_payload_schema() -> dict[str, Any]:
    """The OpenAPI schema of a bare `SceneGraphPayload` body (PUT .../scene-graph), as FastAPI wrote it when
    it read that body itself (the definitions it refers to are the components')."""
    schema = TypeAdapter(SceneGraphPayload).json_schema(ref_template="#/components/schemas/{model}")
    schema.pop("$defs", None)
    return {**schema, "title": "Scene Graph"}
