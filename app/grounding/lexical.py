"""A simple lexical hypothesis proposer: anchors are objects whose label names the anchor phrase.

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
from app.vocabulary import label_tokens, lemmas, normalise

# Storey words of a region phrase, and the side of the map they pick.
_STOREYS = {"upstairs": 1.0, "upper": 1.0, "downstairs": -1.0, "lower": -1.0, "ground": -1.0}


def match_score(anchor_phrase: str, label: str) -> int:
    """2: the label is the phrase; 1: the phrase's head noun (last word) is a word of the label; else 0."""
    phrase, words = label_tokens(anchor_phrase), label_tokens(label)
    if not phrase or not words:
        return 0
    if phrase == words or phrase[-len(words) :] == words:
        return 2
    return 1 if phrase[-1] in words else 0


def matching_objects(
    scene_graph: SceneGraph, anchor_phrase: str, region_ids: set[str] | None
) -> list[SceneObject]:
    """Objects of the best match score (> 0), restricted to `region_ids` when given."""
    scored = [(match_score(anchor_phrase, o.label), o) for o in scene_graph.objects]
    if region_ids is not None:
        scored = [(s, o) for s, o in scored if o.region_id in region_ids]
    best = max((s for s, _ in scored), default=0)
    return [o for s, o in scored if s == best and best > 0]


def regions_named(scene_graph: SceneGraph, phrase: str | None) -> set[str] | None:
    """Ids of the regions a region phrase names ("kitchen", "upstairs bedroom", "upstairs"), None if none: the
    one rule of the proposers and of the broad term.

    Regions match by shared words; a storey word keeps those of them (or of all regions, if the phrase names
    no room) whose centre lies above (below) the middle of their heights.
    """
    if not phrase or not scene_graph.regions:
        return None
    words = normalise(phrase).split()
    storey = [_STOREYS[w] for w in words if w in _STOREYS]
    room_words = set(lemmas(" ".join(w for w in words if w not in _STOREYS)).split())
    pool = [r for r in scene_graph.regions if room_words & set(lemmas(r.name).split())] if room_words else []
    if storey:
        pool = pool or ([] if room_words else list(scene_graph.regions))
        heights = np.array([r.center[2] for r in pool])
        if len(pool) > 1 and np.ptp(heights) > 1.0:
            middle = 0.5 * (heights.min() + heights.max())
            pool = [r for r, z in zip(pool, heights, strict=True) if (z - middle) * storey[0] > 0]
    return {r.id for r in pool} or None


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
        region_names = tuple(normalise(r.name) for r in scene_graph.regions if r.name)
        parse = parse_utterance(utterance, region_names)
        if not parse.anchor_phrases:
            return Proposal(parse, (), grounded=False, reason="the utterance names no anchor object")
        region_ids = regions_named(scene_graph, parse.region_phrase)
        candidates = [matching_objects(scene_graph, p, region_ids) for p in parse.anchor_phrases]
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
