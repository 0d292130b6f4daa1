"""The one vocabulary: how object names are normalised, which names mean the same kind of thing, and which
words of an utterance can name an object at all.

Every part that compares names uses these functions: the belief (is this label the target's class?), the
proposers (which objects does "the bin" name?), the parser (which words of "this is a brown chair by the
window" are objects?), the case builder (how may a speaker call a labelled object?) and the simulator.

- `lemmas("Kitchen_Cabinets") == "kitchen cabinet"`: lower case, words split at case changes, underscores
  and dashes, each word singular.
- `class_key(name)`: one key per kind of object. Two names are the same class when their keys are equal:
  the same lemmas up to spaces ("trash can", "trashcans"), or two names of one `SYNONYM_GROUPS` entry
  ("sofa", "couch"). Groups are disjoint, so "same class" is an equivalence.
- `GENERIC_NAMES`: a word that covers several classes ("bag" covers backpack and handbag, "bin" the trash can
  and the recycling bin). A generic phrase names each of them loosely (`lexical_match` 1), never as the
  same class.
- `lexical_match(phrase, name)`: 2 for the same class, 1 for a looser naming (the same head noun, "table" and
  "coffee table", or a generic word on either side: the phrase "bag" for a backpack, the map's label
  "computer" for "the computer tower"), 0 otherwise.
- `object_nouns()`: the lemmatised names of things indoor maps hold (every label of the training layouts,
  the synonyms and the generic words), the parser's lexicon of possible mentions.
- `in_classes(label, names)`: whether a label, or its head noun, is of one of the classes a set of names
  names ("file cabinets" is a cabinet, "chest of drawers" a dresser and not a drawer): how the label
  policies of the box relations (`app.grounding.box_relations`: walls, containers, seats) and of the
  conventions read a map's labels.
- Regions: `ROOM_WORDS` (read as a region even when the map names none), `STOREY_WORDS`, and
  `regions_named(regions, phrase)`, the one rule for which of a map's regions a region phrase names (the
  proposers, the broad term), and `regions_said(regions, phrases)` for all of an utterance's phrases; the
  parser reads region names through `normalise`, as it reads utterances.

Same class, or a looser naming: the one rule for look-alikes. "Same class" (`class_key`) is an equivalence
over synonyms only; a generic word never makes two names the same class. The belief compares classes and
only classes: a robot label names the target when it is of the target's class, and a mapped object is a
look-alike (its voxels carry no label evidence, `app.belief.session.mapped_look_alikes`) only when it is of
the target's class. So with the target "backpack" a "bag" sighting is a sighting of another class, and a
mapped "bag" is not a look-alike: it may be the very backpack the robot looks for, and filtering it out
would make the target unfindable there (a label map that says only "bag" has no name for a backpack target
at all, and the session refuses it). Naming is looser (`lexical_match` 1): "the bag" in an utterance may
mean the backpack, so the proposers match it, the case builder may say it, and a session looking for a
backpack fuses an utterance about "the bag".
"""

from __future__ import annotations

import re
import unicodedata
from collections.abc import Sequence
from functools import cache, lru_cache
from pathlib import Path
from typing import Protocol

__all__ = [
    "GENERIC_NAMES",
    "ROOM_WORDS",
    "STOREY_WORDS",
    "SYNONYM_GROUPS",
    "NamedRegion",
    "class_key",
    "head_noun",
    "in_classes",
    "label_tokens",
    "lemmas",
    "lexical_match",
    "normalise",
    "object_nouns",
    "other_names",
    "regions_named",
    "regions_said",
    "same_class",
    "singular",
]

_IRREGULAR_PLURALS = {
    "shelves": "shelf",
    "halves": "half",
    "knives": "knife",
    "leaves": "leaf",
    "wolves": "wolf",
    "people": "person",
    "feet": "foot",
    "mice": "mouse",
    "dishes": "dish",
    "glasses": "glass",
    "clothes": "clothes",
    "pants": "pants",
    "shorts": "shorts",
    "scissors": "scissors",
}
# Irregular plurals that also end compounds ("bookshelves", "penknives"); the short ones ("feet", "mice") do
# not: they end unrelated words too.
_IRREGULAR_SUFFIXES = tuple(p for p in _IRREGULAR_PLURALS if len(p) >= 5)
# Words that end in "s" in the singular.
_SINGULAR_S = frozenset(
    {"glass", "bus", "gas", "lens", "canvas", "chess", "dress", "mattress", "news", "series"}
)
_WORD = re.compile(r"[a-z0-9']+")
_CAMEL = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")
_SEPARATORS = re.compile(r"[_\-/.]+")


