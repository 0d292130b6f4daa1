"""Utterance templates: how people say where something is, per relation.

The relation vocabulary is the grounding's table (`app.grounding.relations.RELATION_PHRASES`), with which the
parser reads utterances back; `RELATION_PHRASES` here is what the generator says: the vocabulary less the
phrases that do not fit a statement, plus a few generation-only phrasings (a vocabulary phrase with a modifier
the parser absorbs, "just above", "farthest away from"). Sentence frames differ by kind of relation: locative
("the mug is on the counter"), ternary ("the lamp is between the sofa and the armchair") and ordinal ("the
chair closest to the door"). Frames that speak of "my <thing>" are used only for portable targets. All
randomness comes from the caller's generator.
"""

from __future__ import annotations

import numpy as np

from app.grounding.relations import RELATION_PHRASES as VOCABULARY
from app.grounding.relations import Relation

# Vocabulary phrases that a statement "the mug is <rel> the anchor" does not use: motion words ("onto"),
# bare ordinals ("closest the door"), rare or target-specific variants ("hanging over", "besides").
_UNSPOKEN = frozenset(
    {
        "on the top of",
        "onto",
        "atop",
        "into",
        "besides",
        "alongside",
        "adjacent to",
        "around",
        "against",
        "hanging over",
        "closest",
        "farthest",
        "furthest",
    }
)
#: Generation-only phrasings: a vocabulary phrase with a modifier that the parser absorbs.
GENERATION_ONLY_PHRASES: dict[Relation, tuple[str, ...]] = {
    Relation.IN: ("stored in",),
    Relation.NEAR: ("right next to", "near to"),
    Relation.ABOVE: ("just above", "up above", "right above"),
    Relation.BELOW: ("just under",),
    Relation.FARTHEST: ("farthest away from", "furthest away from"),
}
#: What the generator says for each relation (drawn uniformly).
RELATION_PHRASES: dict[Relation, tuple[str, ...]] = {
    relation: tuple(p for p in VOCABULARY[relation] if p not in _UNSPOKEN)
    + GENERATION_ONLY_PHRASES.get(relation, ())
    for relation in Relation
}

# Other names people use for a labelled object; a phrase keeps the label itself most of the time.
LABEL_SYNONYMS: dict[str, tuple[str, ...]] = {
    "couch": ("sofa",),
    "sofa": ("couch",),
    "sofa chair": ("armchair",),
    "armchair": ("arm chair", "easy chair"),
    "office chair": ("desk chair",),
    "tv": ("television",),
    "television": ("tv",),
    "trash can": ("garbage can", "trash bin", "bin"),
    "garbage can": ("trash can", "bin"),
    "recycling bin": ("recycling",),
    "refrigerator": ("fridge",),
    "fridge": ("refrigerator",),
    "mini fridge": ("small fridge",),
    "nightstand": ("bedside table", "night stand"),
    "kitchen counter": ("counter",),
    "countertop": ("counter", "kitchen counter"),
    "cell phone": ("phone", "mobile"),
    "telephone": ("phone",),
    "end table": ("side table",),
    "side table": ("end table",),
    "dining table": ("kitchen table", "table"),
    "desk lamp": ("lamp",),
    "floor lamp": ("standing lamp", "lamp"),
    "house plant": ("plant", "potted plant"),
    "plant": ("potted plant", "houseplant"),
    "computer tower": ("computer", "pc"),
    "monitor": ("screen", "computer screen"),
    "backpack": ("bag", "rucksack"),
    "remote control": ("remote", "tv remote"),
    "alarm clock": ("clock",),
    "garbage bag": ("trash bag",),
    "toilet paper": ("toilet roll",),
    "tissue box": ("box of tissues", "tissues"),
    "keychain": ("keys",),
    "clothes": ("clothing",),
    "clothing": ("clothes",),
    "pillow": ("cushion",),
    "basketball": ("ball",),
    "tennis racket": ("racket",),
    "baseball bat": ("bat",),
    "dumbbell": ("weight",),
    "wine bottle": ("bottle of wine",),
    "soap bottle": ("soap",),
    "bathtub": ("tub", "bath"),
    "dresser": ("chest of drawers",),
    "shelving unit": ("shelves",),
    "bookshelf": ("bookcase",),
    "file cabinet": ("filing cabinet",),
    "kitchen cabinets": ("cupboards", "kitchen cupboards"),
    "kitchen cabinet": ("cupboard",),
    "cabinet": ("cupboard",),
    "laundry hamper": ("hamper", "laundry basket"),
    "coffee maker": ("coffee machine",),
    "coffee machine": ("coffee maker",),
    "whiteboard": ("white board",),
    "laptop": ("notebook computer",),
    "mug": ("coffee mug",),
}
SYNONYM_PROBABILITY = 0.3
# Nouns that take "some" rather than "a" ("there is some clothing on the bed").
MASS_NOUNS = frozenset({"clothing", "paper", "foil", "bread", "lettuce", "laundry", "furniture", "food"})

