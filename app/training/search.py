"""One-dimensional minimisation shared by the fitting code."""

from __future__ import annotations

import math
from collections.abc import Callable


def golden_section(f: Callable[[float], float], low: float, high: float, iterations: int = 60) -> float:
    """The minimiser of a unimodal f on [low, high] by golden-section search: each step keeps the part of the
    bracket around the lower of two interior points, shrinking it by 1/phi = 0.618 (60 steps: 3e-13 of it)."""
    ratio = 0.5 * (math.sqrt(5.0) - 1.0)
    for _ in range(iterations):
        a, b = high - ratio * (high - low), low + ratio * (high - low)
        if f(a) < f(b):
            high = b
        else:
            low = a
    return 0.5 * (low + high)


__all__ = ["golden_section"]
