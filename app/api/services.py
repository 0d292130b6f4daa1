"""What the routes need, built once per app: settings, metrics, the language sensors, the store, a pool."""

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
from app.errors import InvalidInput
from app.grounding.geometric import FixedGrounder, GeometricGrounder
from app.grounding.interfaces import Grounder
from app.grounding.lexical import LexicalProposer
from app.grounding.sensor import LanguageSensor
from app.settings import Settings
from app.stores import open_store
from app.stores.base import SessionStore

log = logging.getLogger("vlmap.services")
T = TypeVar("T")


@dataclass(frozen=True)
class Sensors:
    """The language sensors this service offers, one per grounder, all sharing one proposer."""

    by_grounder: dict[str, LanguageSensor]
    default: str

    @classmethod
    def of(cls, sensor: LanguageSensor) -> Sensors:
        return cls({sensor.grounder.name: sensor}, sensor.grounder.name)

    def get(self, grounder: str | None = None) -> LanguageSensor:
        """The sensor with this grounder (the default one when None)."""
        name = grounder or self.default
        if name not in self.by_grounder:
            msg = f"grounder {name!r} is not loaded in this service; available: {sorted(self.by_grounder)}"
            raise InvalidInput(msg, field="options.grounder")
        return self.by_grounder[name]


def build_sensors(settings: Settings, metrics: Metrics) -> Sensors:
    """Every grounder the settings allow, with the lexical proposer; the configured one is the default."""
    grounders: list[Grounder] = [GeometricGrounder(), FixedGrounder()]
    proposer = LexicalProposer(max_hypotheses=settings.max_hypotheses)
    sensors = {g.name: LanguageSensor(proposer, g, observer=metrics.observe_stage) for g in grounders}
    return Sensors(sensors, settings.grounder)


@dataclass
class Services:
    settings: Settings
    metrics: Metrics
    sensors: Sensors | None = None
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
