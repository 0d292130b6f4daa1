"""Utterance parsing: "I left my backpack on the table in the kitchen" -> target, relation, anchors, region.

Rule-based on purpose: it runs in well under a millisecond, offline, and every rule is visible here. People
write referring expressions in many sentences ("this is a brown chair. it is at the end of the table close
to the painting."), so the parse reads the whole utterance as noun phrases (mentions) and the spatial
phrases between them, and says how each mention constrains the target:

1. region mentions ("in the kitchen", "in the upstairs bedroom", "upstairs") are cut out first, so that
   their "in" is not read as a relation; the utterance is split into sentences;
2. mentions are the longest runs of words that name an object (`app.vocabulary.object_nouns`, and the
   map's own labels when the caller passes them), with the attribute words in front of them ("small white
   table"); relation phrases come from `RELATION_PHRASES` (the one relation table) and `EXTRA_PHRASES`
   (how Sr3D and people say closest, farthest and between); spatial phrases that name no relation we model
   ("behind", "in front of", "at the end of") read as "near" with `relation_known=False`;
3. the target is the first mention no relation phrase governs ("the chair closest to the door": the
   chair; "on the shelf there is a book": the book), or a pronoun ("it's under the sofa"); a later
   ungoverned mention of the target's class is the target named again ("... the black monitor sits on");
   a superlative said before the name is read after it ("the closest chair to the door" as "the chair
   closest to the door"), unless what follows is a side ("the farthest window to the right");
4. each relation phrase relates its *subject*, the nearest mention before it in the same clause (the
   target when there is none, or after a comma), to the mentions that follow it ("A and B", "A or B"). A
   relation of the target makes its relata *anchors*; a relation of another mention makes them *qualifiers*
   of that mention ("the cup is on the table next to the tv": the tv says which table);
5. "not", "n't", "never", "without" before a relation phrase negate it; left/right/front/behind words (or a
   viewpoint: "when facing the door") mark the relations of that clause view-dependent; "between A and B"
   pairs two anchors, "in the middle of A and B" too. The objects of a clause that opens a sentence with
   a viewpoint ("if you face the whiteboard, the bench is ...", "when facing the windows, the one on the
   left") are view-dependent anchors, not the target, unless nothing else names one ("the one on the
   left": a window). A viewpoint may be a sentence of its own ("Face the door. The table you want ...")
   or end without a comma where the description starts ("... facing the windows the correct one is",
   "face the fridge and then ...", "... the box you are looking for is ...");
6. a mention after the target that no relation phrase governs ("the ball is halfway up the stairs") is an
   anchor with an unknown relation (near); a relation phrase followed by no known object name keeps the
   words it governs as an unknown mention ("next to the spaceship").

The primary reading (`target`, `relation`, `anchor_phrases`: the first relation of the target and its
relata) is what the first parser gave; `mentions` hold everything.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from functools import lru_cache

from app.grounding.hypotheses import Mention, UtteranceParse
from app.grounding.relations import RELATION_PHRASES, Relation
from app.vocabulary import ROOM_WORDS, fold, lemmas, normalise, object_nouns, same_class

__all__ = [
    "ATTRIBUTE_WORDS",
    "COLOR_WORDS",
    "EXTRA_PHRASES",
    "MATERIAL_WORDS",
    "SHAPE_WORDS",
    "SIZE_WORDS",
    "VAGUE_PHRASES",
    "VIEW_PHRASES",
    "clean_target",
    "normalise",
    "parse_utterance",
    "split_attributes",
    "strip_determiners",
    "target_noun",
]

#: Spatial phrases for relations the sensor does not model, view-independent: read as "near", widened.
VAGUE_PHRASES: tuple[str, ...] = (
    "at the end of",
    "at the foot of",
    "at the side of",
    "on the side of",
    "to the side of",
    "on the opposite side of",
    "on the other side of",
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
    "has",
    "have",
    "having",
    "contains",
    "towards",
    "toward",
    "at",
    "surrounded by",
    "in the corner of",
    "in the middle of",
    "in the center of",
    "in the centre of",
)
#: Spatial phrases that need the speaker's viewpoint: read as "near", view-dependent.
VIEW_PHRASES: tuple[str, ...] = (
    "in front of",
    "in back of",
    "at the back of",
    "to the left of",
    "to the right of",
    "on the left of",
    "on the right of",
    "on the left side of",
    "on the right side of",
    "to the left side of",
    "to the right side of",
    "left of",
    "right of",
    "behind",
    "north of",
    "south of",
    "east of",
    "west of",
)
#: More ways to say relations we model (Sr3D's templates and people's words), beside RELATION_PHRASES.
EXTRA_PHRASES: dict[Relation, tuple[str, ...]] = {
    Relation.CLOSEST: ("closer to", "nearer to", "the closest to", "the nearest to"),
    Relation.FARTHEST: (
        "far from",
        "far away from",
        "farther from",
        "further from",
        "farthest away from",
        "furthest away from",
        "farther away from",
        "further away from",
        "most far from",
        "most distant from",  # VLA-3D's templates (`app.data.templates.VLA3D_PHRASES`)
        "away from",
    ),
    Relation.ON: (
        "on the top of",
        "sitting on top of",
        "placed on",
        "hanging on",
        "mounted on",
        "leaning on",
    ),
    Relation.IN: ("inside of", "stored in", "placed in"),
    Relation.BELOW: ("right under", "directly under", "directly below", "just below", "just under"),
    Relation.ABOVE: ("directly above", "right above", "just above", "up above", "hanging above"),
    Relation.NEAR: ("right next to", "near to", "close by", "next to each other with"),
}
# "in the middle of A and B" is between; of one thing ("of the room") it is a vague place.
_MIDDLE_PHRASES = frozenset({"in the middle of", "in the center of", "in the centre of"})
_REGION_QUALIFIERS = (
    "upstairs|downstairs|main|master|guest|spare|kids|kids'|children's|first|second|third|big|small|"
    "large|little|front|back|other|top|ground floor|upper|lower"
)


def _words(text: str) -> frozenset[str]:
    return frozenset(text.split())


#: Adjectives a speaker puts on an object ("the small table"); matched against SceneObject.attributes.
COLOR_WORDS = _words(
    "white black grey gray silver red blue navy green yellow orange brown beige tan pink purple "
    "violet gold golden cream teal turquoise maroon"
)
SIZE_WORDS = _words("small little tiny big large huge tall short long wide narrow low high")
MATERIAL_WORDS = _words("wooden wood metal metallic glass plastic leather fabric marble steel")
SHAPE_WORDS = _words("round square rectangular circular oval")
ATTRIBUTE_WORDS = COLOR_WORDS | SIZE_WORDS | MATERIAL_WORDS | SHAPE_WORDS
# Comparative and superlative forms read as their size word ("the biggest table" ranks by size).
_DEGREES = {
    f"{stem}{end}": base
    for base, stems in {
        "small": ("smaller", "smallest"),
        "big": ("bigger", "biggest"),
        "large": ("larger", "largest"),
        "tall": ("taller", "tallest"),
        "short": ("shorter", "shortest"),
        "long": ("longer", "longest"),
        "wide": ("wider", "widest"),
        "narrow": ("narrower", "narrowest"),
        "low": ("lower", "lowest"),
        "high": ("higher", "highest"),
        "little": ("littler", "littlest"),
        "tiny": ("tinier", "tiniest"),
        "huge": ("huger", "hugest"),
    }.items()
    for stem in stems
    for end in ("",)
}
# Words that may sit between a determiner and an attribute or a noun without ending the noun phrase.
_FILLERS = _words("light dark bright pale very rather quite kind sort of colored coloured shaped looking")

_LEAD_INS = re.compile(
    r"^(?:"
    r"(?:hey|ok|okay|so|please|robot|well|um|uh)\b"
    r"|i (?:think|believe|guess|mean|bet)\b"
    r"|i'm (?:pretty |quite |fairly )?sure\b|i am (?:pretty |quite |fairly )?sure\b"
    r"|(?:i|we) (?:have |had |must have |might have )?(?:left|put|placed|dropped|forgot|saw|keep|kept|lost)\b"
    r"|(?:can|could|would|will) you (?:please )?(?:find|get|fetch|bring me|grab|look for|check)\b"
    r"|you(?:'ll| will| can| should) (?:find|see)\b"
    r"|(?:go (?:and )?|please )?"
    r"(?:find|fetch|get|grab|bring me|look for|search for|locate|check|go to|look|select|choose|pick)\b"
    r"|there(?:'s| is| are)\b|it(?:'s| is)\b|they(?:'re| are)\b|where(?:'s| is| are)\b"
    r")\s*"
)
_DETERMINERS = re.compile(
    r"^(?:(?:the|a|an|my|our|your|his|her|their|some|this|that|these|those|both|one of the|one of|"
    r"the other|other|another)\s+)+"
)
_DETERMINER_WORDS = _words(
    "the a an my our your his her their some this that these those both other another one of its two "
    "three four several all any each"
)
# Words that end a target phrase but are not part of it: copulas, relative pronouns, relation modifiers.
_TARGET_TAIL = _words(
    "is are was were be been being should must might may will would that which who the one ones "
    "somewhere stored kept located placed left put sits lies stands hangs rests sitting lying "
    "standing hanging usually probably still now always just right up directly slightly also there"
)
_COPULAS = _words("is are was were it's they're")
_RELATIVE_PRONOUNS = _words("that which who")
_PRONOUNS = _words("it this that they them one ones itself")
# The speaker and the listener: "closest to you" is a viewpoint, not an object of the map.
_PERSONS = _words("you me us yourself myself")
_NEGATORS = _words("not n't never no nowhere nothing without neither nor isn't aren't wasn't weren't don't")
_VIEW_WORDS = _words("left right front behind facing leftmost rightmost")
_COORDINATORS = _words("and or")
# What may stand between a relation phrase and its relatum, or between two relata: "next to the other two".
_NOUN_PHRASE_GAP = (
    _DETERMINER_WORDS
    | ATTRIBUTE_WORDS
    | _FILLERS
    | _COORDINATORS
    | frozenset(_DEGREES)
    | _words("either neither the other same")
    # Which one of its kind: "on the top shelf", "nearest the front doors", "under the right window".
    | _words("top bottom middle center centre upper lower front back rear left right far inner outer")
)
# Names in the vocabulary that in an utterance name a place or nothing in particular, not an object.
_NOT_MENTIONS = frozenset(
    {"corner", "object", "thing", "item", "can", "hanging", *(lemmas(w) for w in ROOM_WORDS)}
)
# Words before "can" that make it a noun ("the can", "the white can"; not "a chair that can roll").
_BEFORE_A_NOUN = (_DETERMINER_WORDS - _words("that this")) | ATTRIBUTE_WORDS | _words("middle other")
# Words after a relation phrase that name a side or a part of the view, not an object ("on the far left").
_PLACE_WORDS = _words("far left right side top bottom end middle center centre corner front back edge way")
# Leading words of the anchor text that belong to the relation ("farthest away from", "near to").
_ANCHOR_HEAD = re.compile(r"^(?:(?:away|from|to|of)\s+)+")
_CLAUSE_END = re.compile(
    r"\s+(?:that|which|where|who|so|because|but|i think|i guess|i believe|please|right now|now|"
    r"somewhere|for me|again|too|as well|if you can|thanks|thank you)\b.*$"
)
# Any other words between a copula and a determiner: "the ball is halfway up the stairs".
_UNKNOWN_RELATION = re.compile(
    r"(?<=\s)(?:is|are|was|were|sits|lies|stands|hangs|rests)\s+"
    r"(?P<rel>[a-z']+(?:\s+[a-z']+){0,2}?)(?=\s+(?:the|a|an|my|our|your|his|her|their|this|that)\s)"
)
#: A clause that sets the speaker's viewpoint ("if you face the door", "when standing by the sink", "facing
#: the windows", "with your back to the bed"): its objects are view-dependent anchors, not the target
#: (step 5).
_VIEWPOINT_CLAUSE = re.compile(
    r"^(?:if|when|whenever|while|as|once|assuming)\b"
    r"|^(?:facing|standing|looking(?! for)|sitting|walking|entering|from|with (?:your|my|one's) back)\b"
    r"|^(?:staring|turn (?:around |and )?(?:to )?face|position yourself|sit (?:on|at|in|down)\b)"
    r"|^face (?:the|a|an|both|all|two|three|four|towards?|away)\b"
    r"|^stand (?:at|in|by|near|next|facing|so|with|on|between|behind|before|directly|from|up)\b"
)
#: The verb of an imperative viewpoint, which is not an object ("stand at the end of the bed").
_VIEWPOINT_VERB = re.compile(r"^(?:stand|sit|face|staring)\s")
#: Where a viewpoint said without a comma ends and the description starts: "when standing in the middle of
#: the room facing the windows | the correct one is on the left", "face the fridge | and then ...".
_VIEWPOINT_END = re.compile(
    r"\s(?:and then|then|the (?:correct|wanted|target)|the right one|the one|it is|it's|this is|choose|"
    r"select|pick|(?P<named>you want|you need|you're looking for|you are looking for))\s"
)
#: "the closest chair to the door": a superlative before the target's name, its relatum after to/from
#: ("the chair closest to the door"); the name may be one to four words long, without a verb or a new phrase.
_SPLIT_SUPERLATIVE = re.compile(
    r"\b(?P<sup>closest|nearest|farthest|furthest)\s+"
    r"(?P<name>(?:(?!(?:is|are|was|were|be|the|a|an|to|from|away|of|on|in|at|by|with|for|near|next|and|or|"
    r"that|which|it|itself|back|closest|nearest|farthest|furthest)\s)[a-z'/-]+\s+){1,4}?)"
    r"(?P<rel>(?:away\s+)?(?:to|from))\b"
    r"(?!\s+(?:the\s+|your\s+|my\s+)?(?:right|left|back|rear|front|far)\b)"  # a direction, not a relatum
)
_SENTENCE = re.compile(r"[.!?;:\n]+")
_COMMA = re.compile(r"\s*,\s*")
#: Share of words that must be English (in the vocabulary or common function words) to parse at all.
MIN_ENGLISH_SHARE = 0.5
_FUNCTION_WORDS = _words(
    "the a an is are was were be it its this that there here of on in at to by with from for and or not "
    "my your i you we they he she near next under over above below between left right front back behind "
    "side top bottom middle corner closest farthest furthest one two three find choose select pick look "
    "where which who what has have can could would should will please thanks wall room floor door window"
)


def strip_determiners(phrase: str) -> str:
    return _DETERMINERS.sub("", phrase.strip()).strip()


def split_attributes(phrase: str) -> tuple[tuple[str, ...], str]:
    """Leading attribute words and the noun they modify: "small white table" -> (("small", "white"), "table").

    The last word is always the noun ("the glass", "the light").
    """
    words = phrase.split()
    count = 0
    while count < len(words) - 1 and words[count] in ATTRIBUTE_WORDS:
        count += 1
    return tuple(words[:count]), " ".join(words[count:])


def clean_target(phrase: str) -> str:
    """The target noun phrase: no determiners in front, no copula or modifiers behind."""
    words = strip_determiners(phrase).split()
    # Nothing after a copula is the target's name ("the cat is sleeping", "my wallet it's").
    cut = next((i for i, w in enumerate(words) if w in _COPULAS), len(words))
    words = words[:cut]
    while words and words[-1] in _TARGET_TAIL:
        words.pop()
    return strip_determiners(" ".join(words))


# --- the phrase tables, as token sequences ---


@dataclass(frozen=True)
class _Phrase:
    relation: Relation
    known: bool
    view: bool
    text: str


@lru_cache(maxsize=1)
def _phrase_table() -> dict[tuple[str, ...], _Phrase]:
    table: dict[tuple[str, ...], _Phrase] = {}
    for phrase in VAGUE_PHRASES:
        table[tuple(phrase.split())] = _Phrase(Relation.NEAR, False, False, phrase)
    for phrase in VIEW_PHRASES:
        table[tuple(phrase.split())] = _Phrase(Relation.NEAR, False, True, phrase)
    for relation, phrases in (*RELATION_PHRASES.items(), *EXTRA_PHRASES.items()):
        for phrase in phrases:
            table[tuple(phrase.split())] = _Phrase(relation, True, False, phrase)
    return table


@lru_cache(maxsize=1)
def _longest_phrase() -> int:
    return max(len(k) for k in _phrase_table())


def _region_pattern(region_names: tuple[str, ...]) -> re.Pattern[str]:
    return _region_regex(tuple(sorted(set(region_names))))


_BOUNDARY_WORDS = sorted(
    {w.split()[0] for w in (*VAGUE_PHRASES, *VIEW_PHRASES)}
    | {p.split()[0] for ps in (*RELATION_PHRASES.values(), *EXTRA_PHRASES.values()) for p in ps}
    | {"is", "are", "was", "were", "should", "must", "might", "may", "there", "and", "or", "for", "please"}
    | {"now", "i", "somewhere", "that", "which", "where", "but", "so", "right", "just", "sits", "lies"}
)


@lru_cache(maxsize=256)
def _region_regex(region_names: tuple[str, ...]) -> re.Pattern[str]:
    """ "in the (upstairs) kitchen" at a phrase boundary (not "in the kitchen cabinet"), or "upstairs"."""
    names = sorted({n for n in (*region_names, *ROOM_WORDS) if n}, key=lambda n: (-len(n), n))
    alternation = "|".join(re.escape(n) for n in names)
    boundary = rf"(?=$|\s+(?:{'|'.join(re.escape(w) for w in _BOUNDARY_WORDS)})\b)"
    return re.compile(
        rf"(?:^|\s)(?:(?:in|inside|at|from|of|on)\s+(?:the\s+|my\s+|our\s+|this\s+|that\s+)?"
        rf"(?P<region>(?:(?:{_REGION_QUALIFIERS})\s+)*(?:{alternation}))(?:\s+(?P<after>upstairs|downstairs))?"
        rf"|(?P<storey>upstairs|downstairs)){boundary}"
    )


def _take_regions(text: str, region_names: tuple[str, ...]) -> tuple[str, list[str], list[str]]:
    """The text without its region mentions, the mentions ("upstairs bedroom", also for "the bedroom
    upstairs") in order, and the negated ones ("not in the kitchen") apart."""
    found: list[str] = []
    negated: list[str] = []
    pattern = _region_pattern(region_names)
    while (match := pattern.search(text)) is not None:
        region, after = match.group("region"), match.group("after")
        phrase = f"{after} {region}" if region and after else region or match.group("storey")
        before = text[: match.start()].split()
        (negated if _negated(before, len(before)) else found).append(phrase)
        text = " ".join((text[: match.start()] + " " + text[match.end() :]).split())
    return text, found, negated


def _strip_lead_ins(text: str) -> str:
    while True:
        shorter = _LEAD_INS.sub("", text, count=1).strip()
        if shorter == text:
            return text
        text = shorter


# --- mentions and relations in one sentence ---


@dataclass
class _Item:
    """A mention or a relation phrase found in a clause, by token position."""

    kind: str  # "mention" or "relation"
    start: int
    end: int
    phrase: str = ""  # a mention's attribute words and noun, as said
    noun: str = ""  # a mention's object name, lemmatised
    attributes: tuple[str, ...] = ()
    relation: _Phrase | None = None
    negated: bool = False


def _mention_spans(
    tokens: list[str], lexicon: frozenset[str], blocked: set[int]
) -> list[tuple[int, int, str]]:
    """Longest runs of up to 4 tokens whose lemmas name an object, outside relation phrases."""
    spans: list[tuple[int, int, str]] = []
    i = 0
    lemma = [lemmas(t) for t in tokens]
    while i < len(tokens):
        if i in blocked or tokens[i] in _DETERMINER_WORDS:
            i += 1
            continue
        for width in (4, 3, 2, 1):
            j = i + width
            if j > len(tokens) or any(k in blocked for k in range(i, j)):
                continue
            name = " ".join(lemma[i:j])
            adjective = width == 1 and tokens[i] in _FILLERS and j < len(tokens) and tokens[j] in COLOR_WORDS
            named = name not in _NOT_MENTIONS or (name == "can" and i > 0 and tokens[i - 1] in _BEFORE_A_NOUN)
            if name in lexicon and named and not adjective:
                spans.append((i, j, name))
                i = j
                break
        else:
            i += 1
    return spans


def _attributes_before(tokens: list[str], start: int) -> tuple[str, ...]:
    """The attribute words right before a mention (fillers such as "dark" or "very" skipped)."""
    found: list[str] = []
    k = start - 1
    while k >= 0 and (tokens[k] in ATTRIBUTE_WORDS or tokens[k] in _DEGREES or tokens[k] in _FILLERS):
        word = _DEGREES.get(tokens[k], tokens[k])
        if word in ATTRIBUTE_WORDS:
            found.append(word)
        k -= 1
    return tuple(reversed(found))


def _modifiers_before(tokens: list[str], start: int, blocked: set[int], floor: int) -> int:
    """Where a mention's words start: up to two unknown modifiers before its name ("cat toy") belong to it,
    function words, attributes, verbs and relation words do not."""
    k = start
    while (
        k > floor
        and start - k < 2
        and (k - 1) not in blocked
        and tokens[k - 1] not in _DETERMINER_WORDS
        and tokens[k - 1] not in _FUNCTION_WORDS
        and tokens[k - 1] not in _TARGET_TAIL
        and tokens[k - 1] not in ATTRIBUTE_WORDS
        and tokens[k - 1] not in _DEGREES
        and tokens[k - 1] not in _FILLERS
        and not tokens[k - 1].endswith(("ing", "ed", "'s", "n't"))
    ):
        k -= 1
    return k


def _negated(tokens: list[str], start: int) -> bool:
    """Whether a negator governs the relation phrase at `start`: one of the three words before it, with no
    verb "to be" or relative pronoun between them ("is not on", "not the one on"; not "the mug that isn't
    mine is on", whose "isn't" belongs to another clause)."""
    for token in reversed(tokens[max(0, start - 3) : start]):
        if token in _NEGATORS or token.endswith("n't"):
            return True
        if token in _COPULAS or token in _RELATIVE_PRONOUNS:
            return False
    return False


def _clause_items(tokens: list[str], lexicon: frozenset[str]) -> list[_Item]:
    """Relation phrases (longest first, left to right) and the mentions between them, in order."""
    table, longest = _phrase_table(), _longest_phrase()
    relations: list[_Item] = []
    i = 0
    while i < len(tokens):
        for width in range(min(longest, len(tokens) - i), 0, -1):
            phrase = table.get(tuple(tokens[i : i + width]))
            if phrase is not None:
                negated = _negated(tokens, i)
                relations.append(_Item("relation", i, i + width, relation=phrase, negated=negated))
                i += width
                break
        else:
            i += 1
    blocked = {k for r in relations for k in range(r.start, r.end)}
    merged: list[_Item] = []
    for a, b, name in _mention_spans(tokens, lexicon, blocked):
        if merged and merged[-1].end == a:
            # Adjacent names are one compound ("bay window table"): its noun is the last one.
            last = merged[-1]
            merged[-1] = replace(last, end=b, phrase=f"{last.phrase} {' '.join(tokens[a:b])}", noun=name)
            continue
        a = _modifiers_before(tokens, a, blocked, merged[-1].end if merged else 0)
        attributes = _attributes_before(tokens, a)
        said = " ".join((*attributes, *tokens[a:b]))
        merged.append(_Item("mention", a, b, phrase=said, noun=name, attributes=attributes))
    return sorted([*relations, *merged], key=lambda item: item.start)


def _unknown_relatum(tokens: list[str], start: int, stop: int) -> str:
    """The words a relation phrase governs when none names an object: up to the next clause word."""
    words: list[str] = []
    for token in tokens[start:stop]:
        if token in _COPULAS or token in _RELATIVE_PRONOUNS or token in ("where", "and", "or", "but", "so"):
            break
        words.append(token)
    # "furthest to the right": the leading "to" belongs to the relation, and "the right" names no object.
    phrase = clean_target(_ANCHOR_HEAD.sub("", " ".join(words[:4])))
    first = phrase.split()[0] if phrase else ""
    if not phrase or first in _PRONOUNS | _PERSONS or any(w in _PLACE_WORDS for w in phrase.split()):
        return ""
    return phrase


@dataclass
class _Sentence:
    tokens: list[str]
    items: list[_Item]
    view: bool


def _sentences(text: str) -> list[list[list[str]]]:
    """Sentences of the original text, each as clauses (split at commas), each a list of words."""
    out = []
    for sentence in _SENTENCE.split(text.lower().replace("’", "'")):
        clauses = [normalise(c).split() for c in _COMMA.split(sentence)]
        clauses = [c for c in clauses if c]
        if clauses:
            out.append(clauses)
    return out


def _split_viewpoint(clauses: list[list[str]]) -> list[list[str]]:
    """The clauses with a viewpoint that opens the sentence without a comma split off its first clause
    ("when standing by the door the correct one is on the left": "when standing by the door", "the correct
    one is on the left"); "and then" after it is dropped."""
    first = " ".join(clauses[0])
    if not _VIEWPOINT_CLAUSE.match(_strip_lead_ins(first)):
        return clauses
    end = _VIEWPOINT_END.search(first)
    if end is None:
        return clauses
    head, tail = first[: end.start()].split(), first[end.start() :].split()
    if end.group("named"):  # "... the box you are looking for is ...": the box starts the description
        start = next((k for k in range(len(head) - 1, max(len(head) - 5, -1), -1) if head[k] == "the"), None)
        if start is not None:
            head, tail = head[:start], head[start:] + tail
    if len(head) < 3:
        return clauses
    while tail and tail[0] in ("and", "then"):
        tail = tail[1:]
    return [head, *([tail] if tail else []), *clauses[1:]]


def _superlative_after_name(text: str) -> str:
    """ "the closest chair to the door" as "the chair closest to the door" (`_SPLIT_SUPERLATIVE`)."""
    return _SPLIT_SUPERLATIVE.sub(r"\g<name>\g<sup> \g<rel>", text)


# --- the whole utterance ---


def parse_utterance(
    utterance: str, region_names: tuple[str, ...] = (), object_names: tuple[str, ...] = ()
) -> UtteranceParse:
    """Read an utterance: its target, every mention and how it constrains the target, the regions named.

    `region_names` are the scene's region names, read through `normalise` as the utterance is ("Living_Room"
    is "living room"); room words (`ROOM_WORDS`: "kitchen", "garage") are read as regions too.
    `object_names` (lemmatised labels of the map) join the vocabulary of object names. With no relation word
    at all, the whole utterance names the target and the relation is "near" with no anchor.
    """
    utterance = fold(utterance)  # full-width forms and accents as plain letters, punctuation included
    lexicon = object_nouns() | frozenset(object_names)
    region_names = tuple(normalise(n) for n in region_names)
    regions: list[str] = []
    excluded: list[str] = []  # regions the utterance rules out ("not in the kitchen")
    mentions: list[Mention] = []
    target_index: int | None = None
    view_any = False
    english_words = total_words = 0
    viewpoint: int | None = None  # the first mention of a viewpoint clause: the target if none is named
    sentences = [_split_viewpoint(clauses) for clauses in _sentences(utterance)]
    for number, clauses in enumerate(sentences):
        sentence_view = any(w in _VIEW_WORDS for c in clauses for w in c)
        more = len(clauses) > 1 or number < len(sentences) - 1  # a viewpoint needs something after it
        for clause_number, words in enumerate(clauses):
            text, found, negated = _take_regions(" ".join(words), region_names)
            regions += found
            excluded += negated
            body = _superlative_after_name(_strip_lead_ins(text) if clause_number == 0 else text)
            from_viewpoint = clause_number == 0 and more and bool(_VIEWPOINT_CLAUSE.match(body))
            if from_viewpoint:
                body = _VIEWPOINT_VERB.sub("", body, count=1)
            tokens = body.split()
            total_words += len(words)
            english_words += sum(1 for w in words if w in _FUNCTION_WORDS or lemmas(w) in lexicon)
            items = _clause_items(tokens, lexicon)
            view_any |= sentence_view
            view_any |= from_viewpoint
            before = len(mentions)
            target_index = _read_clause(
                tokens,
                items,
                mentions,
                target_index,
                number,
                sentence_view or from_viewpoint,
                fresh_clause=clause_number > 0,
                names_target=not from_viewpoint,
            )
            # The viewpoint clause's first object name ("shoes", not "row of", in "facing the row of shoes").
            if from_viewpoint and viewpoint is None:
                viewpoint = next((k for k in range(before, len(mentions)) if mentions[k].known), None)
    if target_index is None and viewpoint is not None:  # "facing the windows, the one on the left": a window
        said = mentions[viewpoint]
        mentions[viewpoint] = Mention(
            said.phrase, said.noun, said.attributes, "target", sentence=said.sentence
        )
        target_index = viewpoint
    english = total_words == 0 or english_words / total_words >= MIN_ENGLISH_SHARE
    return _primary(utterance, region_names, mentions, target_index, regions, excluded, view_any, english)


def _relata(tokens: list[str], items: list[_Item], position: int) -> tuple[list[tuple[int, bool]], int]:
    """The relata of the relation phrase at `items[position]`: the mentions after it joined by "and"/"or"
    (only determiners, attributes and coordinators between them), up to the next relation phrase, as (item
    index, joined by "or"); and the index of the first item after them."""
    relata: list[tuple[int, bool]] = []
    cursor = position + 1
    last_end = items[position].end
    while cursor < len(items) and items[cursor].kind == "mention":
        gap = tokens[last_end : items[cursor].start]
        if relata and not any(w in _COORDINATORS for w in gap):
            break
        if any(w in _COPULAS for w in gap) or not all(w in _NOUN_PHRASE_GAP or w.isdigit() for w in gap):
            break
        relata.append((cursor, "or" in gap))
        last_end = items[cursor].end
        cursor += 1
    return relata, cursor


def _read_clause(
    tokens: list[str],
    items: list[_Item],
    mentions: list[Mention],
    target_index: int | None,
    sentence: int,
    view: bool,
    fresh_clause: bool,
    names_target: bool = True,
) -> int | None:
    """Add the clause's mentions to `mentions` (step 3-6 of the module docstring); returns the target's
    index (set by the first ungoverned mention when no target is known yet, unless the clause cannot name
    it: a viewpoint clause's objects are view-dependent anchors)."""
    subject: int | None = None  # the index of the latest mention of this clause
    governed: set[int] = set()
    position = 0
    while position < len(items):
        item = items[position]
        if item.kind == "mention" and position not in governed:
            index = len(mentions)
            if target_index is not None and same_class(item.noun, mentions[target_index].noun):
                subject = target_index  # the target named again ("... the black monitor sits on ...")
                position += 1
                continue
            if target_index is None and names_target:
                mentions.append(Mention(item.phrase, item.noun, item.attributes, "target", sentence=sentence))
                target_index = index
            else:
                # A noun after the target (or in a viewpoint clause) with no relation phrase: an anchor of an
                # unknown relation.
                mentions.append(
                    Mention(
                        item.phrase,
                        item.noun,
                        item.attributes,
                        "anchor",
                        Relation.NEAR,
                        "",
                        False,
                        view_dependent=view,
                        sentence=sentence,
                    )
                )
            subject = index
            position += 1
            continue
        if item.kind != "relation" or item.relation is None:
            position += 1
            continue
        phrase = item.relation
        relata, cursor = _relata(tokens, items, position)
        head = subject if subject is not None else target_index
        role = "anchor" if head is None or head == target_index else "qualifier"
        relation, known = phrase.relation, phrase.known
        if phrase.text in _MIDDLE_PHRASES:  # "in the middle of A and B", or of the plural "the desks"
            plural = (
                len(relata) == 1
                and lemmas(tokens[items[relata[0][0]].end - 1]) != tokens[items[relata[0][0]].end - 1]
            )
            relation, known = (
                (Relation.BETWEEN, True) if len(relata) == 2 or plural else (Relation.NEAR, False)
            )
        first = len(mentions)
        if not relata:
            unknown = _unknown_relatum(
                tokens, item.end, items[cursor].start if cursor < len(items) else len(tokens)
            )
            if unknown:
                mentions.append(
                    Mention(
                        unknown,
                        split_attributes(unknown)[1],
                        split_attributes(unknown)[0],
                        role,
                        relation,
                        phrase.text if known else "",
                        known,
                        head if role == "qualifier" else None,
                        negated=item.negated,
                        view_dependent=view or phrase.view,
                        sentence=sentence,
                        known=False,
                    )
                )
        for k, (at, disjunct) in enumerate(relata):
            relatum = items[at]
            partner = None
            if relation is Relation.BETWEEN and len(relata) >= 2 and k < 2:
                partner = first + (1 - k)
            mentions.append(
                Mention(
                    relatum.phrase,
                    relatum.noun,
                    relatum.attributes,
                    role,
                    relation,
                    phrase.text if known else "",
                    known,
                    head if role == "qualifier" else None,
                    partner,
                    item.negated,
                    view or phrase.view,
                    disjunct,
                    sentence,
                )
            )
            governed.add(at)
        if relata:
            subject = first + len(relata) - 1
        position = cursor
    return target_index


def _primary(
    utterance: str,
    region_names: tuple[str, ...],
    mentions: list[Mention],
    target_index: int | None,
    regions: list[str],
    excluded: list[str],
    view: bool,
    english: bool,
) -> UtteranceParse:
    """The parse with its primary reading: the target's first relation and that relation's relata; where
    the mentions find no target name, the words before the first relation phrase (the first parser's rule)."""
    target = mentions[target_index] if target_index is not None else None
    anchors = [m for m in mentions if m.role == "anchor"]
    first = anchors[0] if anchors else None
    group: list[Mention] = []
    if first is not None:
        for m in anchors[anchors.index(first) :]:
            if (
                m.relation is not first.relation
                or m.sentence != first.sentence
                or (group and not (m.disjunct or m.partner is not None or first.relation is Relation.BETWEEN))
            ):
                break
            group.append(m)
            if len(group) == 2:
                break
    target_text = target.phrase if target is not None else _fallback_target(utterance, region_names)
    if target is None and target_text:  # a name the vocabulary lacks ("the cat is in the box")
        attributes, noun = split_attributes(target_text)
        said = Mention(target_text, lemmas(noun), attributes, "target", known=False)
        mentions = [said, *(_shift(m, 1) for m in mentions)]
    return UtteranceParse(
        target=target_text,
        relation=first.relation if first is not None and first.relation is not None else Relation.NEAR,
        anchor_phrases=tuple(m.phrase for m in group),
        relation_phrase=first.relation_phrase if first is not None else "",
        region_phrase=regions[0] if regions else None,
        attributes=tuple(a for m in group for a in m.attributes),
        relation_known=first.relation_known if first is not None else True,
        mentions=tuple(mentions),
        region_phrases=tuple(regions),
        excluded_region_phrases=tuple(excluded),
        target_attributes=target.attributes if target is not None else split_attributes(target_text)[0],
        sentences=max(1, len(_SENTENCE.split(utterance.strip(" .!?;\n")))),
        view_dependent=view,
        english=english,
    )


def _shift(mention: Mention, by: int) -> Mention:
    return replace(
        mention,
        head=None if mention.head is None else mention.head + by,
        partner=None if mention.partner is None else mention.partner + by,
    )


def _fallback_target(utterance: str, region_names: tuple[str, ...]) -> str:
    """The first parser's target: the words before the first relation phrase, cleaned."""
    text = normalise(utterance)
    text, _, _ = _take_regions(text, region_names)
    body = _superlative_after_name(_strip_lead_ins(text))
    tokens = body.split()
    table, longest = _phrase_table(), _longest_phrase()
    for i in range(len(tokens)):
        for width in range(min(longest, len(tokens) - i), 0, -1):
            if tuple(tokens[i : i + width]) in table:
                return clean_target(" ".join(tokens[:i]))
    match = _UNKNOWN_RELATION.search(body)
    return clean_target(body[: match.start()] if match else body)


@lru_cache(maxsize=4096)  # the LSM reads it beside the proposer's own parse; robots repeat themselves
def target_noun(utterance: str, region_names: tuple[str, ...] = ()) -> str:
    """The target's name, what the spatial grounder reads of it: the longest object name of the vocabulary
    that ends the target phrase, singular ("my old black backpacks ..." -> "backpack", "the kitchen cabinets"
    -> "kitchen cabinet"), else the phrase without its attribute words. Words that say nothing of where it
    is ("old", "favourite", a plural) so never reach the model."""
    said = split_attributes(parse_utterance(utterance, region_names).target)[1]
    words = lemmas(said).split()
    nouns = object_nouns()
    for start in range(len(words)):
        if " ".join(words[start:]) in nouns:
            return " ".join(words[start:])
    return said
