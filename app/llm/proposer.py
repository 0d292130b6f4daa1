"""The LLM hypothesis proposer: P(h | utterance, map) from a chat-completions model, checked against the map.

The model answers with up to five readings, each with anchor ids and a confidence in [0, 1] (the contract
in `app.llm.prompts`). Every reading is checked before it is used, and dropped (and counted) if it fails:

- its ids exist in the scene graph (ids may come back as JSON numbers: 7 reads as "7");
- its relation, read from the reading's sentence with the service's own parser (so "under" is below,
  "on top of" is on, "next to" is near), is one of near/between/above/below/in/on;
- it has exactly one anchor, or two different ones for "between", both in the same region;
- its confidence is a finite number (clipped to [0, 1]); the same anchors and relation twice keep the first.

The kept readings (the K = 5 most confident at most) are weighted by a softmax over their confidences,

    w_i = exp(c_i / T) / sum_j exp(c_j / T),

with temperature T = 1 by default: with c in [0, 1] the largest weight ratio is then e^(1/T) = e, so an
LLM's (often overconfident) certainty is softened into a hedge over every reading it found plausible.
Lower T follows the LLM's ranking more sharply.

When the endpoint fails (timeout, no connection, HTTP error, no JSON) or nothing valid is left, the
proposer logs a warning, calls `on_fallback(reason)` (the API counts `vlmap_llm_fallbacks_total{reason}`)
and answers with the fallback proposer instead, marking the proposal with extra["llm_fallback"] = 1.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from app.errors import LLMResponseError
from app.grounding.hypotheses import Hypothesis, Proposal
from app.grounding.interfaces import HypothesisProposer
from app.grounding.parsing import normalise, parse_utterance
from app.grounding.relations import Relation
from app.llm.client import UNAVAILABLE_REASONS, ChatClient, EndpointUnavailable
from app.llm.prompts import LLM_RELATIONS, MAX_HYPOTHESES, hypothesis_messages
from app.scene_graph.model import SceneGraph

log = logging.getLogger("vlmap.llm")

#: Labels `on_fallback` is called with.
FALLBACK_REASONS = (*UNAVAILABLE_REASONS, "malformed_reply", "no_valid_hypotheses")

_ALLOWED_RELATIONS = frozenset(Relation(r) for r in LLM_RELATIONS)


def softmax_weights(confidences: list[float] | np.ndarray, temperature: float = 1.0) -> np.ndarray:
    """w_i = exp(c_i / T) / sum_j exp(c_j / T), computed with the maximum subtracted for stability."""
    if temperature <= 0:
        msg = f"softmax temperature must be > 0, got {temperature}"
        raise ValueError(msg)
    scaled = np.asarray(confidences, dtype=np.float64) / temperature  # (H,)
    exp = np.exp(scaled - scaled.max())
    weights: np.ndarray = exp / exp.sum()
    return weights


def check_hypothesis(item: Any, scene_graph: SceneGraph) -> tuple[Hypothesis, float] | str:
    """One reading of the reply as (hypothesis, confidence), or the reason it is dropped."""
    if not isinstance(item, dict):
        return "not_an_object"
    ids = item.get("referred_object_id")
    if not isinstance(ids, list):
        ids = [ids]  # a lone id where a list was asked for: read it as a list of one
    anchor_ids = []
    for raw in ids:
        if isinstance(raw, bool) or not isinstance(raw, str | int):
            return "unknown_id"
        anchor_ids.append(str(raw))
    objects = {o.id: o for o in scene_graph.objects}
    if not anchor_ids or any(i not in objects for i in anchor_ids):
        return "unknown_id"

    sentence = item.get("utterance")
    if not isinstance(sentence, str):
        return "relation"
    reading = parse_utterance(sentence)
    if not reading.relation_phrase or reading.relation not in _ALLOWED_RELATIONS:
        return "relation"
    relation = reading.relation
    if len(set(anchor_ids)) != len(anchor_ids) or len(anchor_ids) != relation.n_anchors:
        return "id_count"
    regions = {objects[i].region_id for i in anchor_ids}
    if len(regions) != 1:
        return "regions_differ"

    confidence = _finite(item.get("confidence"))
    if confidence is None:
        return "confidence"
    hypothesis = Hypothesis(
        anchor_ids=tuple(anchor_ids), relation=relation, region_id=regions.pop(), text=sentence.strip()
    )
    return hypothesis, min(max(confidence, 0.0), 1.0)


def _finite(value: Any) -> float | None:
    """A JSON number as a finite float, else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # JSON integers are unbounded: one past the float range is no usable number
        return None
    return number if math.isfinite(number) else None


