"""The spatial relations the language sensor understands, in one table."""

from __future__ import annotations

from enum import StrEnum


class Relation(StrEnum):
    """A spatial relation between the target and its anchor object(s)."""

    ON = "on"
    IN = "in"
    NEAR = "near"
    BETWEEN = "between"
    ABOVE = "above"
    BELOW = "below"
    CLOSEST = "closest"
    FARTHEST = "farthest"

    @property
    def n_anchors(self) -> int:
        """How many anchor objects the relation takes (two for "between", one otherwise)."""
        return 2 if self is Relation.BETWEEN else 1


#: How people say each relation, longest phrases first within a relation. The parser matches these as
#: whole words; a phrase found nowhere here reads as "near" with a wider prior.
RELATION_PHRASES: dict[Relation, tuple[str, ...]] = {
    Relation.BETWEEN: ("in between", "between"),
    Relation.CLOSEST: ("closest to", "nearest to", "closest", "nearest"),
    Relation.FARTHEST: ("farthest from", "furthest from", "farthest", "furthest"),
    Relation.ON: ("on top of", "on the top of", "sitting on", "lying on", "resting on", "onto", "on", "atop"),
    Relation.IN: ("inside of", "inside", "within", "into", "in"),
    Relation.BELOW: ("underneath", "beneath", "below", "under"),
    Relation.ABOVE: ("hanging over", "above", "over"),
    Relation.NEAR: (
        "next to",
        "close to",
        "right by",
        "beside",
        "besides",
        "alongside",
        "adjacent to",
        "near",
        "by",
        "around",
        "against",
    ),
}
