"""Utterance parsing: "I left my backpack on the table in the kitchen" -> target, relation, anchors, region.

Rule-based on purpose: it runs in microseconds, offline, and every rule is visible here. The steps:

1. a region mention ("in the kitchen", "in the upstairs bedroom", "upstairs") is cut out first, so that its
   "in" is not read as the relation;
2. lead-ins ("I think I put", "can you get", "there is") are stripped from the front;
3. the first relation phrase (by position, longest on ties) splits the rest into the target phrase before it
   and the anchor phrase(s) after it. Relation phrases come from `RELATION_PHRASES`, the one relation table;
   spatial phrases that name no relation we model ("behind", "in front of", "at") read as "near" with
   `relation_known=False` and an empty `relation_phrase`, so that a grounder can widen its prior;
4. fronted sentences ("on the shelf there is a book", "check between A and B for the mug") take the target
   from the clause after the anchor; modifiers of the relation ("just above", "farthest away from",
   "near to", "stored in") are absorbed;
5. the anchor phrase keeps its attribute words ("white table"), which are also listed in `attributes`;
   "between A and B" gives two anchor phrases, "on the table or the desk" two alternatives.
"""

from __future__ import annotations

import re
from functools import lru_cache

from app.grounding.hypotheses import UtteranceParse
from app.grounding.relations import RELATION_PHRASES, Relation

#: Spatial phrases for relations the sensor does not model: read as "near" with a wider prior.
VAGUE_PHRASES: tuple[str, ...] = (
    "in front of",
    "in back of",
    "at the back of",
    "at the end of",
    "at the foot of",
    "at the side of",
    "on the side of",
    "to the side of",
    "to the left of",
    "to the right of",
    "on the left of",
    "on the right of",
    "on the left side of",
    "on the right side of",
    "left of",
    "right of",
    "behind",
    "across from",
    "opposite to",
    "opposite of",
    "opposite",
    "facing",
    "along",
    "beyond",
    "past",
    "outside of",
    "outside",
    "amongst",
    "among",
    "amid",
    "with",
    "towards",
    "toward",
    "at",
)

#: Room words read as a region even when the scene graph names no such region ("in the garage").
ROOM_WORDS: tuple[str, ...] = (
    "kitchen",
    "bedroom",
    "bathroom",
    "living room",
    "dining room",
    "family room",
    "guest room",
    "laundry room",
    "utility room",
    "storage room",
    "conference room",
    "meeting room",
    "office",
    "hallway",
    "hall",
    "corridor",
    "garage",
    "basement",
    "attic",
    "lounge",
    "study",
    "nursery",
    "playroom",
    "lobby",
    "entrance",
    "entryway",
    "foyer",
    "porch",
    "balcony",
    "room",
    "apartment",
    "house",
)
_REGION_QUALIFIERS = (
    "upstairs|downstairs|main|master|guest|spare|kids|kids'|children's|first|second|third|big|small|"
    "large|little|front|back|other|top|ground floor|upper|lower"
)


def _words(text: str) -> frozenset[str]:
    return frozenset(text.split())


#: Adjectives a speaker puts on an anchor ("the small table"); matched against SceneObject.attributes.
COLOR_WORDS = _words(
    "white black grey gray silver red blue navy green yellow orange brown beige tan pink purple "
    "violet gold golden cream teal turquoise maroon"
)
SIZE_WORDS = _words("small little tiny big large huge tall short long wide narrow low high")
MATERIAL_WORDS = _words("wooden wood metal metallic glass plastic leather fabric marble steel")
SHAPE_WORDS = _words("round square rectangular circular oval")
ATTRIBUTE_WORDS = COLOR_WORDS | SIZE_WORDS | MATERIAL_WORDS | SHAPE_WORDS

