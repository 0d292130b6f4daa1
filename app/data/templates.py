"""Utterance templates: how people say where something is, per relation, in each convention's style.

vlmap style (`render_utterance`): the relation vocabulary is the grounding's table
(`app.grounding.relations.RELATION_PHRASES`), with which the parser reads utterances back; `RELATION_PHRASES`
here is what the generator says: the vocabulary less the phrases that do not fit a statement, plus a few
generation-only phrasings (a vocabulary phrase with a modifier the parser absorbs, "just above", "farthest
away from"). Sentence frames differ by kind of relation: locative ("the mug is on the counter"), ternary
("the lamp is between the sofa and the armchair") and ordinal ("the chair closest to the door"). Frames that
speak of "my <thing>" are used only for portable targets. Objects are named as the one vocabulary
(`app.vocabulary`) allows: the label, another name of its class, or a generic word that covers it.

Sr3D style (`render_sr3d`): ReferIt3D's templates and relation words
(`referit3d/data/language/sr3d/references_to_human_language.json`): "[find | choose | select] the <target>
that is <relation> the <anchor>", closest as "closer to / close to / near", or "next to / beside" when the
two are next to each other; farthest as "farthest from / far from / far away from"; between as "between",
or "in the middle of / in the center of" when the target is in the centre; objects named by their label.

VLA-3D style (`render_vla3d`): the language generator's template "the <target> that is <relation> the
<anchor>" with the README's synonyms per relation; objects named by their label.

All randomness comes from the caller's generator.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from functools import lru_cache

import numpy as np

from app.grounding.relations import RELATION_PHRASES as VOCABULARY
from app.grounding.relations import Relation
from app.vocabulary import GENERIC_NAMES, SYNONYM_GROUPS, lemmas, other_names, same_class

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

# How often a phrase names an object by another name of its class ("couch" for a sofa) or, less often, by a
# generic word that covers it ("the bin" for a trash can); the label itself otherwise.
SYNONYM_PROBABILITY = 0.3
GENERIC_PROBABILITY = 0.1
# Nouns that take "some" rather than "a" ("there is some clothing on the bed") and stay singular after "of".
MASS_NOUNS = frozenset(
    {"clothing", "paper", "foil", "bread", "lettuce", "laundry", "furniture", "food", "wine", "water"}
)

# {be}: is/are agreeing with the target; {a_target}: "a mug", "an apple", "books". Every frame names the
# target: a frame "it's on the table" would leave a case's target to the map alone.
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


def _spoken(name: str) -> str:
    """A vocabulary name as said: its words are lemmas, so the noun after "of" takes its plural again
    ("chest of drawer" -> "chest of drawers", "bottle of wine" stays)."""
    words = name.split()
    if "of" in words[1:-1]:
        k = words.index("of") + 1
        if k == len(words) - 1 and words[k] not in MASS_NOUNS:
            words[k] = words[k] + ("es" if words[k].endswith(("s", "x", "ch", "sh")) else "s")
    return " ".join(words)


@lru_cache(maxsize=1 << 14)
def class_names(label: str) -> tuple[str, ...]:
    """Other names of the label's class in the vocabulary, as a speaker says them ("couch" for "sofa")."""
    return tuple(_spoken(n) for n in other_names(label))


@lru_cache(maxsize=1 << 14)
def generic_names(label: str) -> tuple[str, ...]:
    """The vocabulary's generic words that cover the label's class ("bin" for "trash can")."""
    lemma = lemmas(label)
    return tuple(
        g
        for g, covered in GENERIC_NAMES.items()
        if g != lemma and any(same_class(c, label) for c in covered) and not same_class(g, label)
    )


def speaker_names(label: str) -> tuple[str, ...]:
    """Every other name a speaker may use for an object with this label: its class's names, then the
    generic words that cover it."""
    return tuple(dict.fromkeys(class_names(label) + generic_names(label)))


class _SpeakerNames(Mapping[str, tuple[str, ...]]):
    """`speaker_names` as a read-only mapping: looked up for any label, iterating over the vocabulary's names
    (for callers that ask which phrases the generator may say for a label)."""

    def __getitem__(self, label: str) -> tuple[str, ...]:
        names = speaker_names(label)
        if not names:
            raise KeyError(label)
        return names

    def __iter__(self) -> Iterator[str]:
        names = {n for group in SYNONYM_GROUPS for n in group}
        names |= {c for covered in GENERIC_NAMES.values() for c in covered}
        return iter(sorted(n for n in names if speaker_names(n)))

    def __len__(self) -> int:
        return sum(1 for _ in self)


#: The other names a phrase may use for a label (`speaker_names`), as a mapping.
LABEL_SYNONYMS: Mapping[str, tuple[str, ...]] = _SpeakerNames()


def noun_phrase(label: str, rng: np.random.Generator) -> str:
    """How the speaker names an object with this label: the label, sometimes another name of its class,
    less often a generic word that covers it."""
    text = label.strip().lower()
    draw = rng.random()
    same, generic = class_names(text), generic_names(text)
    if same and draw < SYNONYM_PROBABILITY:
        return same[int(rng.integers(len(same)))]
    if generic and draw > 1.0 - GENERIC_PROBABILITY:
        return generic[int(rng.integers(len(generic)))]
    return text


def _frames(relation: Relation, portable: bool) -> tuple[str, ...]:
    if relation is Relation.BETWEEN:
        return _BETWEEN + (_BETWEEN_PERSONAL if portable else ())
    if relation in (Relation.CLOSEST, Relation.FARTHEST):
        return _ORDINAL + (_ORDINAL_PERSONAL if portable else ())
    return _LOCATIVE + (_LOCATIVE_PERSONAL if portable else ())


