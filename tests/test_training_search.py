"""`golden_section` against a brute-force grid search on unimodal functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.training.search import golden_section


@pytest.mark.parametrize(
    ("f", "low", "high"),
    [
        (lambda x: (x - 1.3) ** 2, -4.0, 4.0),
        (lambda x: math.exp(x) - 2.0 * x, -3.0, 3.0),  # minimum at log 2
        (lambda x: abs(x + 0.7) ** 1.5, -2.0, 1.0),
        (lambda x: x, 0.5, 2.0),  # monotone: the bracket's lower end
    ],
)
def test_golden_section_finds_the_grid_minimum(f, low: float, high: float) -> None:
    grid = np.linspace(low, high, 200_001)
    best = grid[int(np.argmin([f(float(x)) for x in grid]))]
    assert golden_section(f, low, high) == pytest.approx(best, abs=1e-4)