def fold(text: str) -> str:
    """The text with compatibility forms and accents folded to plain letters ("ＭＵＧ" -> "MUG", "canapé" ->
    "canape", the same whether the accent is composed or not), so that a name matches however its
    characters were encoded; ASCII text is returned as it is."""
    if text.isascii():
        return text
    return "".join(c for c in unicodedata.normalize("NFKD", text) if not unicodedata.combining(c))


def normalise(text: str) -> str:
    """Lower case, accents folded (`fold`), plain spaces, no punctuation except apostrophes."""
    return " ".join(_WORD.findall(fold(text.replace("’", "'")).lower()))


def singular(word: str) -> str:
    """Rough English singular of one word ("boxes" -> "box", "chairs" -> "chair", "glass" stays,
    "bookshelves" -> "bookshelf")."""
    if word in _IRREGULAR_PLURALS:
        return _IRREGULAR_PLURALS[word]
    for plural in _IRREGULAR_SUFFIXES:
        if word.endswith(plural):
            return word[: -len(plural)] + _IRREGULAR_PLURALS[plural]
    if word in _SINGULAR_S:
        return word
    if len(word) > 4 and word.endswith("ies"):
        return word[:-3] + "y"
    if len(word) > 3 and word.endswith(("ches", "shes", "xes", "sses")):
        return word[:-2]
    if len(word) > 2 and word.endswith("s") and not word.endswith(("ss", "us", "is")):
        return word[:-1]
    return word


def label_tokens(text: str) -> tuple[str, ...]:
    """The singular words of a label or phrase: "KitchenCabinets" -> ("kitchen", "cabinet")."""
    spaced = _SEPARATORS.sub(" ", _CAMEL.sub(" ", text))
    return tuple(singular(w) for w in normalise(spaced).split())


@lru_cache(maxsize=1 << 16)
def lemmas(text: str) -> str:
    """Lower-case singular words: "Kitchen_Cabinets" -> "kitchen cabinet"."""
    return " ".join(label_tokens(text))


def head_noun(lemma_text: str) -> str:
    """The noun a phrase is about: its last word, or the word before "of" ("chest of drawer" -> "chest")."""
    words = lemma_text.split()
    if "of" in words[1:]:
        return words[words.index("of") - 1]
    return words[-1] if words else ""


#: Names of one kind of object (lemmatised; the first is the class's key). Disjoint groups.
SYNONYM_GROUPS: tuple[tuple[str, ...], ...] = tuple(
    tuple(group.split(", "))
    for group in (
        "couch, sofa, settee",
        "tv, television, tv screen, tv monitor",
        "refrigerator, fridge, refridgerator",
        "mini fridge, small fridge",
        "trash can, garbage can, trash bin, garbage bin, waste bin, wastebasket, rubbish bin, dustbin",
        "recycling bin, recycling",
        "cabinet, cupboard",
        "kitchen cabinet, kitchen cupboard",
        "nightstand, night stand, bedside table, night table",
        "dresser, chest of drawer",
        "bookshelf, bookcase, book shelf",
        "shelving unit, shelf unit",
        "armchair, arm chair, easy chair, sofa chair",
        "office chair, desk chair",
        "counter, countertop, kitchen counter, worktop",
        "cell phone, mobile phone, mobile, smartphone, cellphone",
        "telephone, landline",
        "end table, side table",
        "dining table, kitchen table",
        "coffee table, cocktail table",
        "rug, carpet",
        "monitor, computer screen, computer monitor, display",
        "laptop, notebook computer, laptop computer",
        "computer tower, pc, desktop computer",
        "backpack, rucksack, knapsack",
        "remote control, remote, tv remote",
        "bathtub, tub, bath",
        "toilet paper, toilet roll",
        "tissue box, box of tissue",
        "laundry hamper, hamper, laundry basket",
        "coffee maker, coffee machine",
        "whiteboard, white board, dry erase board",
        "mug, coffee mug",
        "pillow, cushion",
        "plant, house plant, houseplant, potted plant",
        "doorframe, door frame",
        "file cabinet, filing cabinet",
        "keychain, key, key ring",
        "clothes, clothing",
        "garbage bag, trash bag",
        "microwave, microwave oven",
        "stove, cooker",
        "sink, basin, washbasin",
        "wardrobe, armoire",
        "picture, photo, photograph",
        "alarm clock, clock radio",
        "tennis racket, racket",
        "baseball bat, bat",
        "dumbbell, weight",
        "wine bottle, bottle of wine",
        "soap bottle, soap dispenser",
        "basketball, ball",
        "blackboard, chalkboard",
        "blinds, window blind",
        "curtain, drape",
        "printer, printing machine",
    )
)