_LEAD_INS = re.compile(
    r"^(?:"
    r"(?:hey|ok|okay|so|please|robot|well|um|uh)\b"
    r"|i (?:think|believe|guess|mean|bet)\b"
    r"|i'm (?:pretty |quite |fairly )?sure\b|i am (?:pretty |quite |fairly )?sure\b"
    r"|(?:i|we) (?:have |had |must have |might have )?(?:left|put|placed|dropped|forgot|saw|keep|kept|lost)\b"
    r"|(?:can|could|would|will) you (?:please )?(?:find|get|fetch|bring me|grab|look for|check)\b"
    r"|you(?:'ll| will| can| should) (?:find|see)\b"
    r"|(?:go (?:and )?|please )?"
    r"(?:find|fetch|get|grab|bring me|look for|search for|locate|check|go to|look)\b"
    r"|there(?:'s| is| are)\b|it(?:'s| is)\b|they(?:'re| are)\b|where(?:'s| is| are)\b"
    r")\s*"
)
_DETERMINERS = re.compile(
    r"^(?:(?:the|a|an|my|our|your|his|her|their|some|this|that|these|those|both|one of the|one of|"
    r"the other|other|another)\s+)+"
)
# Words that end a target phrase but are not part of it: copulas, relative pronouns, relation modifiers.
_TARGET_TAIL = _words(
    "is are was were be been being should must might may will would that which who the one ones "
    "somewhere stored kept located placed left put sits lies stands hangs rests sitting lying "
    "standing hanging usually probably still now always just right up directly slightly also there"
)
_COPULAS = _words("is are was were it's they're")
# Leading words of the anchor text that belong to the relation ("farthest away from", "near to").
_ANCHOR_HEAD = re.compile(r"^(?:(?:away|from|to|of)\s+)+")
# A clause after the anchor: the fronted target ("... there is a book", "... for the mug") or a remark.
_FRONTED_TARGET = re.compile(r"\s+(?:there(?:'s| is| are)|for)\s+(?P<target>.+)$")
_CLAUSE_END = re.compile(
    r"\s+(?:that|which|where|who|so|because|but|i think|i guess|i believe|please|right now|now|"
    r"somewhere|for me|again|too|as well|if you can|thanks|thank you)\b.*$"
)
# Any other words between a copula and a determiner: "the ball is halfway up the stairs".
_UNKNOWN_RELATION = re.compile(
    r"(?<=\s)(?:is|are|was|were|sits|lies|stands|hangs|rests)\s+"
    r"(?P<rel>[a-z']+(?:\s+[a-z']+){0,2}?)(?=\s+(?:the|a|an|my|our|your|his|her|their|this|that)\s)"
)
_WORD = re.compile(r"[a-z0-9']+")


def normalise(text: str) -> str:
    """Lower case, plain spaces, no punctuation except apostrophes."""
    return " ".join(_WORD.findall(text.lower().replace("’", "'")))


def strip_determiners(phrase: str) -> str:
    return _DETERMINERS.sub("", phrase.strip()).strip()


_PHRASE_TO_RELATION = {p: r for r, ps in RELATION_PHRASES.items() for p in ps}


@lru_cache(maxsize=1)
def _relation_pattern() -> re.Pattern[str]:
    """All relation and vague phrases as one alternation, longest first (so "in front of" beats "in")."""
    phrases = sorted({*_PHRASE_TO_RELATION, *VAGUE_PHRASES}, key=lambda p: (-len(p), p))
    alternation = "|".join(re.escape(p) for p in phrases)
    return re.compile(rf"\b(?P<rel>{alternation})\b")


_BOUNDARY_WORDS = sorted(
    {p.split()[0] for p in (*_PHRASE_TO_RELATION, *VAGUE_PHRASES)}
    | {"is", "are", "was", "were", "should", "must", "might", "may", "there", "and", "or", "for", "please"}
    | {"now", "i", "somewhere", "that", "which", "where", "but", "so", "right", "just", "sits", "lies"}
)


@lru_cache(maxsize=256)
def _region_pattern(region_names: tuple[str, ...]) -> re.Pattern[str]:
    """ "in the (upstairs) kitchen" at a phrase boundary (not "in the kitchen cabinet"), or "upstairs"."""
    names = sorted({n for n in (*region_names, *ROOM_WORDS) if n}, key=lambda n: (-len(n), n))
    alternation = "|".join(re.escape(n) for n in names)
    boundary = rf"(?=$|\s+(?:{'|'.join(re.escape(w) for w in _BOUNDARY_WORDS)})\b)"
    return re.compile(
        rf"(?:^|\s)(?:(?:in|inside|at|from|of|on)\s+(?:the\s+|my\s+|our\s+|this\s+|that\s+)?"
        rf"(?P<region>(?:(?:{_REGION_QUALIFIERS})\s+)*(?:{alternation}))"
        rf"|(?P<storey>upstairs|downstairs)){boundary}"
    )


