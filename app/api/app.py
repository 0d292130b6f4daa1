"""`create_app()`: the FastAPI application factory."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from functools import partial
from typing import Any

import anyio
import anyio.to_thread
from fastapi import Depends, FastAPI

from app import __version__
from app.api.bootstrap import Sensors, build_sensors, build_store, freeze_startup_objects
from app.api.content_types import FormAsJsonMiddleware
from app.api.deps import reject_unknown_query
from app.api.docs import install_docs
from app.api.errors import install_error_handlers
from app.api.examples import add_request_examples
from app.api.limits import BodySizeLimitMiddleware
from app.api.observability import Metrics, RequestContextMiddleware
from app.api.routes import (
    dashboard,
    events,
    ground,
    health,
    metrics,
    models,
    recordings,
    scene_graphs,
    sessions,
)
from app.api.schemas import (
    GroundRequest,
    ObservationBatchJson,
    PackedArray,
    SensorModelIn,
    SensorModelOverride,
    SessionCreate,
    UtteranceIn,
)
from app.api.services import Services
from app.api.workers import WorkerProcesses
from app.errors import VLMapError
from app.settings import Settings, get_settings
from app.stores.base import SessionStore

log = logging.getLogger("vlmap.app")

DESCRIPTION = (
    "Language as a calibrated sensor for robots: turn a scene graph and an utterance "
    '("I left my backpack on the table") into weighted hypotheses and a Gaussian mixture over the '
    "target's 3-D position."
)


# Bodies that routes read themselves (JSON off the event loop, or JSON and msgpack; `app.api.bodies`) are
# referenced by hand in their OpenAPI.
_RAW_BODY_MODELS = (
    GroundRequest,
    SessionCreate,
    UtteranceIn,
    ObservationBatchJson,
    PackedArray,
    SensorModelIn,
    SensorModelOverride,
)


def openapi_with_raw_bodies(app: FastAPI) -> dict[str, Any]:
    """FastAPI's OpenAPI document plus the schemas of the raw-read bodies and the request examples
    (`app.api.examples`), built once."""
    if app.openapi_schema is None:
        spec = FastAPI.openapi(app)
        schemas = spec.setdefault("components", {}).setdefault("schemas", {})
        for model in _RAW_BODY_MODELS:
            schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            schemas.update(schema.pop("$defs", {}))
            schemas[model.__name__] = schema
        app.openapi_schema = add_request_examples(spec)
    return app.openapi_schema


async def purge_expired_sessions(services: Services) -> None:
    """Free idle sessions' memory now and then (they read as deleted from the moment they expire)."""
    interval = min(60.0, services.settings.session_ttl_s / 2)
    while True:
        await anyio.sleep(interval)
        if services.store is not None:
            try:
                purged = await services.store.purge_expired()
            except VLMapError as exc:  # a store outage: the next round tries again
                log.warning("session purge failed", extra={"error": str(exc)})
                continue
            if purged:
                log.info("purged expired sessions", extra={"sessions": purged})


async def start_up(services: Services, owns_store: bool) -> None:
    """Open the store, start the grounding workers (each loads the local models) and describe or load the
    sensors: the service is ready when `services.sensors` and `services.sessions` are set."""
    settings = services.settings
    if owns_store:
        services.use_store(await anyio.to_thread.run_sync(build_store, settings))
    if services.sensors is None:
        if settings.worker_processes > 0:  # the workers load the models (injected sensors stay here)
            workers = WorkerProcesses(settings, settings.worker_processes)
            await anyio.to_thread.run_sync(workers.start)
            services.worker_processes = workers
        in_workers = settings.worker_processes > 0
        build = partial(build_sensors, settings, services.metrics, in_workers=in_workers)
        services.sensors = await anyio.to_thread.run_sync(build)
    await anyio.to_thread.run_sync(freeze_startup_objects)
    log.info("ready", extra={"grounder": services.sensors.default, "store": settings.store})


async def start_up_or_stop(services: Services, owns_store: bool, stop: Callable[[], None] | None) -> None:
    """`start_up` in the background: if it fails (the data directory held by another service, a model file
    unreadable), the error is logged and kept for the 503s, which say so instead of "still loading", and
    `stop` is called: `vlmap serve` stops serving and exits 1, so that a supervisor restarts it."""
    try:
        await start_up(services, owns_store)
    except Exception as exc:
        services.startup_error = str(exc) or type(exc).__name__
        log.critical("start-up failed", extra={"error": services.startup_error}, exc_info=exc)
        if stop is not None:
            stop()


def create_app(
    settings: Settings | None = None,
    sensors: Sensors | None = None,
    store: SessionStore | None = None,
    *,
    start_in_background: bool = False,
    on_startup_failure: Callable[[], None] | None = None,
) -> FastAPI:
    """Build the service. `sensors` and `store` override what the settings describe (tests, benchmarks).

    `start_in_background`: serve at once while the models load (`/healthz` answers, `/readyz` and the
    routes that need the models or the store answer 503 until they are loaded), as `vlmap serve` does so
    that an orchestrator can tell "starting" from "dead"; otherwise the app is ready when it starts.
    `on_startup_failure`: called if that background start-up fails (after the error is logged and kept).
    """
    settings = settings or get_settings()
    services = Services(settings=settings, metrics=Metrics(), sensors=sensors, store=store)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owns_store = services.store is None
        async with anyio.create_task_group() as tasks:
            if start_in_background:
                tasks.start_soon(start_up_or_stop, services, owns_store, on_startup_failure)
            else:
                await start_up(services, owns_store)
            tasks.start_soon(purge_expired_sessions, services)
            try:
                yield
            finally:
                tasks.cancel_scope.cancel()
                if services.sessions is not None:
                    await services.sessions.close()  # before the store it reads
                if services.worker_processes is not None:
                    await anyio.to_thread.run_sync(services.worker_processes.close)
                    services.worker_processes = None
                if owns_store and services.store is not None:
                    services.store.close()
                    services.store = services.sessions = None

    app = FastAPI(
        title="VL-Map",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        separate_input_output_schemas=False,
        dependencies=[Depends(reject_unknown_query)],
        # No redirect from /path/ to /path: it was built from the Host header, before any authentication.
        redirect_slashes=False,
        docs_url=None,  # FastAPI's /docs and /redoc load their assets from a CDN: `install_docs` serves ours
        redoc_url=None,
    )
    app.state.services = services
    app.openapi = lambda: openapi_with_raw_bodies(app)  # type: ignore[method-assign]
    install_error_handlers(app)
    install_docs(app)
    for module in (health, models, metrics, ground, scene_graphs, sessions, events, recordings, dashboard):
        app.include_router(module.router)
    app.add_middleware(FormAsJsonMiddleware)
    app.add_middleware(
        BodySizeLimitMiddleware,
        max_body_bytes=settings.max_body_bytes,
        body_timeout_s=settings.body_timeout_s,
    )
    app.add_middleware(RequestContextMiddleware, metrics=services.metrics)  # outermost: sees every answer
    return app