#: Generic words and the classes they may name (a looser match than a synonym; lemmatised).
GENERIC_NAMES: dict[str, tuple[str, ...]] = {
    "bag": ("backpack", "handbag", "purse", "paper bag", "plastic bag", "garbage bag", "bag"),
    "bin": ("trash can", "recycling bin", "storage bin"),
    "lamp": ("desk lamp", "floor lamp", "table lamp", "lamp"),
    "light": ("lamp", "ceiling light", "desk lamp", "floor lamp", "light"),
    "phone": ("cell phone", "telephone"),
    "screen": ("monitor", "tv", "projector screen"),
    "computer": ("computer tower", "laptop", "monitor"),
    "seat": ("chair", "office chair", "armchair", "stool", "bench", "couch"),
    "chair": ("chair", "armchair"),  # the others' head noun is "chair" already
    "couch": ("couch", "sofa chair", "loveseat"),
    "clock": ("alarm clock", "wall clock", "clock"),
    "shelf": ("bookshelf", "shelving unit", "shelf"),
    "board": ("whiteboard", "blackboard", "bulletin board", "board"),
    "basket": ("laundry hamper", "basket"),
    "container": ("box", "storage bin", "storage container", "bucket", "basket"),
    "cupboard": ("kitchen cabinet", "cabinet"),
    "table": ("dining table", "coffee table", "end table", "desk", "nightstand", "table"),
    "desk": ("desk", "table"),
}


def _group_index() -> dict[str, int]:
    index: dict[str, int] = {}
    for number, group in enumerate(SYNONYM_GROUPS):
        for name in group:
            key = lemmas(name)
            if key in index:
                msg = f"{name!r} is in two synonym groups; groups must be disjoint"
                raise ValueError(msg)
            index[key] = number
    return index


_GROUP = _group_index()


def _group_index_without_spaces() -> dict[str, int]:
    return {name.replace(" ", ""): number for name, number in _GROUP.items()}


_GROUP_WITHOUT_SPACES = _group_index_without_spaces()


@lru_cache(maxsize=1 << 16)
def class_key(name: str) -> str:
    """The key shared by every name of one kind of object ("Sofa", "couches" -> "couch"; "Trash_Can",
    "trashcans", "garbage bin" -> "trashcan"): the class's first name, lemmatised, without spaces."""
    lemma = lemmas(name).replace(" ", "")
    group = _GROUP_WITHOUT_SPACES.get(lemma)
    return lemmas(SYNONYM_GROUPS[group][0]).replace(" ", "") if group is not None else lemma


def same_class(a: str, b: str) -> bool:
    """Whether two names mean the same kind of object."""
    key = class_key(a)
    return bool(key) and key == class_key(b)


def other_names(name: str) -> tuple[str, ...]:
    """The other names of a name's class (what a speaker may say instead of the label)."""
    lemma = lemmas(name)
    group = _GROUP.get(lemma)
    return () if group is None else tuple(n for n in SYNONYM_GROUPS[group] if lemmas(n) != lemma)


def _generic_covers(phrase: str, name: str) -> bool:
    covered = GENERIC_NAMES.get(phrase)
    return covered is not None and any(class_key(c) == class_key(name) for c in covered)


@lru_cache(maxsize=1 << 16)
def lexical_match(phrase: str, name: str) -> int:
    """2: the same class; 1: a looser naming (same head noun, or a generic word covering it); 0: neither.

    Both arguments are lemmatised names.
    """
    if not phrase or not name:
        return 0
    if same_class(phrase, name):
        return 2
    looser = (
        head_noun(phrase) == head_noun(name)
        or same_class(head_noun(phrase), name)  # "mini fridge" for a "refrigerator"
        or same_class(phrase, head_noun(name))
        or _generic_covers(phrase, name)
        or _generic_covers(name, phrase)
        or _generic_covers(head_noun(phrase), name)  # "the blue bin" for a trash can
    )
    if looser:
        return 1
    return 0