def _check_anchors(relation: Relation, anchor_labels: tuple[str, ...]) -> None:
    if len(anchor_labels) != relation.n_anchors:
        msg = f"relation {relation.value!r} takes {relation.n_anchors} anchor(s), got {len(anchor_labels)}"
        raise ValueError(msg)


def render_utterance(
    relation: Relation,
    target_label: str,
    anchor_labels: tuple[str, ...],
    rng: np.random.Generator,
    *,
    portable: bool = False,
) -> str:
    """One utterance saying that the target stands in `relation` to the anchor(s).

    Two anchors of the same class read "the chair and the other chair".
    """
    _check_anchors(relation, anchor_labels)
    frames = _frames(relation, portable)
    frame = frames[int(rng.integers(len(frames)))]
    phrases = RELATION_PHRASES[relation]
    target = noun_phrase(target_label, rng)
    anchor = noun_phrase(anchor_labels[0], rng)
    anchor2 = ""
    if relation is Relation.BETWEEN:
        same = same_class(anchor_labels[1], anchor_labels[0])
        anchor2 = f"other {anchor}" if same else noun_phrase(anchor_labels[1], rng)
    plural = is_plural(target)
    return frame.format(
        target=target,
        a_target=indefinite(target),
        anchor=anchor,
        anchor2=anchor2,
        rel=phrases[int(rng.integers(len(phrases)))],
        be="are" if plural else "is",
    )


# Sr3D (references_to_human_language.json): the frames of every reference type, its relation words, and the
# NEXT_TO / IN_CENTER variants of closest and between.
_SR3D_FRAMES = (
    "the {target} that {be} {rel} the {anchor}",
    "find the {target} that {be} {rel} the {anchor}",
    "choose the {target} that {be} {rel} the {anchor}",
    "select the {target} that {be} {rel} the {anchor}",
)
_SR3D_NEXT_TO_FRAMES = (
    "the {target} that {be} {rel} the {anchor}",
    "find the {target} that {be} {rel} the {anchor}",
    "choose the {target} that {be} {rel} the {anchor}",
)
SR3D_PHRASES: dict[Relation, tuple[str, ...]] = {
    Relation.ON: ("on top of", "on", "lying on"),
    Relation.ABOVE: ("above", "over"),
    Relation.BELOW: ("below", "under", "beneath", "underneath"),
    Relation.FARTHEST: ("farthest from", "far from", "far away from"),
    Relation.CLOSEST: ("closer to", "close to", "near"),
}
SR3D_NEXT_TO_PHRASES = ("next to", "beside")
SR3D_BETWEEN_PHRASES = ("between",)
SR3D_IN_CENTER_PHRASES = ("in the middle of", "in the center of")

# VLA-3D: the language generator's one frame; relation words of its README table and relationship templates.
_VLA3D_FRAME = "the {target} that {be} {rel} the {anchor}"
VLA3D_PHRASES: dict[Relation, tuple[str, ...]] = {
    Relation.ABOVE: ("above", "over"),
    Relation.BELOW: ("below", "under", "beneath", "underneath"),
    Relation.CLOSEST: ("closest to", "nearest to"),
    Relation.FARTHEST: ("farthest from", "most distant from"),
    Relation.BETWEEN: ("in between", "in the middle of"),
    Relation.NEAR: ("near", "next to", "close to", "adjacent to", "beside"),
    Relation.IN: ("in", "inside", "within"),
    Relation.ON: ("on", "on top of"),
}


def _templated(frame: str, rel: str, target_label: str, anchor_labels: tuple[str, ...]) -> str:
    target = target_label.strip().lower()
    anchor = anchor_labels[0].strip().lower()
    if len(anchor_labels) == 2:
        second = anchor_labels[1].strip().lower()
        anchor = f"{anchor} and the {'other ' + anchor if same_class(second, anchor) else second}"
    return frame.format(target=target, anchor=anchor, rel=rel, be="are" if is_plural(target) else "is")


def render_sr3d(
    relation: Relation,
    target_label: str,
    anchor_labels: tuple[str, ...],
    rng: np.random.Generator,
    *,
    next_to: bool = False,
    in_center: bool = False,
) -> str:
    """One Sr3D-style reference: "choose the chair that is close to the door".

    `next_to` (closest only) and `in_center` (between only) choose the generator's variants for objects next
    to each other and for a target in the middle of its anchors.
    """
    _check_anchors(relation, anchor_labels)
    if relation is Relation.IN or relation is Relation.NEAR:
        msg = f"Sr3D has no {relation.value!r} reference"
        raise ValueError(msg)
    frames: tuple[str, ...] = _SR3D_FRAMES
    phrases: tuple[str, ...]
    if relation is Relation.BETWEEN:
        phrases = SR3D_IN_CENTER_PHRASES if in_center else SR3D_BETWEEN_PHRASES
    elif relation is Relation.CLOSEST and next_to:
        phrases, frames = SR3D_NEXT_TO_PHRASES, _SR3D_NEXT_TO_FRAMES
    else:
        phrases = SR3D_PHRASES[relation]
    frame = frames[int(rng.integers(len(frames)))]
    return _templated(frame, phrases[int(rng.integers(len(phrases)))], target_label, anchor_labels)


def render_vla3d(
    relation: Relation, target_label: str, anchor_labels: tuple[str, ...], rng: np.random.Generator
) -> str:
    """One VLA-3D-style statement: "the pillow that is on top of the bed"."""
    _check_anchors(relation, anchor_labels)
    phrases = VLA3D_PHRASES[relation]
    return _templated(_VLA3D_FRAME, phrases[int(rng.integers(len(phrases)))], target_label, anchor_labels)
