"""Utterance parsing: "I left my backpack on the table in the kitchen" -> target, relation, anchors, region.

Rule-based on purpose: it runs in microseconds, offline, and every rule is visible here. The relation
vocabulary is `RELATION_PHRASES`; the first relation phrase (by position, longest on ties) splits the
utterance into the target phrase before it and the anchor phrase after it.
"""

from __future__ import annotations

import re
from functools import lru_cache

from app.grounding.hypotheses import UtteranceParse
from app.grounding.relations import RELATION_PHRASES, Relation

_LEAD_INS = re.compile(
    r"^(?:(?:hey|ok|okay|so|please|robot)[, ]+)*"
    r"(?:i (?:think |believe |guess )?(?:left|put|placed|dropped|forgot|saw|keep|kept|have left)"
    r"|(?:can|could|would) you (?:find|get|fetch|bring me|look for)"
    r"|(?:go |please )?(?:find|fetch|get|grab|bring me|look for|search for|locate)"
    r"|there (?:is|are|'s)|it(?:'s| is)|they(?:'re| are)|where(?:'s| is))\b\s*"
)
_DETERMINERS = re.compile(r"^(?:(?:the|a|an|my|our|your|his|her|their|some|this|that|one of the|one of)\s+)+")
_COPULA = re.compile(
    r"\s+(?:is|are|was|were|should be|must be|might be|may be|sits|lies|stands|hangs|rests)$"
)
_TRAILING = re.compile(r"\s+(?:please|now|somewhere|i think|right now|for me)$")
_REGION_SPLIT = re.compile(r"\s+(?:in|inside|of|at|from) (?:the |my |our )?(?P<region>[a-z ]+)$")
_WORD = re.compile(r"[a-z0-9']+")


@lru_cache(maxsize=1)
def _relation_pattern() -> re.Pattern[str]:
    phrases = sorted(((p, r) for r, ps in RELATION_PHRASES.items() for p in ps), key=lambda pr: -len(pr[0]))
    alternation = "|".join(re.escape(p) for p, _ in phrases)
    return re.compile(rf"\b(?P<rel>{alternation})\b")


_PHRASE_TO_RELATION = {p: r for r, ps in RELATION_PHRASES.items() for p in ps}


def normalise(text: str) -> str:
    """Lower case, plain spaces, no punctuation except apostrophes."""
    return " ".join(_WORD.findall(text.lower().replace("’", "'")))


def strip_determiners(phrase: str) -> str:
    return _DETERMINERS.sub("", phrase.strip()).strip()


def parse_utterance(utterance: str, region_names: tuple[str, ...] = ()) -> UtteranceParse:
    """Split an utterance into target phrase, relation and anchor phrase(s).

    `region_names` (lower case) lets a trailing "in the kitchen" be read as a region rather than part of
    the anchor. With no relation word at all, the whole utterance names the target and the relation is
    "near" with no anchor.
    """
    text = normalise(utterance)
    body = _LEAD_INS.sub("", text)
    match = _relation_pattern().search(body)
    if match is None:
        return UtteranceParse(target=strip_determiners(body), relation=Relation.NEAR, anchor_phrases=())
    relation_phrase = match.group("rel")
    relation = _PHRASE_TO_RELATION[relation_phrase]
    target = _COPULA.sub("", strip_determiners(body[: match.start()].strip())).strip()
    target = _COPULA.sub("", target)
    rest = _TRAILING.sub("", body[match.end() :].strip())

    region_phrase = None
    region_match = _REGION_SPLIT.search(rest)
    if region_match and _matches_region(region_match.group("region"), region_names):
        region_phrase = region_match.group("region").strip()
        rest = rest[: region_match.start()].strip()

    if relation is Relation.BETWEEN:
        parts = re.split(r"\s+and\s+", rest, maxsplit=1)
        anchors = tuple(strip_determiners(p) for p in parts if strip_determiners(p))
    else:
        # "the chair closest to the door": relation words before the anchor are already consumed.
        anchors = (strip_determiners(rest),) if strip_determiners(rest) else ()
    return UtteranceParse(
        target=target,
        relation=relation,
        anchor_phrases=anchors,
        relation_phrase=relation_phrase,
        region_phrase=region_phrase,
    )


def _matches_region(phrase: str, region_names: tuple[str, ...]) -> bool:
    words = set(phrase.split())
    return any(name and (name == phrase or set(name.split()) <= words) for name in region_names)
