"""Dependencies as `Annotated` aliases, so route signatures read as plain types."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from app.api.services import Services
from app.errors import ModelUnavailable
from app.grounding.sensor import LanguageSensor
from app.settings import Settings


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


ServicesDep = Annotated[Services, Depends(get_services)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
SensorDep = Annotated[LanguageSensor, Depends(get_sensor)]
