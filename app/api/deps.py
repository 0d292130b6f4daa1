"""Dependencies as `Annotated` aliases, so route signatures read as plain types."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.auth import OPEN_ACCESS, Principal
from app.api.services import Services
from app.errors import ModelUnavailable, Unauthenticated
from app.grounding.sensor import LanguageSensor
from app.settings import Settings

_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="ApiKey",
    description="An API key: `Authorization: Bearer <key>`. Roles: robot (its own robots' sessions), "
    "viewer (read-only), admin. A service started without keys accepts every request.",
)


def get_services(request: Request) -> Services:
    services: Services = request.app.state.services
    return services


def get_settings(request: Request) -> Settings:
    return get_services(request).settings


def get_sensor(request: Request) -> LanguageSensor:
    sensor = get_services(request).sensor
    if sensor is None:
        msg = "the grounding model is still loading"
        raise ModelUnavailable(msg)
    return sensor


def get_principal(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> Principal:
    """The calling key's principal (rate-limited per key), or open access when no key is configured."""
    services = get_services(request)
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
SensorDep = Annotated[LanguageSensor, Depends(get_sensor)]
PrincipalDep = Annotated[Principal, Depends(get_principal)]
