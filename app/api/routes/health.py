"""Liveness and readiness probes."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import SensorsDep, SessionsDep
from app.api.errors import error_responses
from app.api.schemas import HealthResponse, ReadyResponse

router = APIRouter(tags=["operations"])


@router.get("/healthz", operation_id="healthz", response_model=HealthResponse)
async def healthz() -> HealthResponse:
    """Liveness: the process answers."""
    return HealthResponse(status="ok")


@router.get("/readyz", operation_id="readyz", response_model=ReadyResponse, responses=error_responses(503))
async def readyz(sensors: SensorsDep, _: SessionsDep) -> ReadyResponse:
    """Readiness: the grounding models are loaded and the session store is open."""
    return ReadyResponse(status="ready", grounder=sensors.default)
