"""The language sensor: P(x | L, map) = sum_h P(x | h, map) P(h | L, map), served as one mixture.

A `HypothesisProposer` gives the weighted hypotheses and the weight beta of the broad "I may have
misunderstood" term, a `Grounder` one density per hypothesis (a small Gaussian mixture). The sensor serves

    p(x) = (1 - beta) sum_h w_h p_h(x) + beta_min U(x; map) + (beta - beta_min) B(x),

with beta at least beta_min = `MIN_BACKGROUND_WEIGHT`, U the uniform density over the map's box (`map_box`),
and B the broad density over what the utterance allows: uniform over the mentioned region(s), else the map
with the areas a negation rules out carved away ("not on the table"), else the map; a tenth of B lies on a
wide Gaussian about the map, so places just outside the mapped objects' box keep some mass. Since
p(x) >= beta_min / vol(map box)
everywhere in the map, no input makes it worse than the uniform over the map by more than
log(1 / beta_min) = 3.9 nats.

Only the `max_grounded` heaviest hypotheses go through the grounder; the others keep their mass, merged per
region into one broad Gaussian each (moment-matched over rough per-anchor Gaussians), so no reading a long
list of look-alike anchors holds is dropped. A hypothesis with a spread c > 1 (a vague or view-dependent
relation) has every covariance of its density multiplied by c. Caller-given hypotheses skip the proposer:
they are served as given, beta = 0 (a caller who names the reading has nothing to be misunderstood).

When no hypothesis is left (nothing to read, a map without objects) the mixture is the broad prior alone.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from app.errors import InvalidInput
from app.grounding.hypotheses import MIN_BACKGROUND_WEIGHT, Hypothesis, Proposal, UtteranceParse
from app.grounding.interfaces import Grounder, HypothesisProposer
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox, map_box
from app.grounding.parsing import parse_utterance
from app.scene_graph.model import SceneGraph

StageObserver = Callable[[str, float], None]
#: Hypotheses grounded one by one (the rest are merged per region).
DEFAULT_MAX_GROUNDED = 8
# The rough per-anchor Gaussian of a merged hypothesis: sigma = half extent + this (metres) per axis.
_MERGED_MARGIN = 0.5
#: The broad density's share on a wide Gaussian about the map (beside its uniform boxes).
WIDE_SHARE = 0.1


@dataclass(frozen=True)
class Grounding:
    """What the sensor concluded from one utterance."""

    proposal: Proposal
    hypotheses: tuple[Hypothesis, ...]  # the served readings: weights sum to 1; merged ones summarise many
    mixture: GaussianMixture
    timings_ms: dict[str, float] = field(default_factory=dict)
    densities: tuple[GaussianMixture, ...] = ()  # P(x | h, map) of each served hypothesis, in order
    background: float = MIN_BACKGROUND_WEIGHT  # beta, the broad term's weight in `mixture`
    broad: GaussianMixture | None = None  # the broad term, normalised: mixture = (1 - beta) sum + beta broad

    @property
    def grounded(self) -> bool:
        return self.proposal.grounded

    def component_hypotheses(self) -> list[int | None]:
        """The index in `hypotheses` of each Gaussian of the mixture, None for one of no hypothesis.

        The mixture holds the densities' Gaussians first, in hypothesis order; a Gaussian after them (a broad
        prior, all of them when the utterance was not grounded) belongs to no hypothesis.
        """
        owners: list[int | None] = [h for h, density in enumerate(self.densities) for _ in density.weights]
        return owners + [None] * (len(self.mixture.weights) - len(owners))


class LanguageSensor:
    """Proposer then grounder; every stage timed (and reported to `observer`, e.g. Prometheus)."""

    def __init__(
        self,
        proposer: HypothesisProposer,
        grounder: Grounder,
        observer: StageObserver | None = None,
        max_grounded: int = DEFAULT_MAX_GROUNDED,
    ):
        if max_grounded < 1:
            msg = f"max_grounded must be at least 1, got {max_grounded}"
            raise ValueError(msg)
        self.proposer = proposer
        self.grounder = grounder
        self.observer = observer
        self.max_grounded = max_grounded

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: Sequence[Hypothesis] | None = None
    ) -> Grounding:
        """Hypotheses from the proposer (or the caller's, validated), their densities, the served mixture."""
        timings: dict[str, float] = {}
        if hypotheses is None:
            with self._stage("proposer", timings):
                proposal = self.proposer.propose(scene_graph, utterance)
        else:
            proposal = self._caller_proposal(scene_graph, utterance, hypotheses)
        return self.ground_proposal(scene_graph, utterance, proposal, timings)

    def ground_proposal(
        self,
        scene_graph: SceneGraph,
        utterance: str,
        proposal: Proposal,
        timings: dict[str, float] | None = None,
    ) -> Grounding:
        """The served mixture of a proposal made already (the evaluation shares one among grounders)."""
        timings = {} if timings is None else timings
        beta = min(1.0, max(0.0, proposal.background))
        box = map_box(scene_graph)  # the broad term's and the merged tail's
        if not proposal.hypotheses or beta >= 1.0:
            prior = broad_term(1.0, scene_graph, proposal, box)
            return Grounding(proposal, (), prior, timings, background=1.0, broad=prior)
        ranked = sorted(proposal.hypotheses, key=lambda h: -h.weight)
        grounded, rest = ranked[: self.max_grounded], ranked[self.max_grounded :]
        with self._stage("grounder", timings):
            densities = [
                widened(d, h.spread)
                for d, h in zip(self.grounder.ground(scene_graph, utterance, grounded), grounded, strict=True)
            ]
        served = list(grounded)
        for merged, density in merged_tail(scene_graph, rest, box):
            served.append(merged)
            densities.append(density)
        weights = np.array([h.weight for h in served], dtype=np.float64)
        weights /= weights.sum()
        mixture = GaussianMixture.combine(weights, densities)
        served_hypotheses = tuple(replace(h, weight=float(w)) for h, w in zip(served, weights, strict=True))
        if beta <= 0.0:
            return Grounding(proposal, served_hypotheses, mixture, timings, tuple(densities), 0.0)
        broad = broad_term(beta, scene_graph, proposal, box)
        full = GaussianMixture.combine([1.0 - beta, beta], [mixture, broad])
        return Grounding(proposal, served_hypotheses, full, timings, tuple(densities), beta, broad)

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
        parse = parse_utterance(utterance, tuple(r.name for r in scene_graph.regions))
        # Relative weights, scaled to a largest of 1: weights near the float maximum would sum to infinity.
        heaviest = max((h.weight for h in hypotheses), default=1.0)
        filled = tuple(
            replace(
                h,
                weight=h.weight / heaviest,
                region_id=h.region_id or scene_graph.object(h.anchor_ids[0]).region_id,
            )
            for h in hypotheses
        )
        return Proposal(parse, filled, background=0.0)


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


def widened(density: GaussianMixture, spread: float) -> GaussianMixture:
    """The density with every covariance times `spread` (>= 1: a vague reading is less certain)."""
    if spread == 1.0:
        return density
    return replace(density, covariances=density.covariances * spread)


def merged_tail(
    scene_graph: SceneGraph, hypotheses: Sequence[Hypothesis], box: UniformBox
) -> list[tuple[Hypothesis, GaussianMixture]]:
    """One summarising hypothesis and one broad Gaussian per region for the hypotheses not grounded one by
    one: each hypothesis stands for a rough Gaussian at its anchors' centre (sigma = half extent + 0.5 m
    per axis; the whole map's box for a region hypothesis), and the region's Gaussian is their
    weight-averaged moment match, its weight their sum. `box`: the map's (`map_box`)."""
    by_region: dict[str | None, list[Hypothesis]] = defaultdict(list)
    for h in hypotheses:
        by_region[h.region_id].append(h)
    out = []
    for region_id, group in by_region.items():
        weights = np.array([h.weight for h in group])
        means, covs = [], []
        for h in group:
            if h.anchor_ids:
                anchors = [scene_graph.object(i) for i in h.anchor_ids]
                low = np.min([a.min_corner for a in anchors], axis=0)
                high = np.max([a.max_corner for a in anchors], axis=0)
                means.append(0.5 * (low + high))
                covs.append(np.diag((0.5 * (high - low) + _MERGED_MARGIN) ** 2))
            else:
                means.append(box.center)
                covs.append(box.covariance)
        rough = GaussianMixture.from_components(
            weights, [Gaussian(m, c) for m, c in zip(means, covs, strict=True)]
        )
        density = GaussianMixture.of(Gaussian(rough.mean(), rough.covariance()))
        anchor_ids = tuple(dict.fromkeys(a for h in group for a in h.anchor_ids))
        # Ties go to the relation first seen (the heaviest reading's): a set's order varies between processes.
        relation = max(
            dict.fromkeys(h.relation for h in group),
            key=lambda r: sum(h.weight for h in group if h.relation is r),
        )
        text = f"{len(group)} more readings" + (f" in region {region_id}" if region_id else "")
        out.append((Hypothesis(anchor_ids, relation, float(weights.sum()), region_id, text), density))
    return out


def broad_term(beta: float, scene_graph: SceneGraph, proposal: Proposal, box: UniformBox) -> GaussianMixture:
    """The broad term normalised, (beta_min U(map) + (beta - beta_min) B) / beta (module docstring); `box`
    is the map's (`map_box`)."""
    floor = min(MIN_BACKGROUND_WEIGHT, beta)
    uniform = GaussianMixture.from_components([], [], boxes=[box], box_weights=[1.0])
    broad = broad_density(scene_graph, proposal.parse, box, proposal.avoid)
    return GaussianMixture.combine([floor, beta - floor], [uniform, broad])


def broad_density(
    scene_graph: SceneGraph, parse: UtteranceParse, box: UniformBox, avoid: Sequence[UniformBox] = ()
) -> GaussianMixture:
    """The broad density B: uniform over what the utterance allows (`broad_boxes`), with a share
    `WIDE_SHARE` on one wide Gaussian about the map (sigma = half the map box's side per axis), so that
    places just outside the mapped objects' box (a partly explored map) keep some mass. `box`: the map's
    (`map_box`)."""
    boxes, weights = broad_boxes(scene_graph, parse, box, avoid)
    wide = Gaussian(box.center, np.diag((0.5 * box.size) ** 2))
    return GaussianMixture.from_components(
        [WIDE_SHARE], [wide], boxes=boxes, box_weights=(1.0 - WIDE_SHARE) * weights
    )


def broad_boxes(
    scene_graph: SceneGraph, parse: UtteranceParse, box: UniformBox, avoid: Sequence[UniformBox] = ()
) -> tuple[list[UniformBox], np.ndarray]:
    """The uniform part of B as boxes with weights summing to one: the regions the utterance puts the target
    in (equal shares; `UtteranceParse.region_ids`: "not in the kitchen" is every other region), else the
    map's box minus the `avoid` boxes (shares by volume, so it is uniform on what is left), else the map's
    box `box` (`map_box`)."""
    region_ids, _ = parse.region_ids(scene_graph.regions)
    if region_ids:
        boxes = [
            UniformBox.around(
                np.asarray(r.center) - 0.5 * np.asarray(r.size),
                np.asarray(r.center) + 0.5 * np.asarray(r.size),
            )
            for r in scene_graph.regions
            if r.id in region_ids
        ]
        return boxes, np.full(len(boxes), 1.0 / len(boxes))
    pieces = [box]
    for hole in avoid:
        pieces = [part for piece in pieces for part in subtract(piece, hole)]
    if not pieces:  # the negation covers the whole map: nothing is left to prefer
        pieces = [box]
    volumes = np.array([p.volume for p in pieces])
    return pieces, volumes / volumes.sum()


def subtract(box: UniformBox, hole: UniformBox) -> list[UniformBox]:
    """box minus hole as at most six disjoint boxes (slabs below and above the hole in z, then in y, x)."""
    low, high = np.maximum(box.low, hole.low), np.minimum(box.high, hole.high)
    if np.any(high <= low):
        return [box]
    out = []
    lo, hi = box.low.copy(), box.high.copy()
    for axis in (2, 1, 0):
        if lo[axis] < low[axis]:
            part_hi = hi.copy()
            part_hi[axis] = low[axis]
            out.append(UniformBox(lo.copy(), part_hi))
        if high[axis] < hi[axis]:
            part_lo = lo.copy()
            part_lo[axis] = high[axis]
            out.append(UniformBox(part_lo, hi.copy()))
        lo[axis], hi[axis] = low[axis], high[axis]
    return [b for b in out if np.all(b.high - b.low > 1e-9)]
