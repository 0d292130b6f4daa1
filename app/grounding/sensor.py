"""The language sensor: P(x | L, map) = sum_h P(x | h, map) P(h | L, map) as one mixture.

A `HypothesisProposer` gives the weighted hypotheses, a `Grounder` one density per hypothesis (a small
Gaussian mixture). When no anchor matches, the sensor says so (`grounded = False`) and returns a broad prior
over the mentioned region(s) or the whole map instead of inventing an anchor.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from app.errors import InvalidInput
from app.grounding.hypotheses import Hypothesis, Proposal, UtteranceParse
from app.grounding.interfaces import Grounder, HypothesisProposer
from app.grounding.lexical import regions_named
from app.grounding.mixture import Gaussian, GaussianMixture
from app.grounding.parsing import parse_utterance
from app.scene_graph.model import SceneGraph

StageObserver = Callable[[str, float], None]


@dataclass(frozen=True)
class Grounding:
    """What the sensor concluded from one utterance."""

    proposal: Proposal
    hypotheses: tuple[Hypothesis, ...]  # weights sum to 1; empty when not grounded
    mixture: GaussianMixture
    timings_ms: dict[str, float] = field(default_factory=dict)
    densities: tuple[GaussianMixture, ...] = ()  # P(x | h, map) of each hypothesis, in order

    @property
    def grounded(self) -> bool:
        return self.proposal.grounded


class LanguageSensor:
    """Proposer then grounder; every stage timed (and reported to `observer`, e.g. Prometheus)."""

    def __init__(
        self, proposer: HypothesisProposer, grounder: Grounder, observer: StageObserver | None = None
    ):
        self.proposer = proposer
        self.grounder = grounder
        self.observer = observer

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: Sequence[Hypothesis] | None = None
    ) -> Grounding:
        """Hypotheses from the proposer (or the caller's, validated) and their mixture."""
        timings: dict[str, float] = {}
        if hypotheses is None:
            with self._stage("proposer", timings):
                proposal = self.proposer.propose(scene_graph, utterance)
        else:
            proposal = self._caller_proposal(scene_graph, utterance, hypotheses)
        if not proposal.hypotheses:
            mixture = broad_prior(scene_graph, proposal.parse)
            return Grounding(proposal, (), mixture, timings)
        with self._stage("grounder", timings):
            densities = tuple(self.grounder.ground(scene_graph, utterance, list(proposal.hypotheses)))
        weights = np.array([h.weight for h in proposal.hypotheses], dtype=np.float64)
        mixture = GaussianMixture.combine(weights, densities)
        normalised = tuple(
            replace(h, weight=float(w))
            for h, w in zip(proposal.hypotheses, weights / weights.sum(), strict=True)
        )
        return Grounding(proposal, normalised, mixture, timings, densities)

    def _stage(self, name: str, timings: dict[str, float]) -> _StageTimer:
        return _StageTimer(name, timings, self.observer)

    @staticmethod
    def _caller_proposal(
        scene_graph: SceneGraph, utterance: str, hypotheses: Sequence[Hypothesis]
    ) -> Proposal:
        known = {o.id for o in scene_graph.objects}
        for index, h in enumerate(hypotheses):
            where = f"options.hypotheses.{index}.anchor_ids"
            if len(h.anchor_ids) != h.relation.n_anchors:
                wanted = h.relation.n_anchors
                msg = f"relation {h.relation.value!r} takes {wanted} anchor id(s), got {len(h.anchor_ids)}"
                raise InvalidInput(msg, field=where)
            unknown = [a for a in h.anchor_ids if a not in known]
            if unknown:
                msg = f"unknown object id(s) {unknown}"
                raise InvalidInput(msg, field=where)
        region_names = tuple(r.name.lower() for r in scene_graph.regions if r.name)
        parse = parse_utterance(utterance, region_names)
        filled = tuple(
            replace(h, region_id=h.region_id or scene_graph.object(h.anchor_ids[0]).region_id)
            for h in hypotheses
        )
        return Proposal(parse, filled)


class _StageTimer:
    def __init__(self, name: str, timings: dict[str, float], observer: StageObserver | None) -> None:
        self.name, self.timings, self.observer = name, timings, observer

    def __enter__(self) -> None:
        self.start = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        seconds = time.perf_counter() - self.start
        self.timings[self.name] = round(seconds * 1000.0, 3)
        if self.observer is not None:
            self.observer(self.name, seconds)


def broad_prior(scene_graph: SceneGraph, parse: UtteranceParse) -> GaussianMixture:
    """Moment-matched Gaussians of a uniform distribution over the mentioned regions, else the whole map.

    A uniform density over a box of widths w has covariance diag(w^2 / 12); regions get equal weight.
    """
    region_ids = regions_named(scene_graph, parse.region_phrase)
    boxes: list[tuple[np.ndarray, np.ndarray]] = []
    if region_ids:
        for region in scene_graph.regions:
            if region.id in region_ids:
                boxes.append(
                    (np.asarray(region.center, dtype=np.float64), np.asarray(region.size, dtype=np.float64))
                )
    if not boxes:
        low, high = scene_graph.bounds()
        boxes.append((0.5 * (low + high), np.maximum(high - low, 0.1)))
    gaussians = [Gaussian(center, np.diag(size**2 / 12.0)) for center, size in boxes]
    return GaussianMixture.from_components(np.ones(len(gaussians)), gaussians)
