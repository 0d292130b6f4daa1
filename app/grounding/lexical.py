"""A simple lexical hypothesis proposer: anchors are objects whose label names the anchor phrase best (by the
vocabulary's `lexical_match`, as the built-in proposer names them).

Every matching object is equally plausible (uniform weights): honest about referential ambiguity,
blind to everything else. The calibrated built-in proposer replaces it behind the same interface.
"""

from __future__ import annotations

import itertools

import numpy as np

from app.grounding.hypotheses import Hypothesis, Proposal, UtteranceParse
from app.grounding.parsing import parse_utterance
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, SceneObject
from app.vocabulary import lemmas, lexical_match


def match_score(noun: str, phrase: str, label: str) -> int:
    """How well a mention names an object's label, by the vocabulary's `lexical_match` (2 the same class, 1 a
    looser naming, 0 none) of the mention's noun or of its whole phrase (a name with an attribute word in
    it: "white board"), whichever is better."""
    name = lemmas(label)
    return max(lexical_match(lemmas(noun), name), lexical_match(lemmas(phrase), name))


def matching_objects(
    scene_graph: SceneGraph, noun: str, phrase: str, region_ids: set[str] | None
) -> list[SceneObject]:
    """Objects of the best match score (> 0), restricted to `region_ids` when given."""
    scored = [(match_score(noun, phrase, o.label), o) for o in scene_graph.objects]
    if region_ids is not None:
        scored = [(s, o) for s, o in scored if o.region_id in region_ids]
    best = max((s for s, _ in scored), default=0)
    return [o for s, o in scored if s == best and best > 0]


class LexicalProposer:
    """Uniform weights over every object whose label matches the anchor phrase (pairs for "between")."""

    name = "lexical"

    def __init__(self, max_hypotheses: int = 5) -> None:
        self.max_hypotheses = max_hypotheses

    def describe(self) -> dict[str, object]:
        return {
            "name": self.name,
            "version": "1",
            "config": {"max_hypotheses": self.max_hypotheses},
            "checksum": None,
        }

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        parse = parse_utterance(utterance, tuple(r.name for r in scene_graph.regions))
        if not parse.anchor_phrases:
            return Proposal(parse, (), grounded=False, reason="the utterance names no anchor object")
        region_ids, _ = parse.region_ids(scene_graph.regions)
        nouns = {m.phrase: m.noun for m in parse.mentions}
        candidates = [
            matching_objects(scene_graph, nouns.get(p, p), p, region_ids) for p in parse.anchor_phrases
        ]
        missing = [p for p, c in zip(parse.anchor_phrases, candidates, strict=True) if not c]
        if missing:
            reason = f"no object in the scene graph matches {', '.join(repr(m) for m in missing)}"
            return Proposal(parse, (), grounded=False, reason=reason)
        groups = self._anchor_groups(parse, candidates)[: self.max_hypotheses]
        weight = 1.0 / len(groups)
        hypotheses = tuple(
            Hypothesis(
                anchor_ids=tuple(o.id for o in group),
                relation=parse.relation,
                weight=weight,
                region_id=group[0].region_id,
                text=describe(parse.target, parse.relation, group),
            )
            for group in groups
        )
        return Proposal(parse, hypotheses)

    @staticmethod
    def _anchor_groups(
        parse: UtteranceParse, candidates: list[list[SceneObject]]
    ) -> list[tuple[SceneObject, ...]]:
        if parse.relation is not Relation.BETWEEN or len(candidates) < 2:
            return [(o,) for o in candidates[0]]
        # Pairs of distinct objects, the closest pairs first: "between" anchors are usually near each other.
        pairs = [(a, b) for a, b in itertools.product(candidates[0], candidates[1]) if a.id != b.id]
        pairs.sort(key=lambda ab: float(np.linalg.norm(np.subtract(ab[0].center, ab[1].center))))
        unique: dict[frozenset[str], tuple[SceneObject, ...]] = {}
        for a, b in pairs:
            unique.setdefault(frozenset((a.id, b.id)), (a, b))
        return list(unique.values())


def describe(target: str, relation: Relation, anchors: tuple[SceneObject, ...], region: str = "") -> str:
    """ "the backpack on table 7" style text for one hypothesis ("the backpack in the kitchen" for a region
    hypothesis, "... in the map" without a region name)."""
    said = target or "target"
    if not anchors:
        return f"the {said} in the {region or 'map'}"
    names = " and ".join(f"{o.label} {o.id}" for o in anchors)
    return f"the {said} {relation.value} {names}"
