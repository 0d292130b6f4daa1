"""Hypotheses h = (anchor object(s), relation) and their weights P(h | utterance, map)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from app.grounding.mixture import UniformBox
from app.grounding.relations import Relation
from app.vocabulary import NamedRegion, regions_said

#: The smallest weight of the broad "I may have misunderstood" term in every served mixture: the density is
#: never below MIN_BACKGROUND_WEIGHT / vol(map box) inside the map's box, so never more than
#: log(1 / MIN_BACKGROUND_WEIGHT) = 3.9 nats worse than a uniform density over the map, whatever was said.
MIN_BACKGROUND_WEIGHT = 0.02


@dataclass(frozen=True)
class Hypothesis:
    """One reading of the utterance: the target stands in `relation` to the anchor object(s)."""

    anchor_ids: tuple[str, ...]  # empty: a region hypothesis (the target in `region_id`, or in the map)
    relation: Relation
    weight: float = 1.0
    region_id: str | None = None
    text: str = ""
    spread: float = 1.0  # covariance multiplier: > 1 widens a vague or view-dependent reading


#: Roles of a mention: the target itself, an anchor of the target, a qualifier of another mention (which
#: object of its kind: "the table next to the tv"), or a noun attached to nothing.
MENTION_ROLES = ("target", "anchor", "qualifier", "other")


@dataclass(frozen=True)
class Mention:
    """One noun phrase of the utterance that may name a mapped object, with how it constrains the target.

    `relation` is how the mention's head (the target for an anchor, mention `head` for a qualifier) stands
    to it: "the cup is on the table" gives the table (anchor, on); "... the table next to the tv" the tv
    (qualifier of the table, near). "between" pairs two mentions (`partner`). `negated`: said not to hold
    ("not on the table"); `view_dependent`: left/right/front/behind, which need a viewpoint nobody gave;
    `known`: the phrase is in the vocabulary of object names (else an unknown word in an object's place).
    """

    phrase: str  # attribute words and noun as said, lemmatised: "small white table"
    noun: str  # the noun alone: "table"
    attributes: tuple[str, ...]
    role: str  # one of MENTION_ROLES
    relation: Relation | None = None
    relation_phrase: str = ""
    relation_known: bool = True
    head: int | None = None  # for a qualifier: the index of the mention it qualifies
    partner: int | None = None  # for "between": the other anchor's index
    negated: bool = False
    view_dependent: bool = False
    disjunct: bool = False  # joined to the previous relatum by "or": one of several alternatives
    sentence: int = 0
    known: bool = True


@dataclass(frozen=True)
class UtteranceParse:
    """What the proposer read from the utterance.

    The first fields are the primary reading (the target, its first relation and that relation's anchor
    phrases); `mentions` hold the whole utterance's noun phrases and how each constrains the target.
    """

    target: str
    relation: Relation
    anchor_phrases: tuple[str, ...]
    relation_phrase: str = ""
    region_phrase: str | None = None
    attributes: tuple[str, ...] = ()
    # False when the relation was guessed ("near") from a spatial phrase the sensor does not model.
    relation_known: bool = True
    mentions: tuple[Mention, ...] = ()
    region_phrases: tuple[str, ...] = ()  # every region mention, the first being `region_phrase`
    excluded_region_phrases: tuple[str, ...] = ()  # regions ruled out ("not in the kitchen"), not above
    target_attributes: tuple[str, ...] = ()
    sentences: int = 1
    view_dependent: bool = False  # some relation needs a viewpoint
    english: bool = True  # False when too few words are English

    @property
    def anchors(self) -> tuple[Mention, ...]:
        """The mentions that anchor the target (negated ones included)."""
        return tuple(m for m in self.mentions if m.role == "anchor")

    def region_ids(self, regions: Sequence[NamedRegion]) -> tuple[set[str] | None, set[str] | None]:
        """(ids of the map's regions the utterance puts the target in; ids of those it rules out), each None
        where there are none (`regions_said`). The first are the regions named less those ruled out, or,
        where it names none, every region it does not rule out ("not in the kitchen": one of the others)."""
        excluded = regions_said(regions, self.excluded_region_phrases)
        named = regions_said(regions, self.region_phrases)
        if excluded is not None:
            named = (named if named is not None else {r.id for r in regions}) - excluded or None
        return named, excluded


@dataclass(frozen=True)
class Proposal:
    """The proposer's answer: weighted hypotheses summing to one (or none), whether an anchor was found
    (`grounded`, else the `reason`), and the broad term: its weight `background` (at least
    MIN_BACKGROUND_WEIGHT where the sensor serves it) and the areas a negation rules out (`avoid`)."""

    parse: UtteranceParse
    hypotheses: tuple[Hypothesis, ...]
    grounded: bool = True
    reason: str | None = None
    extra: dict[str, float] = field(default_factory=dict)
    background: float = MIN_BACKGROUND_WEIGHT
    avoid: tuple[UniformBox, ...] = ()
