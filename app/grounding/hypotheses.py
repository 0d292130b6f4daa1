"""Hypotheses h = (anchor object(s), relation) and their weights P(h | utterance, map)."""

from __future__ import annotations

from dataclasses import dataclass, field

from app.grounding.relations import Relation


@dataclass(frozen=True)
class Hypothesis:
    """One reading of the utterance: the target stands in `relation` to the anchor object(s)."""

    anchor_ids: tuple[str, ...]
    relation: Relation
    weight: float = 1.0
    region_id: str | None = None
    text: str = ""


@dataclass(frozen=True)
class UtteranceParse:
    """What the proposer read from the utterance."""

    target: str
    relation: Relation
    anchor_phrases: tuple[str, ...]
    relation_phrase: str = ""
    region_phrase: str | None = None
    attributes: tuple[str, ...] = ()
    # False when the relation was guessed ("near") from a spatial phrase the sensor does not model.
    relation_known: bool = True


@dataclass(frozen=True)
class Proposal:
    """The proposer's answer: weighted hypotheses summing to one, or none with the reason why."""

    parse: UtteranceParse
    hypotheses: tuple[Hypothesis, ...]
    grounded: bool = True
    reason: str | None = None
    extra: dict[str, float] = field(default_factory=dict)
