"""The built-in referent proposer: calibrated hypotheses P(h | utterance, map), offline, in milliseconds.

"My backpack is on the table" in a house with three tables is a referential ambiguity: each table is a
hypothesis h = (anchor, relation). The proposer

1. parses the utterance (`parse_utterance`: target, relation, anchor phrase(s), region, attributes);
2. takes as candidates the objects whose label names an anchor phrase: the same lemmas, a synonym
   (`SYNONYM_GROUPS`), or a MiniLM cosine of at least `min_label_similarity` (label embeddings cached),
   restricted to the mentioned region when one matches; "between" pairs them up;
3. scores each hypothesis linearly in its plausibility features (`referent_features`), with weights fitted
   per relation on the built grounding cases (`vlmap fit-proposer`), plus a fixed prior weight on attribute
   agreement ("the white table": the built data carries no attributes to fit it on);
4. turns the scores s_h into weights with a softmax, w_h = exp(s_h / T) / sum_h' exp(s_h' / T), keeps the
   `max_hypotheses` heaviest and renormalises them.

The weights are a conditional logit model fitted by maximum likelihood, so they are calibrated probabilities
on data like the training cases (see models/proposer/MODEL_CARD.md for the measured calibration). When no
object matches an anchor phrase the proposal is `grounded=False` with the reason, and the language sensor
falls back to a broad region or scene prior.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import threading
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from app.errors import ModelUnavailable
from app.grounding.hypotheses import Hypothesis, Proposal, UtteranceParse
from app.grounding.lexical import describe, label_tokens
from app.grounding.parsing import normalise, parse_utterance, split_attributes
from app.grounding.referent_features import (
    FEATURES,
    N_FEATURES,
    SceneBoxes,
    attribute_scores,
    hypothesis_features,
    object_attribute_words,
)
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, SceneObject

if TYPE_CHECKING:
    from app.lsm.text_encoder import TextEncoder

DEFAULT_PARAMS_PATH = Path(__file__).resolve().parents[2] / "models" / "proposer" / "params.json"
LABEL_CACHE_SIZE = 50_000  # object names whose embeddings the proposer keeps
PARAMS_VERSION = 1

#: Names people use interchangeably for one kind of object (lemmatised, lower case).
SYNONYM_GROUPS: tuple[frozenset[str], ...] = tuple(
    frozenset(group.split(", "))
    for group in (
        "sofa, couch, settee",
        "tv, television, tv screen",
        "refrigerator, fridge",
        "mini fridge, small fridge",
        "trash can, garbage can, trash bin, garbage bin, waste bin, wastebasket, rubbish bin, dustbin, bin",
        "recycling bin, recycling",
        "cabinet, cupboard",
        "kitchen cabinet, kitchen cupboard, cupboard",
        "nightstand, night stand, bedside table, night table",
        "dresser, chest of drawer",
        "bookshelf, bookcase, book shelf",
        "shelving unit, shelf, shelf unit",
        "armchair, arm chair, easy chair, sofa chair",
        "office chair, desk chair",
        "counter, countertop, kitchen counter, worktop",
        "cell phone, phone, mobile phone, mobile, smartphone",
        "telephone, phone",
        "end table, side table",
        "dining table, kitchen table",
        "coffee table, cocktail table",
        "rug, carpet",
        "monitor, screen, computer screen, display",
        "laptop, notebook computer",
        "computer tower, pc, computer",
        "backpack, rucksack, knapsack, bag",
        "remote control, remote, tv remote",
        "bathtub, tub, bath",
        "toilet paper, toilet roll",
        "tissue box, box of tissue, tissue",
        "laundry hamper, hamper, laundry basket",
        "coffee maker, coffee machine",
        "whiteboard, white board, dry erase board",
        "mug, coffee mug",
        "pillow, cushion",
        "plant, house plant, houseplant, potted plant",
        "doorframe, door frame",
        "file cabinet, filing cabinet",
        "keychain, key, key ring",
        "clothes, clothing",
        "garbage bag, trash bag",
        "microwave, microwave oven",
        "stove, cooker",
        "sink, basin, washbasin",
        "wardrobe, armoire",
        "picture, photo, photograph",
        "desk lamp, lamp",
        "floor lamp, standing lamp, lamp",
        "alarm clock, clock",
        "tennis racket, racket",
        "baseball bat, bat",
        "dumbbell, weight",
        "wine bottle, bottle of wine",
        "soap bottle, soap",
        "basketball, ball",
    )
)


def _synonym_index() -> dict[str, frozenset[int]]:
    index: dict[str, set[int]] = {}
    for number, group in enumerate(SYNONYM_GROUPS):
        for name in group:
            index.setdefault(lemmas(name), set()).add(number)
    return {name: frozenset(groups) for name, groups in index.items()}


# Storey words of a region phrase, and the side of the map they pick.
_STOREYS = {"upstairs": 1.0, "upper": 1.0, "downstairs": -1.0, "lower": -1.0, "ground": -1.0}


@lru_cache(maxsize=1 << 16)
def lemmas(text: str) -> str:
    """Lower-case singular words: "Kitchen_Cabinets" -> "kitchen cabinet"."""
    return " ".join(label_tokens(text))


def head_noun(lemma_text: str) -> str:
    """The noun a phrase is about: its last word, or the word before "of" ("chest of drawer" -> "chest")."""
    words = lemma_text.split()
    if "of" in words[1:]:
        return words[words.index("of") - 1]
    return words[-1] if words else ""


@lru_cache(maxsize=1 << 16)
def lexical_match(phrase: str, name: str) -> int:
    """2: same lemmas or synonyms; 1: same head noun ("table", "coffee table"); 0: neither (lemmatised)."""
    if not phrase or not name:
        return 0
    if phrase == name or _SYNONYMS.get(phrase, frozenset()) & _SYNONYMS.get(name, frozenset()):
        return 2
    return 1 if head_noun(phrase) == head_noun(name) else 0


_SYNONYMS = _synonym_index()


def object_names(obj: SceneObject) -> tuple[str, ...]:
    """The label and, when a reader kept it, the raw label ("garbage bin" / "trash can"), lemmatised."""
    names = [lemmas(obj.label) or obj.label.lower()]
    raw = obj.attributes.get("raw_label")
    if isinstance(raw, str) and lemmas(raw) and lemmas(raw) not in names:
        names.append(lemmas(raw))
    return tuple(names)


# --- parameters ---------------------------------------------------------------------------------------------


@dataclass
class ProposerParams:
    """Everything the proposer's scores depend on; saved as JSON by `vlmap fit-proposer`.

    Scores are s = ((x - feature_mean) / feature_scale) . weights[relation] + attribute_weight * a, and
    weights softmax(s / temperature); x the `FEATURES` row of a hypothesis, a its attribute agreement.
    """

    weights: dict[Relation, np.ndarray]  # (F,) per relation, on standardised features
    feature_mean: np.ndarray  # (F,)
    feature_scale: np.ndarray  # (F,)
    temperature: float = 1.0
    attribute_weight: float = 3.0  # a prior, not fitted: the built data has no attribute words
    min_label_similarity: float = 0.7
    sibling_similarity: float = 0.85
    max_candidates: int = 40
    # Lemmatised target label -> median (dx, dy, dz, centre height above the floor) of the training targets.
    target_boxes: dict[str, list[float]] = field(default_factory=dict)
    default_target_box: tuple[float, float, float, float] = (0.3, 0.3, 0.3, 0.8)
    encoder_sha256: str = ""
    info: dict[str, Any] = field(default_factory=dict)  # what it was fitted on, and the metrics

    @classmethod
    def untrained(cls, **overrides: Any) -> ProposerParams:
        """Zero weights (uniform over the candidates): what fitting starts from."""
        weights = {r: np.zeros(N_FEATURES) for r in Relation}
        return cls(
            weights=weights, feature_mean=np.zeros(N_FEATURES), feature_scale=np.ones(N_FEATURES), **overrides
        )

    def scores(self, relation: Relation, features: np.ndarray, attribute: np.ndarray) -> np.ndarray:
        """s / T for features (H, F) and attribute agreement (H,) -> (H,)."""
        standard = (features - self.feature_mean) / self.feature_scale  # (H, F)
        return (standard @ self.weights[relation] + self.attribute_weight * attribute) / self.temperature

    def to_json(self) -> dict[str, Any]:
        return {
            "version": PARAMS_VERSION,
            "features": list(FEATURES),
            "weights": {r.value: [round(float(v), 6) for v in w] for r, w in self.weights.items()},
            "feature_mean": [round(float(v), 6) for v in self.feature_mean],
            "feature_scale": [round(float(v), 6) for v in self.feature_scale],
            "temperature": self.temperature,
            "attribute_weight": self.attribute_weight,
            "min_label_similarity": self.min_label_similarity,
            "sibling_similarity": self.sibling_similarity,
            "max_candidates": self.max_candidates,
            "default_target_box": list(self.default_target_box),
            "encoder_sha256": self.encoder_sha256,
            "info": self.info,
            "target_boxes": {k: [round(v, 4) for v in b] for k, b in sorted(self.target_boxes.items())},
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ProposerParams:
        if data.get("version") != PARAMS_VERSION or data.get("features") != list(FEATURES):
            msg = (
                f"proposer parameters of version {data.get('version')} with features {data.get('features')} "
                f"do not fit this code (version {PARAMS_VERSION}, features {list(FEATURES)}): refit them"
            )
            raise ModelUnavailable(msg)
        return cls(
            weights={Relation(r): np.asarray(w, dtype=np.float64) for r, w in data["weights"].items()},
            feature_mean=np.asarray(data["feature_mean"], dtype=np.float64),
            feature_scale=np.asarray(data["feature_scale"], dtype=np.float64),
            temperature=float(data["temperature"]),
            attribute_weight=float(data["attribute_weight"]),
            min_label_similarity=float(data["min_label_similarity"]),
            sibling_similarity=float(data["sibling_similarity"]),
            max_candidates=int(data["max_candidates"]),
            target_boxes={k: [float(v) for v in b] for k, b in data["target_boxes"].items()},
            default_target_box=tuple(float(v) for v in data["default_target_box"]),  # type: ignore[arg-type]
            encoder_sha256=str(data["encoder_sha256"]),
            info=dict(data.get("info", {})),
        )

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=1) + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: Path) -> ProposerParams:
        if not path.is_file():
            msg = f"proposer parameters not found at {path}; fit them with `vlmap fit-proposer`"
            raise ModelUnavailable(msg)
        return cls.from_json(json.loads(path.read_text(encoding="utf-8")))


# --- candidates ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidates:
    """The hypotheses of one utterance on one map, before weighting."""

    parse: UtteranceParse
    relation: Relation
    objects: list[SceneObject]
    groups: np.ndarray  # (H, k) object indices; k = 2 for "between"
    features: np.ndarray  # (H, F)
    attribute: np.ndarray  # (H,) attribute agreement in [-1, 1]
    region_ignored: bool = False  # a region was named but no candidate lies in it

    def anchor_ids(self, row: int) -> tuple[str, ...]:
        return tuple(self.objects[i].id for i in self.groups[row])


@dataclass(frozen=True)
class _PhraseMatch:
    """The objects an anchor phrase may name, with their label features (C, 3) and attribute agreement."""

    indices: np.ndarray  # (C,)
    label_features: np.ndarray  # (C, 3): cosine, exact, head
    attribute: np.ndarray  # (C,)


class BuiltinProposer:
    """Calibrated referent hypotheses from lemmas, synonyms, MiniLM label similarity and map geometry."""

    name = "builtin"

    def __init__(
        self,
        encoder: TextEncoder | None = None,
        params: ProposerParams | None = None,
        max_hypotheses: int = 5,
    ) -> None:
        """`encoder`: the service's frozen MiniLM (one is loaded when None); `params`: the shipped ones
        (models/proposer/params.json) when None."""
        if max_hypotheses < 1:
            msg = f"max_hypotheses must be at least 1, got {max_hypotheses}"
            raise ValueError(msg)
        if encoder is None:
            from app.lsm.text_encoder import TextEncoder

            encoder = TextEncoder()
        params = params if params is not None else ProposerParams.load(DEFAULT_PARAMS_PATH)
        if params.encoder_sha256 and params.encoder_sha256 != encoder.sha256:
            msg = (
                f"proposer parameters were fitted with text encoder {params.encoder_sha256[:12]}, "
                f"but this encoder is {encoder.sha256[:12]}: refit them with `vlmap fit-proposer`"
            )
            raise ModelUnavailable(msg)
        self.encoder = encoder
        self.params = params
        self.max_hypotheses = max_hypotheses
        self._label_vectors: dict[str, np.ndarray] = {}
        self._cache_lock = threading.Lock()

    @classmethod
    def load(cls, encoder: TextEncoder, path: Path | None = None, max_hypotheses: int = 5) -> BuiltinProposer:
        """The proposer with parameters read from `path` (default models/proposer/params.json)."""
        return cls(encoder, ProposerParams.load(path or DEFAULT_PARAMS_PATH), max_hypotheses)

    def describe(self) -> dict[str, Any]:
        """Name, version, config and the checksum of the fitted parameters (for /v1/models)."""
        params = self.params.to_json()
        digest = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()
        config = {"max_hypotheses": self.max_hypotheses, "temperature": params["temperature"]}
        return {
            "name": self.name,
            "version": str(params["version"]),
            "config": config,
            "checksum": f"sha256:{digest}",
        }

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        region_names = tuple(normalise(r.name) for r in scene_graph.regions if r.name)
        parse = parse_utterance(utterance, region_names)
        found = self.candidates(scene_graph, parse)
        if isinstance(found, str):
            return Proposal(parse, (), grounded=False, reason=found)
        weights = softmax(self.params.scores(found.relation, found.features, found.attribute))  # (H,)
        order = np.argsort(-weights, kind="stable")[: self.max_hypotheses]
        kept = weights[order] / weights[order].sum()
        objects = found.objects
        hypotheses = tuple(
            Hypothesis(
                anchor_ids=found.anchor_ids(row),
                relation=found.relation,
                weight=float(w),
                region_id=objects[found.groups[row][0]].region_id,
                text=describe(parse, tuple(objects[i] for i in found.groups[row])),
            )
            for row, w in zip(order, kept, strict=True)
        )
        extra = {
            "candidates": float(len(weights)),
            "dropped_weight": float(max(0.0, 1.0 - weights[order].sum())),
        }
        if found.region_ignored:
            extra["region_ignored"] = 1.0
        return Proposal(parse, hypotheses, extra=extra)

    # --- candidates and their features ----------------------------------------------------------------------

    def candidates(self, scene_graph: SceneGraph, parse: UtteranceParse) -> Candidates | str:
        """Every hypothesis with its features, or the reason there is none."""
        objects = list(scene_graph.objects)
        if not parse.anchor_phrases:
            return "the utterance names no anchor object"
        if not objects:
            return "the scene graph has no objects"
        # Texts to match: each phrase's noun, also with its attribute words ("white board"), then the target.
        phrases = [split_attributes(p) for p in parse.anchor_phrases]
        texts: list[str] = []
        rows: list[list[int]] = []
        for (attributes, noun), full in zip(phrases, parse.anchor_phrases, strict=True):
            rows.append([len(texts)] + ([len(texts) + 1] if attributes else []))
            texts += [lemmas(noun), lemmas(full)] if attributes else [lemmas(noun)]
        target = lemmas(parse.target) if parse.target else ""
        if target:
            texts.append(target)
        # Every object has one or two names (label, raw label): score the texts against the distinct names,
        # then each object by its better name.
        names = [object_names(o) for o in objects]
        name_list = sorted({n for ns in names for n in ns})
        column = {n: j for j, n in enumerate(name_list)}
        first = np.array([column[ns[0]] for ns in names])  # (N,)
        last = np.array([column[ns[-1]] for ns in names])
        name_cosine = self._phrase_vectors(texts) @ self._name_vectors(name_list).T  # (T, U)
        name_level = np.array([[lexical_match(t, n) for n in name_list] for t in texts])  # (T, U)
        cosine = np.maximum(name_cosine[:, first], name_cosine[:, last])  # (T, N)
        levels = np.maximum(name_level[:, first], name_level[:, last])  # (T, N)

        region_ids = regions_for_phrase(scene_graph, parse.region_phrase)
        in_region = None if region_ids is None else np.array([o.region_id in region_ids for o in objects])
        boxes = SceneBoxes.of(objects)
        vocabulary = frozenset().union(*(object_attribute_words(o) for o in objects))
        matches: list[_PhraseMatch] = []
        region_ignored = False
        for (attributes, _), text_rows in zip(phrases, rows, strict=True):
            phrase_cos = cosine[text_rows].max(axis=0)  # (N,)
            level = levels[text_rows].max(axis=0)
            eligible = (level > 0) | (phrase_cos >= self.params.min_label_similarity)
            if in_region is not None:
                if np.any(eligible & in_region):
                    eligible &= in_region
                elif np.any(eligible):
                    region_ignored = True
            index = np.flatnonzero(eligible)
            index = index[np.lexsort((-phrase_cos[index], -level[index]))][: self.params.max_candidates]
            label_features = np.stack([phrase_cos[index], level[index] == 2, level[index] == 1], axis=1)
            attribute = attribute_scores(
                attributes, [objects[i] for i in index], boxes.size[index], vocabulary
            )
            matches.append(_PhraseMatch(index, label_features.astype(np.float64), attribute))

        missing = [parse.anchor_phrases[p] for p, m in enumerate(matches) if len(m.indices) == 0]
        relation = parse.relation
        if relation is Relation.BETWEEN:
            if missing:
                return f"no object in the scene graph matches {', '.join(repr(m) for m in missing)}"
            groups, slots = _pairs(matches)
        else:
            if len(missing) == len(matches):
                return f"no object in the scene graph matches {', '.join(repr(m) for m in missing)}"
            groups, slots = _alternatives(matches)
        if len(groups) == 0:
            return "no two distinct objects match the anchors of 'between'"

        label_features = np.stack(
            [np.stack([matches[p].label_features[s] for p, s in row]) for row in slots]
        )  # (H, k, 3)
        attribute = np.array([np.mean([matches[p].attribute[s] for p, s in row]) for row in slots])  # (H,)
        target_cosine = cosine[-1] if target else None  # (N,)
        siblings = np.zeros(len(objects), dtype=bool)
        if target_cosine is not None:  # the target's kind: same lemmas or synonyms, or a very close embedding
            siblings = (levels[-1] == 2) | (target_cosine >= self.params.sibling_similarity)
        target_box = self._target_box(target, boxes, siblings)
        same_label = None
        if groups.shape[1] == 2:
            same_label = np.array([objects[a].label == objects[b].label for a, b in groups], dtype=np.float64)
        features = hypothesis_features(
            relation, boxes, groups, label_features, siblings, target_box, same_label, target_cosine
        )
        return Candidates(parse, relation, objects, groups, features, attribute, region_ignored)

    def _target_box(self, target: str, boxes: SceneBoxes, siblings: np.ndarray) -> np.ndarray:
        """The target's likely size and centre height (4,): its siblings' median, else the fitted table's
        (for its label or a synonym), else the training targets' median."""
        if np.any(siblings):
            height = boxes.center[siblings, 2] - boxes.floor
            return np.append(np.median(boxes.size[siblings], axis=0), np.median(height))
        table = self.params.target_boxes
        for name in (target, *(lemmas(n) for g in _SYNONYMS.get(target, ()) for n in SYNONYM_GROUPS[g])):
            if name in table:
                return np.asarray(table[name], dtype=np.float64)
        return np.asarray(self.params.default_target_box, dtype=np.float64)

    def _phrase_vectors(self, texts: list[str]) -> np.ndarray:
        """Unit embeddings (P, D) of phrases; the encoder's own cache makes repeated phrases free."""
        return np.asarray(self.encoder.encode(texts), dtype=np.float64)

    def _name_vectors(self, names: list[str]) -> np.ndarray:
        """Unit embeddings (U, D) of object names, kept here (the `LABEL_CACHE_SIZE` most recently added):
        a map's labels cost one encoder batch the first time only."""
        with self._cache_lock:
            missing = [n for n in names if n not in self._label_vectors]
            if missing:
                for name, vector in zip(missing, self.encoder.encode(missing), strict=True):
                    self._label_vectors[name] = np.asarray(vector, dtype=np.float32)
                while len(self._label_vectors) > LABEL_CACHE_SIZE:
                    del self._label_vectors[next(iter(self._label_vectors))]
            return np.stack([self._label_vectors[n] for n in names]).astype(np.float64)


