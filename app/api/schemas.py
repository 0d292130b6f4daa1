"""Request and response bodies of the grounding API (shared by routes and the OpenAPI contract)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag

from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, Vec3


def _scene_graph_kind(value: Any) -> str:
    if isinstance(value, SceneGraph):
        return "native"
    if isinstance(value, dict) and isinstance(value.get("objects"), list):
        return "native"
    return "other"


SceneGraphPayload = Annotated[
    Annotated[SceneGraph, Tag("native")] | Annotated[dict[str, Any], Tag("other")],
    Discriminator(_scene_graph_kind),
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

    anchor_ids: list[str] = Field(min_length=1, max_length=2)
    relation: Relation
    weight: float = Field(default=1.0, gt=0, allow_inf_nan=False)


class GroundOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    proposer: Literal["builtin"] = Field(default="builtin", description="Which hypothesis proposer to use.")
    hypotheses: list[HypothesisIn] | None = Field(
        default=None, min_length=1, max_length=5, description="Skip the proposer: ground these hypotheses."
    )


class GroundRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene_graph: SceneGraphPayload
    utterance: str = Field(min_length=1, max_length=1000, examples=["I left my backpack on the table"])
    options: GroundOptions | None = None
    query_points: list[Vec3] | None = Field(
        default=None, description="Points (m) at which to return the mixture's log-density."
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
    weight: float
    mean: list[float] = Field(min_length=3, max_length=3)
    covariance: list[list[float]] = Field(description="3x3, symmetric positive definite (m^2).")


class MixtureOut(BaseModel):
    components: list[ComponentOut]


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
