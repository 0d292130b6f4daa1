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
