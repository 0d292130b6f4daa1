"""The models behind the language sensor."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PrincipalDep, SensorsDep
from app.api.errors import error_responses
from app.api.schemas import ModelInfo, ModelsResponse

router = APIRouter(prefix="/v1", tags=["models"])


@router.get(
    "/models",
    operation_id="list_models",
    response_model=ModelsResponse,
    responses=error_responses(401, 429, 503),
)
async def list_models(sensors: SensorsDep, _: PrincipalDep) -> ModelsResponse:
    """Name, version, config and weights checksum of each loaded grounder (default first) and the proposer."""
    names = [sensors.default, *sorted(n for n in sensors.grounders if n != sensors.default)]
    models = [ModelInfo(role="grounder", **sensors.grounders[n].describe()) for n in names]
    models += [ModelInfo(role="proposer", **p.describe()) for p in sensors.proposers.values()]
    return ModelsResponse(models=models)
