"""The models behind the language sensor."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PrincipalDep, SensorDep
from app.api.errors import error_responses
from app.api.schemas import ModelInfo, ModelsResponse

router = APIRouter(prefix="/v1", tags=["models"])


@router.get(
    "/models",
    operation_id="list_models",
    response_model=ModelsResponse,
    responses=error_responses(401, 429, 503),
)
async def list_models(sensor: SensorDep, _: PrincipalDep) -> ModelsResponse:
    """Name, version, config and weights checksum of the grounder and the proposer in use."""
    grounder = sensor.grounder.describe()
    proposer = {"name": sensor.proposer.name, "version": "1", "config": {}, "checksum": None}
    return ModelsResponse(
        models=[ModelInfo(role="grounder", **grounder), ModelInfo(role="proposer", **proposer)]
    )