# {be}: is/are agreeing with the target; {pronoun_be}: it's/they're; {a_target}: "a mug", "an apple", "books".
_LOCATIVE = (
    "the {target} {be} {rel} the {anchor}",
    "the {target} that {be} {rel} the {anchor}",
    "there {be} {a_target} {rel} the {anchor}",
    "look for the {target} {rel} the {anchor}",
    "find the {target} {rel} the {anchor}",
    "can you get the {target} {rel} the {anchor}",
    "you'll find the {target} {rel} the {anchor}",
    "the {target} should be {rel} the {anchor}",
    "{rel} the {anchor} there {be} {a_target}",
    "{pronoun_be} {rel} the {anchor}",
)
_LOCATIVE_PERSONAL = (
    "I left my {target} {rel} the {anchor}",
    "my {target} {be} {rel} the {anchor}",
    "I think I put the {target} {rel} the {anchor}",
    "I'm pretty sure my {target} {be} {rel} the {anchor}",
)
_BETWEEN = (
    "the {target} {be} {rel} the {anchor} and the {anchor2}",
    "look for the {target} {rel} the {anchor} and the {anchor2}",
    "there {be} {a_target} {rel} the {anchor} and the {anchor2}",
    "find the {target} that {be} {rel} the {anchor} and the {anchor2}",
    "{pronoun_be} {rel} the {anchor} and the {anchor2}",
    "check {rel} the {anchor} and the {anchor2} for the {target}",
)
_BETWEEN_PERSONAL = (
    "I left my {target} {rel} the {anchor} and the {anchor2}",
    "my {target} {be} somewhere {rel} the {anchor} and the {anchor2}",
)
_ORDINAL = (
    "find the {target} {rel} the {anchor}",
    "the {target} {rel} the {anchor}",
    "the {target} that {be} {rel} the {anchor}",
    "I mean the {target} {rel} the {anchor}",
    "go to the {target} {rel} the {anchor}",
    "look for the {target} {rel} the {anchor}",
)
_ORDINAL_PERSONAL = ("my {target} {be} the one {rel} the {anchor}",)


def is_plural(phrase: str) -> bool:
    """Whether a noun phrase reads as plural ("books", "kitchen cabinets"), by its last word."""
    last = phrase.strip().rsplit(" ", 1)[-1].lower()
    return last.endswith("s") and not last.endswith(("ss", "us", "is", "as", "os"))


def indefinite(phrase: str) -> str:
    """The phrase with its indefinite article: "a mug", "an apple", "some paper", plurals bare ("books")."""
    if is_plural(phrase):
        return phrase
    if phrase.strip().rsplit(" ", 1)[-1].lower() in MASS_NOUNS:
        return f"some {phrase}"
    article = "an" if phrase[:1].lower() in "aeiou" else "a"
    return f"{article} {phrase}"


def noun_phrase(label: str, rng: np.random.Generator) -> str:
    """How the speaker names an object with this label: the label, sometimes one of its synonyms."""
    text = label.strip().lower()
    options = LABEL_SYNONYMS.get(text)
    if options and rng.random() < SYNONYM_PROBABILITY:
        return options[int(rng.integers(len(options)))]
    return text


def _frames(relation: Relation, portable: bool) -> tuple[str, ...]:
    if relation is Relation.BETWEEN:
        return _BETWEEN + (_BETWEEN_PERSONAL if portable else ())
    if relation in (Relation.CLOSEST, Relation.FARTHEST):
        return _ORDINAL + (_ORDINAL_PERSONAL if portable else ())
    return _LOCATIVE + (_LOCATIVE_PERSONAL if portable else ())


def render_utterance(
    relation: Relation,
    target_label: str,
    anchor_labels: tuple[str, ...],
    rng: np.random.Generator,
    *,
    portable: bool = False,
) -> str:
    """One utterance saying that the target stands in `relation` to the anchor(s).

    Two anchors with the same label read "the chair and the other chair".
    """
    if len(anchor_labels) != relation.n_anchors:
        msg = f"relation {relation.value!r} takes {relation.n_anchors} anchor(s), got {len(anchor_labels)}"
        raise ValueError(msg)
    frames = _frames(relation, portable)
    frame = frames[int(rng.integers(len(frames)))]
    phrases = RELATION_PHRASES[relation]
    target = noun_phrase(target_label, rng)
    anchor = noun_phrase(anchor_labels[0], rng)
    anchor2 = ""
    if relation is Relation.BETWEEN:
        same = anchor_labels[1].strip().lower() == anchor_labels[0].strip().lower()
        anchor2 = f"other {anchor}" if same else noun_phrase(anchor_labels[1], rng)
    plural = is_plural(target)
    return frame.format(
        target=target,
        a_target=indefinite(target),
        anchor=anchor,
        anchor2=anchor2,
        rel=phrases[int(rng.integers(len(phrases)))],
        be="are" if plural else "is",
        pronoun_be="they're" if plural else "it's",
    )