def _alternatives(matches: list[_PhraseMatch]) -> tuple[np.ndarray, list[list[tuple[int, int]]]]:
    """One-anchor hypotheses: every candidate of every alternative phrase, each object once (best phrase)."""
    best: dict[int, tuple[tuple[float, float, float], int, int]] = {}
    for p, match in enumerate(matches):
        for slot, index in enumerate(match.indices):
            cos, exact, head = match.label_features[slot]
            strength = (exact, head, cos)  # exact match first, then head noun, then cosine
            if int(index) not in best or strength > best[int(index)][0]:
                best[int(index)] = (strength, p, slot)
    indices = list(best)
    groups = np.array(indices, dtype=np.int64).reshape(-1, 1)
    return groups, [[best[i][1:]] for i in indices]


def _pairs(matches: list[_PhraseMatch]) -> tuple[np.ndarray, list[list[tuple[int, int]]]]:
    """ "between" hypotheses: unordered pairs of distinct objects, one per phrase (or two of one plural)."""
    first = matches[0]
    second, q = (matches[1], 1) if len(matches) > 1 else (matches[0], 0)
    seen: set[frozenset[int]] = set()
    groups: list[tuple[int, int]] = []
    slots: list[list[tuple[int, int]]] = []
    for (s1, a), (s2, b) in itertools.product(enumerate(first.indices), enumerate(second.indices)):
        key = frozenset((int(a), int(b)))
        if a == b or key in seen:
            continue
        seen.add(key)
        groups.append((int(a), int(b)))
        slots.append([(0, s1), (q, s2)])
    return np.array(groups, dtype=np.int64).reshape(-1, 2), slots


def regions_for_phrase(scene_graph: SceneGraph, phrase: str | None) -> set[str] | None:
    """Ids of the regions a region phrase names ("kitchen", "upstairs bedroom", "upstairs"); None if none.

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


def softmax(scores: np.ndarray) -> np.ndarray:
    """exp(s_i - max s) / sum_j exp(s_j - max s)."""
    shifted = np.exp(scores - np.max(scores))
    return shifted / shifted.sum()
