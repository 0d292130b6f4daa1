"""`create_app()`: the FastAPI application factory."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI

from app import __version__
from app.api.errors import install_error_handlers
from app.api.limits import BodySizeLimitMiddleware
from app.api.observability import Metrics, RequestContextMiddleware
from app.api.routes import ground, health, metrics, models, scene_graphs
from app.api.services import Services, build_sensor
from app.grounding.sensor import LanguageSensor
from app.settings import Settings, get_settings

log = logging.getLogger("vlmap.app")

DESCRIPTION = (
    "Language as a calibrated sensor for robots: turn a scene graph and an utterance "
    '("I left my backpack on the table") into weighted hypotheses and a Gaussian mixture over the '
    "target's 3-D position."
)


def create_app(settings: Settings | None = None, sensor: LanguageSensor | None = None) -> FastAPI:
    """Build the service. `sensor` overrides the one the settings describe (tests, benchmarks)."""
    settings = settings or get_settings()
    services = Services(settings=settings, metrics=Metrics(), sensor=sensor)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if services.sensor is None:
            services.sensor = await anyio.to_thread.run_sync(build_sensor, settings, services.metrics)
        log.info("ready", extra={"grounder": services.sensor.grounder.name})
        yield

    app = FastAPI(
        title="VL-Map",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        separate_input_output_schemas=False,
    )
    app.state.services = services
    install_error_handlers(app)
    for module in (health, models, metrics, ground, scene_graphs):
        app.include_router(module.router)
    app.add_middleware(BodySizeLimitMiddleware, max_body_bytes=settings.max_body_bytes)
    app.add_middleware(RequestContextMiddleware, metrics=services.metrics)  # outermost: sees every answer
    return app
