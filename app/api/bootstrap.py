"""What a process builds at start-up, once: the language sensors (grounders and proposers, the models they
load) and the session store. Both the request process and the grounding workers build theirs here."""

from __future__ import annotations

import gc
from dataclasses import dataclass
from typing import Any

from app.api.observability import Metrics
from app.errors import InvalidInput, ModelUnavailable
from app.grounding.geometric import FixedGrounder, GeometricGrounder
from app.grounding.hypotheses import Hypothesis, Proposal
from app.grounding.interfaces import Grounder, HypothesisProposer
from app.grounding.lexical import LexicalProposer
from app.grounding.mixture import GaussianMixture
from app.grounding.sensor import DEFAULT_MAX_GROUNDED, LanguageSensor, StageObserver
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from app.stores import open_store
from app.stores.base import SessionStore


@dataclass(frozen=True)
class Sensors:
    """The grounders and proposers this service loaded; each request picks one of each, or the defaults."""

    grounders: dict[str, Grounder]
    proposers: dict[str, HypothesisProposer]
    default: str  # grounder
    default_proposer: str = "builtin"
    observer: StageObserver | None = None
    max_grounded: int = DEFAULT_MAX_GROUNDED

    def get(self, grounder: str | None = None, proposer: str | None = None) -> LanguageSensor:
        """The language sensor made of these (loaded) parts."""
        return LanguageSensor(
            _pick(self.proposers, proposer or self.default_proposer, "options.proposer"),
            _pick(self.grounders, grounder or self.default, "options.grounder"),
            observer=self.observer,
            max_grounded=self.max_grounded,
        )


def _pick(loaded: dict[str, Any], name: str, field: str) -> Any:
    if name not in loaded:
        kind = field.split(".")[-1]
        msg = f"{kind} {name!r} is not loaded in this service; available: {sorted(loaded)}"
        raise InvalidInput(msg, field=field)
    return loaded[name]


class WorkerServed:
    """A grounder or proposer that this process knows by its description only (read from its model files):
    the grounding worker processes load and run it (`app.api.workers`), so the request process does not
    hold a second copy of the models."""

    def __init__(self, description: dict[str, Any]) -> None:
        self._description = description
        self.name: str = description["name"]
        self.version: str = description["version"]

    def describe(self) -> dict[str, Any]:
        return dict(self._description)

    def _elsewhere(self) -> ModelUnavailable:
        msg = f"{self.name} runs in the grounding worker processes, which are not available"
        return ModelUnavailable(msg)

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        raise self._elsewhere()

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        raise self._elsewhere()


def _load_lsm(settings: Settings) -> Grounder:
    from app.lsm.grounder import LSMGrounder
    from app.lsm.text_encoder import default_text_encoder

    encoder = default_text_encoder(settings.text_encoder_precision)
    return LSMGrounder.load(settings.model_dir / "lsm", threads=settings.torch_threads, encoder=encoder)


def _load_builtin(settings: Settings) -> HypothesisProposer:
    from app.grounding.builtin import BuiltinProposer
    from app.lsm.text_encoder import default_text_encoder
    from app.vocabulary import object_nouns

    encoder = default_text_encoder(settings.text_encoder_precision)
    encoder.pin(sorted(object_nouns()))  # 590 nouns, 0.5 s: a new target name costs no MiniLM pass
    return BuiltinProposer.load(encoder)


def _describe_lsm(settings: Settings) -> Grounder:
    from app.lsm.checkpoint import describe_checkpoint

    return WorkerServed(describe_checkpoint(settings.model_dir / "lsm"))


def _describe_builtin(settings: Settings) -> HypothesisProposer:
    from app.grounding.builtin import DEFAULT_PARAMS_PATH, ProposerParams, describe_params

    return WorkerServed(describe_params(ProposerParams.load(DEFAULT_PARAMS_PATH)))


def build_sensors(settings: Settings, metrics: Metrics, *, in_workers: bool = False) -> Sensors:
    """The grounders named in `settings.grounders`, the built-in proposer and, with an endpoint, the LLM's.

    `in_workers`: grounding worker processes serve the local models, so this process describes the LSM and
    the built-in proposer from their files (`WorkerServed`) instead of loading them; the LLM parts run here
    and need the built-in proposer (their fallback) and the grounders loaded, so with an LLM endpoint
    everything is loaded.
    """
    described = in_workers and not settings.llm_url
    grounders: dict[str, Grounder] = {}
    for name in dict.fromkeys([settings.grounder, *settings.grounders]):
        if name == "geometric":
            grounders[name] = GeometricGrounder()
        elif name == "fixed":
            grounders[name] = FixedGrounder()
        elif name == "lsm":
            grounders[name] = _describe_lsm(settings) if described else _load_lsm(settings)
    builtin: HypothesisProposer
    if settings.proposer == "lexical":  # the uniform proposer: no model needed
        builtin = LexicalProposer(max_hypotheses=settings.max_hypotheses)
    else:
        builtin = _describe_builtin(settings) if described else _load_builtin(settings)
    proposers: dict[str, HypothesisProposer] = {"builtin": builtin}
    if settings.llm_url:
        from app.llm.baselines import LLMEndToEndGrounder, ScaffoldedLLMGrounder
        from app.llm.client import ChatClient, LLMEndpoint
        from app.llm.proposer import LLMProposer

        endpoint = LLMEndpoint(
            settings.llm_url, settings.llm_model, settings.llm_api_key, timeout_s=settings.llm_timeout_s
        )
        client = ChatClient(endpoint)
        proposers["llm"] = LLMProposer(
            client,
            builtin,
            max_hypotheses=settings.max_hypotheses,
            on_fallback=lambda reason: metrics.llm_fallbacks.labels(reason=reason).inc(),
        )
        grounders["scaffolded-llm"] = ScaffoldedLLMGrounder(client)
        grounders["llm-e2e"] = LLMEndToEndGrounder(client)
    return Sensors(
        grounders,
        proposers,
        settings.grounder,
        observer=metrics.observe_stage,
        max_grounded=settings.max_grounded_hypotheses,
    )


def build_store(settings: Settings) -> SessionStore:
    """The store the settings name (the memory store replays its log from data_dir first)."""
    return open_store(
        settings.store,
        data_dir=settings.data_dir,
        ttl_s=settings.session_ttl_s,
        mirror_mib=settings.store_mirror_mib,
        idempotency_window_s=settings.idempotency_window_s,
        idempotency_keys=settings.idempotency_keys_per_session,
    )


def freeze_startup_objects() -> None:
    """Exempt what start-up built (torch, transformers, the models: about 400k objects) from the cyclic
    garbage collector: a full collection scanning them takes hundreds of milliseconds, a pause for every
    request in flight, and requests' own garbage triggers one every few seconds under load."""
    gc.collect()
    gc.freeze()