def read_hypotheses(
    reply: dict[str, Any], scene_graph: SceneGraph, max_hypotheses: int = MAX_HYPOTHESES
) -> tuple[list[tuple[Hypothesis, float]], Counter[str]]:
    """The valid readings of a reply (the `max_hypotheses` most confident) and why the others were dropped."""
    items = reply.get("hypotheses")
    if not isinstance(items, list):
        msg = 'LLM reply has no "hypotheses" list'
        raise LLMResponseError(msg)
    dropped: Counter[str] = Counter()
    kept: list[tuple[Hypothesis, float]] = []
    seen: set[tuple[frozenset[str], Relation]] = set()
    for item in items:
        checked = check_hypothesis(item, scene_graph)
        if isinstance(checked, str):
            dropped[checked] += 1
            continue
        key = (frozenset(checked[0].anchor_ids), checked[0].relation)
        if key in seen:
            dropped["duplicate"] += 1
            continue
        seen.add(key)
        kept.append(checked)
    kept.sort(key=lambda hc: -hc[1])  # stable: ties keep the LLM's order
    if len(kept) > max_hypotheses:
        dropped["beyond_limit"] += len(kept) - max_hypotheses
    return kept[:max_hypotheses], dropped


class LLMProposer:
    """Hypotheses from a chat-completions LLM, validated against the map, with a fallback proposer."""

    name = "llm"

    def __init__(
        self,
        client: ChatClient,
        fallback: HypothesisProposer,
        *,
        max_hypotheses: int = MAX_HYPOTHESES,
        temperature: float = 1.0,
        on_fallback: Callable[[str], None] | None = None,
    ) -> None:
        if not 1 <= max_hypotheses <= MAX_HYPOTHESES:
            msg = f"max_hypotheses must be between 1 and {MAX_HYPOTHESES}, got {max_hypotheses}"
            raise ValueError(msg)
        if temperature <= 0:
            msg = f"softmax temperature must be > 0, got {temperature}"
            raise ValueError(msg)
        self.client = client
        self.fallback = fallback
        self.max_hypotheses = max_hypotheses
        self.temperature = temperature
        self.on_fallback = on_fallback

    def describe(self) -> dict[str, Any]:
        """The endpoint (never its key), the softmax temperature and the fallback proposer."""
        config = {
            "endpoint": self.client.endpoint.describe(),
            "temperature": self.temperature,
            "max_hypotheses": self.max_hypotheses,
            "fallback": self.fallback.name,
        }
        return {"name": self.name, "version": "1", "config": config, "checksum": None}

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        region_names = tuple(normalise(r.name) for r in scene_graph.regions if r.name)
        parse = parse_utterance(utterance, region_names)
        try:
            reply = self.client.complete_json(
                hypothesis_messages(scene_graph, utterance, self.max_hypotheses)
            )
            kept, dropped = read_hypotheses(reply, scene_graph, self.max_hypotheses)
        except EndpointUnavailable as exc:
            return self._fall_back(scene_graph, utterance, exc.reason, str(exc))
        except LLMResponseError as exc:
            return self._fall_back(scene_graph, utterance, "malformed_reply", str(exc))
        if dropped:
            log.info("LLM proposer dropped %d hypotheses: %s", sum(dropped.values()), dict(dropped))
        if not kept:
            detail = f"none of the {sum(dropped.values())} hypotheses was valid: {dict(dropped)}"
            return self._fall_back(scene_graph, utterance, "no_valid_hypotheses", detail)
        weights = softmax_weights([c for _, c in kept], self.temperature)
        hypotheses = tuple(
            dataclasses.replace(h, weight=float(w)) for (h, _), w in zip(kept, weights, strict=True)
        )
        extra = {
            "llm_hypotheses_returned": float(len(kept) + sum(dropped.values())),
            "llm_hypotheses_dropped": float(sum(dropped.values())),
        }
        return Proposal(parse, hypotheses, extra=extra)

    def _fall_back(self, scene_graph: SceneGraph, utterance: str, reason: str, detail: str) -> Proposal:
        log.warning("LLM proposer falls back to %s (%s): %s", self.fallback.name, reason, detail)
        if self.on_fallback is not None:
            self.on_fallback(reason)
        proposal = self.fallback.propose(scene_graph, utterance)
        return dataclasses.replace(proposal, extra={**proposal.extra, "llm_fallback": 1.0})
