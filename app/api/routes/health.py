"""Liveness and readiness probes."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import SensorDep
from app.api.errors import error_responses
from app.api.schemas import HealthResponse, ReadyResponse

router = APIRouter(tags=["operations"])


@router.get("/healthz", operation_id="healthz", response_model=HealthResponse)
async def healthz() -> HealthResponse:
    """Liveness: the process answers."""
    return HealthResponse(status="ok")


@router.get("/readyz", operation_id="readyz", response_model=ReadyResponse, responses=error_responses(503))
async def readyz(sensor: SensorDep) -> ReadyResponse:
    """Readiness: the grounding model is loaded and requests can be served."""
    return ReadyResponse(status="ready", grounder=sensor.grounder.name)
