"""The two factors of the language sensor, as interfaces.

P(target | L, map) = sum_h P(target | h, map) * P(h | L, map): a `HypothesisProposer` gives the second
factor (weighted hypotheses), a `Grounder` the first: one density per hypothesis, a small Gaussian mixture
(one Gaussian for the hand-written grounders, a core and a wider tail for the LSM).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from app.grounding.hypotheses import Hypothesis, Proposal
from app.grounding.mixture import GaussianMixture
from app.scene_graph.model import SceneGraph


class SentenceEncoder(Protocol):
    """A frozen sentence encoder (the service's MiniLM, `app.lsm.text_encoder.TextEncoder`), named by the
    sha256 of its weights."""

    sha256: str

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Unit-norm embeddings, (len(texts), D)."""
        ...


@runtime_checkable
class HypothesisProposer(Protocol):
    """Reads the utterance against the map and returns weighted hypotheses."""

    name: str

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal: ...

    def describe(self) -> dict[str, Any]:
        """Name, version, config and parameters checksum, for /v1/models."""
        ...


@runtime_checkable
class Grounder(Protocol):
    """Spatial grounding: a density over the target's position for each hypothesis (weights summing to 1)."""

    name: str
    version: str

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]: ...

    def describe(self) -> dict[str, Any]:
        """Name, version, config and weights checksum, for /v1/models and model cards."""
        ...
