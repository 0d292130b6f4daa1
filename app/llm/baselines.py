"""The reference's foundation-model baseline grounders, for any chat-completions LLM.

- Scaffolded-LLM (`ScaffoldedLLMGrounder`): the hypotheses come from elsewhere; the LLM is asked once per
  hypothesis for a Gaussian over the target's position, {"mu", "sigma", "explanation"}.
- LLM-E2E (`LLMEndToEndGrounder`): the LLM gets only the map and the utterance and answers the whole
  mixture in one call, {"components": [{"mu", "sigma", "weight", "explanation"}]}.

The reference shows both badly overconfident; these exist to measure that, not to serve. Every covariance
the LLM writes is repaired as the reference does before use: symmetrised and projected onto the PD cone by
clipping its eigenvalues at 1e-2 m^2 (a 10 cm standard deviation),

    Sigma' = V diag(max(lambda_i, 1e-2)) V^T,   (lambda, V) = eig((Sigma + Sigma^T) / 2).

A reply with a non-finite number, a wrong shape or no JSON object raises `LLMResponseError`; the endpoint
failing raises `EndpointUnavailable`. Neither grounder falls back: a baseline's failure is part of its score.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np

from app.errors import LLMResponseError
from app.grounding.geometric import region_gaussian
from app.grounding.hypotheses import Hypothesis
from app.grounding.mixture import Gaussian, GaussianMixture, project_to_pd
from app.llm import prompts
from app.llm.client import ChatClient
from app.scene_graph.model import SceneGraph

#: The reference's eigenvalue floor for foundation-model covariances, m^2.
BASELINE_MIN_EIGENVALUE_M2 = 1e-2


def _numbers(value: Any, shape: tuple[int, ...], field: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: an integer past the float range
        msg = f"{field}: expected numbers of shape {shape}, got {str(value)[:80]}"
        raise LLMResponseError(msg) from exc
    if array.shape != shape:
        msg = f"{field}: expected shape {shape}, got {array.shape}"
        raise LLMResponseError(msg)
    if not np.all(np.isfinite(array)):
        msg = f"{field}: holds NaN or infinity"
        raise LLMResponseError(msg)
    return array


def repair_covariance(sigma: Any, field: str = "sigma") -> np.ndarray:
    """Sigma' = V diag(max(lambda_i, 1e-2)) V^T with (lambda, V) = eig((Sigma + Sigma^T) / 2); (3, 3)."""
    return project_to_pd(_numbers(sigma, (3, 3), field), BASELINE_MIN_EIGENVALUE_M2)


def read_gaussian(reply: Any, field: str = "reply") -> Gaussian:
    """N(mu, repaired sigma) from {"mu": [x, y, z], "sigma": [[3x3]], ...}."""
    if not isinstance(reply, dict):
        msg = f"{field}: expected an object with mu and sigma"
        raise LLMResponseError(msg)
    mean = _numbers(reply.get("mu"), (3,), f"{field}.mu")
    return Gaussian(mean, repair_covariance(reply.get("sigma"), f"{field}.sigma"))


def read_mixture(reply: dict[str, Any], max_components: int = prompts.MAX_HYPOTHESES) -> GaussianMixture:
    """sum_k w_k N(mu_k, Sigma_k) from {"components": [{"mu", "sigma", "weight"}, ...]}, weights normalised.

    More components than `max_components`: the heaviest are kept (and renormalised).
    """
    components = reply.get("components")
    if not isinstance(components, list) or not components:
        msg = 'reply: expected a non-empty "components" list'
        raise LLMResponseError(msg)
    weights, gaussians = [], []
    for index, component in enumerate(components):
        field = f"components[{index}]"
        gaussian = read_gaussian(component, field)
        weights.append(_weight(component.get("weight"), f"{field}.weight"))
        gaussians.append(gaussian)
    order = sorted(range(len(weights)), key=lambda k: -weights[k])[:max_components]
    largest = weights[order[0]]
    if largest <= 0:
        msg = "reply: every component weight is zero"
        raise LLMResponseError(msg)
    # Divided by the largest before they are normalised: weights near the float maximum overflow their sum.
    return GaussianMixture.from_components(
        [weights[k] / largest for k in order],
        [gaussians[k] for k in order],
        min_eigenvalue=BASELINE_MIN_EIGENVALUE_M2,
    )


