"""Semantic label noise: what an imperfect segmenter reports for the voxels a camera observed.

For an observed voxel with true class c (an object's label, or "free") and target class T, the reported
label y is drawn as

    c = T:            y = T with prob. tp,  else a uniformly drawn other class of the vocabulary      (1)
    c != T, object:   y = T with prob. fp,  another non-target class (uniform, != c) with prob.
                      `confusion`, else y = c                                                          (2)
    c = free:         y = T with prob. fp,  else y = free                                              (3)

so P(y = T | c = T) = tp and P(y = T | c != T) = fp for every observed voxel, free ones included: exactly
the sensor model (tp, fp) that the belief service's vision update (its equation (4)) assumes, so pass
`LabelNoise.tp` and `LabelNoise.fp` to the session. Classes are compared the way the service compares them
(`app.vocabulary.class_key`: "Trash Can" == "trash can" == "trashcans"). Other objects of the target's
class are T too: they are the distractors that a class-level segmenter cannot tell from the target.

The vocabulary (classes that confusions may produce) defaults to the classes present in the labels; pass the
world's labels to keep it fixed across frames. Without another class available, (1) reports
`UNKNOWN_LABEL` and (2) keeps the true label.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from app.errors import InvalidInput
from app.sim.world import FREE_LABEL
from app.vocabulary import class_key

#: What a missed target voxel is reported as when the vocabulary holds no other class.
UNKNOWN_LABEL = "unknown"


@dataclass(frozen=True)
class LabelNoise:
    """Confusion model of a semantic segmenter: true/false-positive rates for the target class, and the rate
    at which other objects are mistaken for yet another class."""

    tp: float = 0.9
    fp: float = 0.05
    confusion: float = 0.05

    def __post_init__(self) -> None:
        rates = {"tp": self.tp, "fp": self.fp, "confusion": self.confusion}
        for name, value in rates.items():
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                msg = f"{name} must be a probability in [0, 1], got {value}"
                raise InvalidInput(msg, f"noise.{name}")
        if self.fp + self.confusion > 1.0:
            msg = f"fp + confusion must not exceed 1, got {self.fp} + {self.confusion}"
            raise InvalidInput(msg, "noise.confusion")

    def corrupt(
        self,
        labels: Sequence[str] | np.ndarray,
        target_label: str,
        rng: np.random.Generator,
        vocabulary: Sequence[str] | None = None,
    ) -> np.ndarray:
        """(M,) reported labels for (M,) true labels, drawn by equations (1)-(3)."""
        true = np.asarray(labels, dtype=str).reshape(-1)  # (M,)
        names, inverse = np.unique(true, return_inverse=True)
        target_key = class_key(target_label)
        vocab = sorted(
            {
                str(n)
                for n in (names if vocabulary is None else vocabulary)
                if n != FREE_LABEL and class_key(str(n)) != target_key
            }
        )
        # Reported labels are codes into `table`: first the vocabulary, then the rest.
        table = list(dict.fromkeys([*vocab, *(str(n) for n in names), target_label, UNKNOWN_LABEL]))
        code_of = {name: k for k, name in enumerate(table)}
        name_codes = np.array([code_of[str(n)] for n in names], dtype=np.int64)
        name_is_target = np.array([class_key(str(n)) == target_key for n in names], dtype=bool)
        codes = name_codes[inverse]  # (M,)
        is_target = name_is_target[inverse]
        is_free = (names == FREE_LABEL)[inverse]
        n_vocab = len(vocab)

        u = rng.random(len(true))  # (M,) one uniform per voxel decides its case
        missed = is_target & (u >= self.tp)
        if n_vocab:
            codes[missed] = rng.integers(n_vocab, size=int(missed.sum()))
        else:
            codes[missed] = code_of[UNKNOWN_LABEL]
        codes[~is_target & (u < self.fp)] = code_of[target_label]
        confused = ~is_target & ~is_free & (u >= self.fp) & (u < self.fp + self.confusion)
        own = codes[confused]  # codes below n_vocab are positions in the vocabulary
        in_vocab = own < n_vocab
        # Another class, uniformly: one of the n - 1 others (of all n when the own class is not among them).
        n_choices = np.where(in_vocab, n_vocab - 1, n_vocab)
        possible = n_choices > 0
        draw = np.floor(rng.random(len(own)) * n_choices).astype(np.int64)
        draw += in_vocab & (draw >= own)  # skip the own class
        codes[np.flatnonzero(confused)[possible]] = draw[possible]
        return np.asarray(table)[codes]
