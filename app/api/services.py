"""What the routes need, built once per app: settings, metrics, the language sensor, a worker pool."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, TypeVar

import anyio.to_thread
from anyio import CapacityLimiter

from app.api.auth import KeyRing, RateLimiter
from app.api.observability import Metrics
from app.grounding.geometric import FixedGrounder, GeometricGrounder
from app.grounding.interfaces import Grounder
from app.grounding.lexical import LexicalProposer
from app.grounding.sensor import LanguageSensor
from app.settings import Settings
from app.stores import open_store
from app.stores.base import SessionStore

log = logging.getLogger("vlmap.services")
T = TypeVar("T")


def build_grounder(settings: Settings) -> Grounder:
    """The spatial grounder named by the settings."""
    if settings.grounder == "fixed":
        return FixedGrounder()
    return GeometricGrounder()


def build_sensor(settings: Settings, metrics: Metrics) -> LanguageSensor:
    proposer = LexicalProposer(max_hypotheses=settings.max_hypotheses)
    return LanguageSensor(proposer, build_grounder(settings), observer=metrics.observe_stage)


@dataclass
class Services:
    settings: Settings
    metrics: Metrics
    sensor: LanguageSensor | None = None
    store: SessionStore | None = None
    limiter: CapacityLimiter = field(init=False)
    keyring: KeyRing = field(init=False)
    rate_limiter: RateLimiter = field(init=False)

    def __post_init__(self) -> None:
        self.limiter = CapacityLimiter(self.settings.worker_threads)
        self.keyring = KeyRing.load(self.settings.api_keys_file, self.settings.api_keys)
        self.rate_limiter = RateLimiter(self.settings.rate_limit_per_s, self.settings.rate_limit_burst)

    def open_store(self) -> SessionStore:
        """The store the settings name (the memory store replays its log from data_dir first)."""
        s = self.settings
        return open_store(s.store, data_dir=s.data_dir, ttl_s=s.session_ttl_s)

    async def run(self, func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run CPU-bound work in the worker pool so the event loop keeps serving other requests."""
        return await anyio.to_thread.run_sync(partial(func, *args, **kwargs), limiter=self.limiter)