def _weight(value: Any, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        msg = f"{field}: expected a finite number, got {value!r}"
        raise LLMResponseError(msg)
    try:
        weight = float(value)
    except OverflowError as exc:  # JSON integers are unbounded
        msg = f"{field}: expected a finite number, got an integer past the float range"
        raise LLMResponseError(msg) from exc
    if not math.isfinite(weight):
        msg = f"{field}: expected a finite number, got {value!r}"
        raise LLMResponseError(msg)
    if weight < 0:
        msg = f"{field}: must be >= 0, got {weight}"
        raise LLMResponseError(msg)
    return weight


def _prompt_checksum(*texts: str) -> str:
    return "sha256:" + hashlib.sha256("\n".join(texts).encode()).hexdigest()


class ScaffoldedLLMGrounder:
    """Scaffolded-LLM: one LLM call per hypothesis, each answering one Gaussian."""

    name = "scaffolded-llm"
    version = "1"

    def __init__(self, client: ChatClient) -> None:
        self.client = client

    def describe(self) -> dict[str, Any]:
        config = {**self.client.endpoint.describe(), "min_eigenvalue_m2": BASELINE_MIN_EIGENVALUE_M2}
        checksum = _prompt_checksum(prompts.SCAFFOLDED_SYSTEM_PROMPT, prompts.SCAFFOLDED_USER_TEMPLATE)
        return {"name": self.name, "version": self.version, "config": config, "checksum": checksum}

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        return [
            GaussianMixture.of(
                read_gaussian(
                    self.client.complete_json(prompts.scaffolded_messages(scene_graph, utterance, h))
                )
                if h.anchor_ids
                else region_gaussian(scene_graph, h.region_id),  # no anchor to ask about
                BASELINE_MIN_EIGENVALUE_M2,
            )
            for h in hypotheses
        ]


class LLMEndToEndGrounder:
    """LLM-E2E: one LLM call answering the whole mixture; the evaluation calls `ground_mixture`.

    Behind the `Grounder` protocol (`ground`), the mixture is asked for once per call and each hypothesis
    gets the component whose mean lies nearest (Euclidean) to the centroid of its anchors: the LLM's own
    Gaussian for that reading. The mixture's weights are then not used; the caller's hypothesis weights are.
    """

    name = "llm-e2e"
    version = "1"

    def __init__(self, client: ChatClient, max_components: int = prompts.MAX_HYPOTHESES) -> None:
        self.client = client
        self.max_components = max_components

    def describe(self) -> dict[str, Any]:
        config = {
            **self.client.endpoint.describe(),
            "min_eigenvalue_m2": BASELINE_MIN_EIGENVALUE_M2,
            "max_components": self.max_components,
        }
        checksum = _prompt_checksum(prompts.E2E_SYSTEM_PROMPT, prompts.E2E_USER_TEMPLATE)
        return {"name": self.name, "version": self.version, "config": config, "checksum": checksum}

    def ground_mixture(self, scene_graph: SceneGraph, utterance: str) -> GaussianMixture:
        messages = prompts.e2e_messages(scene_graph, utterance, self.max_components)
        return read_mixture(self.client.complete_json(messages), self.max_components)

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        if not hypotheses:
            return []
        mixture = self.ground_mixture(scene_graph, utterance)
        out = []
        for h in hypotheses:
            if not h.anchor_ids:  # a region hypothesis: no anchor to match a component to
                out.append(
                    GaussianMixture.of(region_gaussian(scene_graph, h.region_id), BASELINE_MIN_EIGENVALUE_M2)
                )
                continue
            centroid = np.mean([scene_graph.object(i).center for i in h.anchor_ids], axis=0)  # (3,)
            nearest = int(np.argmin(np.linalg.norm(mixture.means - centroid, axis=1)))
            out.append(GaussianMixture.of(mixture.components[nearest], BASELINE_MIN_EIGENVALUE_M2))
        return out
