"""Dependencies as `Annotated` aliases, so route signatures read as plain types.

Every dependency is a coroutine: FastAPI runs a plain `def` one on a worker thread, a hop out of the event
loop and back per dependency and request (five on an observation batch), each a wait for the interpreter
lock on a busy replica. These only look things up, so they run on the loop.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.auth import OPEN_ACCESS, Principal
from app.api.bootstrap import Sensors
from app.api.services import Services
from app.errors import InvalidInput, ModelUnavailable, Unauthenticated
from app.sessions import SessionService
from app.settings import Settings

_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="ApiKey",
    description="An API key: `Authorization: Bearer <key>`. Roles: robot (its own robots' sessions), "
    "viewer (read-only), admin. A service started without keys accepts every request.",
)


def _services(request: Request) -> Services:
    services: Services = request.app.state.services
    return services


async def get_services(request: Request) -> Services:
    return _services(request)


async def get_settings(request: Request) -> Settings:
    return _services(request).settings


async def get_sensors(request: Request) -> Sensors:
    services = _services(request)
    if services.sensors is None:
        msg = not_started(services) or "the grounding models are still loading"
        raise ModelUnavailable(msg)
    return services.sensors


async def get_sessions(request: Request) -> SessionService:
    services = _services(request)
    if services.sessions is None:
        msg = not_started(services) or "the session store is not open"
        raise ModelUnavailable(msg)
    return services.sessions


def not_started(services: Services) -> str | None:
    """The 503's message while a failed start-up stops the service, else None."""
    if services.startup_error is None:
        return None
    return f"the service failed to start and is stopping: {services.startup_error}"


def _query_names(dependant: Dependant) -> frozenset[str]:
    names = {field.alias for field in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return frozenset(names)


async def reject_unknown_query(request: Request) -> None:
    """422 for query parameters the operation does not declare, or declared ones given twice."""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute):
        return
    declared = _query_names(route.dependant)
    for name in request.query_params:
        if name not in declared:
            msg = f"unknown query parameter {name!r}"
            raise InvalidInput(msg, field=name)
        if len(request.query_params.getlist(name)) > 1:
            msg = f"give {name!r} at most once"
            raise InvalidInput(msg, field=name)


async def get_principal(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> Principal:
    """The calling key's principal (rate-limited per key), or open access when no key is configured."""
    services = _services(request)
    if services.keyring.is_open:
        return OPEN_ACCESS
    if credentials is None:
        msg = "missing API key: send `Authorization: Bearer <key>`"
        raise Unauthenticated(msg)
    principal = services.keyring.authenticate(credentials.credentials)
    if principal is None:
        msg = "unknown API key"
        raise Unauthenticated(msg)
    services.rate_limiter.check(principal.name)
    return principal


ServicesDep = Annotated[Services, Depends(get_services)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
SensorsDep = Annotated[Sensors, Depends(get_sensors)]
PrincipalDep = Annotated[Principal, Depends(get_principal)]
SessionsDep = Annotated[SessionService, Depends(get_sessions)]