@cache
def object_nouns() -> frozenset[str]:
    """Every lemmatised name the parser may read as a mention of an object (see the module docstring)."""
    path = Path(__file__).with_name("object_nouns.txt")
    lines = path.read_text(encoding="utf-8").splitlines()
    listed = {lemmas(line) for line in lines if line.strip() and not line.startswith("#")}
    listed.discard("")
    synonyms = {lemmas(n) for group in SYNONYM_GROUPS for n in group}
    generic = {lemmas(g) for g in GENERIC_NAMES} | {lemmas(c) for cs in GENERIC_NAMES.values() for c in cs}
    return frozenset(listed | synonyms | generic)


@lru_cache(maxsize=256)
def _class_keys(names: frozenset[str]) -> frozenset[str]:
    return frozenset(class_key(n) for n in names)


@lru_cache(maxsize=1 << 16)
def in_classes(label: str, names: frozenset[str]) -> bool:
    """Whether the label, or its head noun, is of one of the classes of `names` (any spelling of them:
    "Kitchen_Cabinets", "cupboards" and "file cabinet" are all of the class "cabinet"; "chest of drawers" is
    of "dresser", its head noun "chest" is not "drawer")."""
    keys = _class_keys(names)
    return class_key(label) in keys or class_key(head_noun(lemmas(label))) in keys


# --- regions ------------------------------------------------------------------------------------------------

#: Room words read as a region even when the map names no such region ("in the garage").
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
#: Storey words of a region phrase, and the side of the map they pick: +1 the upper regions, -1 the lower.
STOREY_WORDS: dict[str, float] = {
    "upstairs": 1.0,
    "upper": 1.0,
    "downstairs": -1.0,
    "lower": -1.0,
    "ground": -1.0,
}
#: Metres: regions whose centres lie closer in height than this are on one storey (a storey word keeps all).
STOREY_MIN_SPREAD = 1.0


class NamedRegion(Protocol):
    """What region matching reads of a map's region (`app.scene_graph.model.Region` is one)."""

    @property
    def id(self) -> str: ...

    @property
    def name(self) -> str: ...

    @property
    def center(self) -> Sequence[float]: ...


def regions_named(regions: Sequence[NamedRegion], phrase: str | None) -> set[str] | None:
    """Ids of the regions a region phrase names ("kitchen", "upstairs bedroom", "upstairs"), None if none.

    Regions match by shared lemmas of their names (normalised as utterances are: "Living_Room" is named by
    "living room" and "living rooms"); a storey word keeps those of them (or of all regions, if the phrase
    names no room) whose centre lies above (below) the middle of their heights, when the heights spread
    over `STOREY_MIN_SPREAD`.
    """
    if not phrase or not regions:
        return None
    words = normalise(phrase).split()
    storey = [STOREY_WORDS[w] for w in words if w in STOREY_WORDS]
    room_words = set(lemmas(" ".join(w for w in words if w not in STOREY_WORDS)).split())
    pool = [r for r in regions if room_words & set(lemmas(r.name).split())] if room_words else []
    if storey:
        pool = pool or ([] if room_words else list(regions))
        heights = [float(r.center[2]) for r in pool]
        if len(pool) > 1 and max(heights) - min(heights) > STOREY_MIN_SPREAD:
            middle = 0.5 * (min(heights) + max(heights))
            pool = [r for r, z in zip(pool, heights, strict=True) if (z - middle) * storey[0] > 0]
    return {r.id for r in pool} or None


def regions_said(regions: Sequence[NamedRegion], phrases: Sequence[str]) -> set[str] | None:
    """Ids of the regions an utterance's region phrases name together, None if none: each phrase's
    (`regions_named`), united ("in the kitchen or in the bedroom"); a phrase that is only a storey word
    qualifies the room phrases beside it ("in the bedroom, upstairs" is the upstairs bedroom)."""
    storeys = [p for p in phrases if p and set(normalise(p).split()) <= STOREY_WORDS.keys()]
    rooms = [p for p in phrases if p and p not in storeys]
    if storeys and rooms:
        phrases = [f"{storeys[0]} {p}" for p in rooms]
    ids = set().union(*(regions_named(regions, p) or set() for p in phrases))
    return ids or None