def _take_region(text: str, region_names: tuple[str, ...]) -> tuple[str, str | None]:
    """The text without its first region mention, and the mention ("upstairs bedroom"), if any."""
    match = _region_pattern(tuple(sorted(set(region_names)))).search(text)
    if match is None:
        return text, None
    region = match.group("region") or match.group("storey")
    rest = (text[: match.start()] + " " + text[match.end() :]).strip()
    return " ".join(rest.split()), region


def _strip_lead_ins(text: str) -> str:
    while True:
        shorter = _LEAD_INS.sub("", text, count=1).strip()
        if shorter == text:
            return text
        text = shorter


def clean_target(phrase: str) -> str:
    """The target noun phrase: no determiners in front, no copula or modifiers behind."""
    words = strip_determiners(phrase).split()
    # Nothing after a copula is the target's name ("the cat is sleeping", "my wallet it's").
    cut = next((i for i, w in enumerate(words) if w in _COPULAS), len(words))
    words = words[:cut]
    while words and words[-1] in _TARGET_TAIL:
        words.pop()
    return strip_determiners(" ".join(words))


def split_attributes(phrase: str) -> tuple[tuple[str, ...], str]:
    """Leading attribute words and the noun they modify: "small white table" -> (("small", "white"), "table").

    The last word is always the noun ("the glass", "the light").
    """
    words = phrase.split()
    count = 0
    while count < len(words) - 1 and words[count] in ATTRIBUTE_WORDS:
        count += 1
    return tuple(words[:count]), " ".join(words[count:])


def _anchor_phrase(text: str) -> str:
    """One anchor noun phrase: no determiners, cut before a nested relation ("table by the window")."""
    phrase = strip_determiners(_ANCHOR_HEAD.sub("", text.strip()))
    nested = _relation_pattern().search(phrase)
    if nested is not None and nested.start() > 0:
        phrase = phrase[: nested.start()].strip()
    return strip_determiners(phrase)


def parse_utterance(utterance: str, region_names: tuple[str, ...] = ()) -> UtteranceParse:
    """Split an utterance into target phrase, relation and anchor phrase(s), region and anchor attributes.

    `region_names` (lower case) are the scene's region names; room words ("kitchen", "garage") are read as
    regions too. With no relation word at all, the whole utterance names the target and the relation is
    "near" with no anchor.
    """
    text, region_phrase = _take_region(normalise(utterance), region_names)
    body = _strip_lead_ins(text)
    match = _relation_pattern().search(body) or _UNKNOWN_RELATION.search(body)
    if match is None:
        return UtteranceParse(
            target=clean_target(body), relation=Relation.NEAR, anchor_phrases=(), region_phrase=region_phrase
        )
    said = match.group("rel")
    relation = _PHRASE_TO_RELATION.get(said, Relation.NEAR)
    known = said in _PHRASE_TO_RELATION
    target = clean_target(body[: match.start()])
    rest = body[match.end() :].strip()
    fronted = _FRONTED_TARGET.search(rest)
    if fronted is not None:
        if not target:
            target = clean_target(fronted.group("target"))
        rest = rest[: fronted.start()]
    rest = _CLAUSE_END.sub("", rest)

    separator = r"\s+and\s+" if relation is Relation.BETWEEN else r"\s+or\s+"
    parts = re.split(separator, rest, maxsplit=1)
    anchors = tuple(p for p in (_anchor_phrase(part) for part in parts) if p)
    attributes = tuple(word for a in anchors for word in split_attributes(a)[0])
    return UtteranceParse(
        target=target,
        relation=relation,
        anchor_phrases=anchors,
        relation_phrase=said if known else "",
        region_phrase=region_phrase,
        attributes=attributes,
        relation_known=known,
    )


def target_noun(utterance: str, region_names: tuple[str, ...] = ()) -> str:
    """The target's name as said, without determiners or attribute words: "my small black backpack ..."
    -> "backpack" (what the spatial grounder reads of the target)."""
    return split_attributes(parse_utterance(utterance, region_names).target)[1]
