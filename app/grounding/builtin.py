"""The built-in referent proposer: calibrated hypotheses P(h | utterance, map), offline, in milliseconds.

"My backpack is on the table next to the tv" in a house with three tables is a referential ambiguity: each
reading is a hypothesis h = (anchor(s), relation). The proposer

1. parses the whole utterance (`parse_utterance`): the target, every mention, how each constrains the
   target (anchors) or says which object another mention is (qualifiers), negations, view-dependent words;
2. matches each mention to the map's objects: the same class or a looser naming (`app.vocabulary`), or a
   MiniLM cosine of at least `min_label_similarity` (label embeddings cached), in the mentioned region
   when one matches; "between" pairs them up;
3. makes hypotheses of every candidate of every anchor (never capped: an anchor dropped here would be mass
   lost from the density), plus
   - the reading "closest" of a "near" anchor when the map holds other objects of the target's class (a
     referring expression: "the chair near the door" is the chair nearest it, as Sr3D writes),
   - each qualifier's candidates as anchors of the target (the attachment of "next to the tv" to the table
     or to the cup is ambiguous),
   - one region hypothesis: the target somewhere in the mentioned region, or in the map;
4. scores each hypothesis linearly in its features, s_h = w_k . standardised(x_h) + attribute_weight a_h,
   with one weight vector per relation (and one for the region hypothesis), and turns the scores into
   weights w_h = softmax(s / T);
5. predicts the weight of a broad "I may have misunderstood" term from how well the parse and the map
   agree, beta = beta_min + (1 - beta_min) sigmoid(v . standardised(g)) (`MIN_BACKGROUND_WEIGHT`); the
   sensor serves (1 - beta) sum_h w_h p(x | h) + beta U(x).

Features (`FEATURES`): the plausibility features of `referent_features` (label match, size, support,
context, ordinals) and the mention's own: its relation vague or view-dependent, a later sentence, an
alternative ("or"), the order of its mention, how well the candidate satisfies the mention's qualifiers
(the table that *is* next to a tv), the alternative "closest" reading, a qualifier read as an anchor, the
region hypothesis. Negated anchors ("not on the table") make no hypothesis; the areas they name are carved
out of the broad term (`Proposal.avoid`), so negation can only lower the mass there.

All parameters (the weight vectors, T, the background model v, the spread of vague and view-dependent
hypotheses) are fitted end to end by `vlmap fit-proposer` (`app.training.referents`), maximising the
marginal likelihood of true target positions over the latent hypotheses, on human descriptions and built
cases of the training scans; `models/proposer/MODEL_CARD.md` says what was fitted on what.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import ModelUnavailable
from app.grounding.box_relations import anchor_allowed
from app.grounding.hypotheses import MIN_BACKGROUND_WEIGHT, Hypothesis, Mention, Proposal, UtteranceParse
from app.grounding.interfaces import SentenceEncoder
from app.grounding.lexical import describe
from app.grounding.mixture import UniformBox
from app.grounding.parsing import parse_utterance
from app.grounding.referent_features import (
    FEATURES as GEOMETRY_FEATURES,
)
from app.grounding.referent_features import (
    N_FEATURES as N_GEOMETRY,
)
from app.grounding.referent_features import (
    SceneBoxes,
    attribute_scores,
    hypothesis_features,
    object_attribute_words,
    related_mask,
    surface_distances,
)
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph, SceneObject
from app.vocabulary import class_key, lemmas, lexical_match, normalise, other_names

DEFAULT_PARAMS_PATH = Path(__file__).resolve().parents[2] / "models" / "proposer" / "params.json"
LABEL_CACHE_SIZE = 50_000  # object names whose embeddings the proposer keeps
PARAMS_VERSION = 2
#: The weight vector of the region hypothesis (the others are keyed by relation).
REGION = "region"
#: Mention features, after the geometry ones.
MENTION_FEATURES: tuple[str, ...] = (
    "kind_region",
    "kind_nested",
    "reading_closest",
    "relation_vague",
    "view_dependent",
    "later_sentence",
    "disjunct",
    "mention_order",
    "qualifier_fit",
    "has_qualifier",
    "log_mention_candidates",
    "log_target_siblings",
    "anchors_in_utterance",
    "region_named",
)
FEATURES: tuple[str, ...] = (*GEOMETRY_FEATURES, *MENTION_FEATURES)
N_FEATURES = len(FEATURES)
_COLUMN = {name: j for j, name in enumerate(FEATURES)}
#: Utterance features of the background model.
BACKGROUND_FEATURES: tuple[str, ...] = (
    "intercept",
    "no_anchor",
    "unknown_anchor",
    "best_label_exact",
    "best_label_cosine",
    "view_dependent",
    "negation",
    "log_sentences",
    "log_hypotheses",
    "target_known",
    "target_in_map",
    "relation_vague",
    "log_words",
)
N_BACKGROUND = len(BACKGROUND_FEATURES)
#: Spreads (covariance multipliers) a hypothesis may get: fitted for vague and view-dependent relations, each
#: at least its floor. A view-dependent word names one side of the anchor without saying whose left it is:
#: the reading must cover every side, so it is never sharper than one and a half times "near".
SPREADS = ("vague", "view")
MIN_SPREADS = {"vague": 1.0, "view": 1.5}
# What a negated relation rules out around its anchor, metres: (grow xy, below, above) of the anchor's box.
_AVOID_GROW = {
    Relation.ON: (0.05, -1.0, 0.4),
    Relation.IN: (0.0, 0.0, 0.0),
    Relation.ABOVE: (0.0, -1.0, 1.5),
    Relation.BELOW: (0.05, 0.0, -1.0),
}
_AVOID_NEAR = 0.6
_MAX_AVOIDED = 8  # negated anchors carved out at most (each costs a few boxes)


@dataclass
class ProposerParams:
    """Everything the proposer's weights depend on; saved as JSON by `vlmap fit-proposer`.

    Scores s = ((x - feature_mean) / feature_scale) . weights[key] + attribute_weight * a, weights
    softmax(s / temperature); x the `FEATURES` row of a hypothesis, a its attribute agreement, key its
    relation or `REGION`. Background beta = MIN_BACKGROUND_WEIGHT + (1 - MIN) sigmoid(g' . background), g'
    the standardised `BACKGROUND_FEATURES`.
    """

    weights: dict[str, np.ndarray]  # (F,) per relation and REGION, on standardised features
    feature_mean: np.ndarray  # (F,)
    feature_scale: np.ndarray  # (F,)
    background: np.ndarray  # (G,) on standardised background features
    background_mean: np.ndarray  # (G,)
    background_scale: np.ndarray  # (G,)
    spreads: dict[str, float] = field(default_factory=lambda: dict(MIN_SPREADS))
    temperature: float = 1.0
    attribute_weight: float = 3.0  # a prior, not fitted: the training maps carry no attributes
    min_label_similarity: float = 0.7
    sibling_similarity: float = 0.85
    max_candidates: int = 500  # per mention: a bound on the work, far above any map's look-alikes
    # Lemmatised target label -> median (dx, dy, dz, centre height above the floor) of the training targets.
    target_boxes: dict[str, list[float]] = field(default_factory=dict)
    default_target_box: tuple[float, float, float, float] = (0.3, 0.3, 0.3, 0.8)
    encoder_sha256: str = ""
    info: dict[str, Any] = field(default_factory=dict)  # what it was fitted on, and the metrics

    @classmethod
    def untrained(cls, **overrides: Any) -> ProposerParams:
        """Zero weights (uniform over the candidates), beta at its floor's side: what fitting starts from."""
        keys = [r.value for r in Relation] + [REGION]
        return cls(
            weights={k: np.zeros(N_FEATURES) for k in keys},
            feature_mean=np.zeros(N_FEATURES),
            feature_scale=np.ones(N_FEATURES),
            background=np.zeros(N_BACKGROUND),
            background_mean=np.zeros(N_BACKGROUND),
            background_scale=np.ones(N_BACKGROUND),
            **overrides,
        )

    def scores(self, keys: list[str], features: np.ndarray, attribute: np.ndarray) -> np.ndarray:
        """s / T for hypotheses with weight keys (H,), features (H, F), attribute agreement (H,) -> (H,)."""
        standard = (features - self.feature_mean) / self.feature_scale  # (H, F)
        weights = np.stack([self.weights[k] for k in keys])  # (H, F)
        logits: np.ndarray = (
            np.sum(standard * weights, axis=1) + self.attribute_weight * attribute
        ) / self.temperature
        return logits

    def background_weight(self, utterance_features: np.ndarray) -> float:
        """beta = MIN_BACKGROUND_WEIGHT + (1 - MIN_BACKGROUND_WEIGHT) sigmoid(g' . v)."""
        standard = (utterance_features - self.background_mean) / self.background_scale
        logit = float(standard @ self.background)
        return MIN_BACKGROUND_WEIGHT + (1.0 - MIN_BACKGROUND_WEIGHT) / (1.0 + math.exp(-logit))

    def to_json(self) -> dict[str, Any]:
        def rounded(v: np.ndarray) -> list[float]:
            return [round(float(x), 6) for x in v]

        return {
            "version": PARAMS_VERSION,
            "features": list(FEATURES),
            "background_features": list(BACKGROUND_FEATURES),
            "weights": {k: rounded(w) for k, w in self.weights.items()},
            "feature_mean": rounded(self.feature_mean),
            "feature_scale": rounded(self.feature_scale),
            "background": rounded(self.background),
            "background_mean": rounded(self.background_mean),
            "background_scale": rounded(self.background_scale),
            "spreads": {k: round(v, 6) for k, v in self.spreads.items()},
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
        if (
            data.get("version") != PARAMS_VERSION
            or data.get("features") != list(FEATURES)
            or data.get("background_features") != list(BACKGROUND_FEATURES)
        ):
            msg = (
                f"proposer parameters of version {data.get('version')} with features {data.get('features')} "
                f"do not fit this code (version {PARAMS_VERSION}, features {list(FEATURES)}): refit them"
            )
            raise ModelUnavailable(msg)

        def array(key: str) -> np.ndarray:
            return np.asarray(data[key], dtype=np.float64)

        return cls(
            weights={k: np.asarray(w, dtype=np.float64) for k, w in data["weights"].items()},
            feature_mean=array("feature_mean"),
            feature_scale=array("feature_scale"),
            background=array("background"),
            background_mean=array("background_mean"),
            background_scale=array("background_scale"),
            spreads={k: float(v) for k, v in data["spreads"].items()},
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


def describe_params(params: ProposerParams) -> dict[str, Any]:
    """What `/v1/models` says of the built-in proposer with these fitted parameters (readable without
    loading the text encoder)."""
    fitted = params.to_json()
    digest = hashlib.sha256(json.dumps(fitted, sort_keys=True).encode()).hexdigest()
    config = {
        "temperature": fitted["temperature"],
        "min_background_weight": MIN_BACKGROUND_WEIGHT,
        "spreads": fitted["spreads"],
    }
    return {
        "name": BuiltinProposer.name,
        "version": str(fitted["version"]),
        "config": config,
        "checksum": f"sha256:{digest}",
    }


def object_names(obj: SceneObject) -> tuple[str, ...]:
    """The label and, when a reader kept it, the raw label ("garbage bin" / "trash can"), lemmatised."""
    names = [lemmas(obj.label) or obj.label.lower()]
    raw = obj.attributes.get("raw_label")
    if isinstance(raw, str) and lemmas(raw) and lemmas(raw) not in names:
        names.append(lemmas(raw))
    return tuple(names)


# --- candidates ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidates:
    """The hypotheses of one utterance on one map, before weighting, with what the background model reads.

    Row h: `anchors[h]` object indices into `objects` (empty for the region hypothesis), `relations[h]`,
    `keys[h]` its weight vector, `spreads[h]` which fitted spread widens it (None: none).
    """

    parse: UtteranceParse
    objects: list[SceneObject]
    anchors: list[tuple[int, ...]]
    relations: list[Relation]
    keys: list[str]
    spreads: list[str | None]
    features: np.ndarray  # (H, F)
    attribute: np.ndarray  # (H,) attribute agreement in [-1, 1]
    utterance_features: np.ndarray  # (G,)
    regions: tuple[str, ...]  # the region hypothesis's regions, sorted (none: the whole map)
    avoid: tuple[UniformBox, ...] = ()  # what negated anchors rule out
    reason: str | None = None  # why nothing anchors the target, when nothing does
    region_ignored: bool = False

    @property
    def region_id(self) -> str | None:
        """The region hypothesis's one region (None: the whole map, or several regions)."""
        return self.regions[0] if len(self.regions) == 1 else None

    def anchor_ids(self, row: int) -> tuple[str, ...]:
        return tuple(self.objects[i].id for i in self.anchors[row])

    def anchor_objects(self, row: int) -> tuple[SceneObject, ...]:
        return tuple(self.objects[i] for i in self.anchors[row])


@dataclass(frozen=True)
class _PhraseMatch:
    """The objects a phrase may name, with their label features (C, 3) and attribute agreement (C,)."""

    indices: np.ndarray  # (C,)
    label_features: np.ndarray  # (C, 3): cosine, same class, looser naming
    attribute: np.ndarray  # (C,)


@dataclass
class _Rows:
    """Hypothesis rows as they are made, before their geometry features."""

    anchors: list[tuple[int, ...]] = field(default_factory=list)
    relations: list[Relation] = field(default_factory=list)
    label: list[np.ndarray] = field(default_factory=list)  # (k, 3) each
    attribute: list[float] = field(default_factory=list)
    mention: list[np.ndarray] = field(default_factory=list)  # (M,) each
    spreads: list[str | None] = field(default_factory=list)

    def add(
        self,
        anchors: tuple[int, ...],
        relation: Relation,
        label: np.ndarray,
        attribute: float,
        mention: np.ndarray,
        spread: str | None,
    ) -> None:
        self.anchors.append(anchors)
        self.relations.append(relation)
        self.label.append(label)
        self.attribute.append(attribute)
        self.mention.append(mention)
        self.spreads.append(spread)


class BuiltinProposer:
    """Calibrated referent hypotheses from the whole utterance, MiniLM label similarity and map geometry."""

    name = "builtin"

    def __init__(self, encoder: SentenceEncoder, params: ProposerParams | None = None) -> None:
        """`encoder`: the service's frozen MiniLM; `params`: the shipped ones (models/proposer/params.json)
        when None."""
        params = params if params is not None else ProposerParams.load(DEFAULT_PARAMS_PATH)
        if params.encoder_sha256 and params.encoder_sha256 != encoder.sha256:
            msg = (
                f"proposer parameters were fitted with text encoder {params.encoder_sha256[:12]}, "
                f"but this encoder is {encoder.sha256[:12]}: refit them with `vlmap fit-proposer`"
            )
            raise ModelUnavailable(msg)
        self.encoder = encoder
        self.params = params
        self._label_vectors: dict[str, np.ndarray] = {}
        self._cache_lock = threading.Lock()

    @classmethod
    def load(cls, encoder: SentenceEncoder, path: Path | None = None) -> BuiltinProposer:
        """The proposer with parameters read from `path` (default models/proposer/params.json)."""
        return cls(encoder, ProposerParams.load(path or DEFAULT_PARAMS_PATH))

    def describe(self) -> dict[str, Any]:
        """Name, version, config and the checksum of the fitted parameters (for /v1/models)."""
        return describe_params(self.params)

    def parse(self, scene_graph: SceneGraph, utterance: str) -> UtteranceParse:
        """The utterance read with the map's region names and labels in the vocabulary."""
        labels = tuple(sorted({n for o in scene_graph.objects for n in object_names(o)}))
        return parse_utterance(utterance, tuple(r.name for r in scene_graph.regions), labels)

    def propose(self, scene_graph: SceneGraph, utterance: str) -> Proposal:
        parse = self.parse(scene_graph, utterance)
        if not parse.english:
            reason = "the utterance reads as no English sentence about objects: only the broad prior"
            return Proposal(parse, (), grounded=False, reason=reason, background=1.0)
        if not scene_graph.objects:
            return Proposal(
                parse, (), grounded=False, reason="the scene graph has no objects", background=1.0
            )
        found = self.candidates(scene_graph, parse)
        params = self.params
        weights = softmax(params.scores(found.keys, found.features, found.attribute))  # (H,)
        objects = found.objects
        region_names = {r.id: r.name for r in scene_graph.regions}
        hypotheses: list[Hypothesis] = []
        for row, w in enumerate(weights):
            relation, spread = found.relations[row], _spread(params, found.spreads[row])
            if found.anchors[row]:
                region_ids: tuple[str | None, ...] = (objects[found.anchors[row][0]].region_id,)
            else:  # "in the kitchen or in the bedroom": the region reading's weight shared by the regions
                region_ids = found.regions or (None,)
            hypotheses += [
                Hypothesis(
                    anchor_ids=found.anchor_ids(row),
                    relation=relation,
                    weight=float(w) / len(region_ids),
                    region_id=region_id,
                    text=describe(
                        parse.target,
                        relation,
                        found.anchor_objects(row),
                        region_names.get(region_id or "", ""),
                    ),
                    spread=spread,
                )
                for region_id in region_ids
            ]
        extra = {"candidates": float(len(weights))}
        if found.region_ignored:
            extra["region_ignored"] = 1.0
        background = params.background_weight(found.utterance_features)
        ranked = sorted(hypotheses, key=lambda h: -h.weight)  # stable: ties keep the rows' order
        if found.avoid:
            # Under a negation "somewhere in the room" is the broad term with the negated areas carved out;
            # the grounder's region density would put its usual mass back on them ("not on the table").
            region_weight = sum(h.weight for h in ranked if not h.anchor_ids)
            ranked = [h for h in ranked if h.anchor_ids]
            background += (1.0 - background) * region_weight
        return Proposal(
            parse,
            tuple(ranked),
            grounded=found.reason is None,
            reason=found.reason,
            extra=extra,
            background=background,
            avoid=found.avoid,
        )

    # --- candidates and their features ----------------------------------------------------------------------

    def candidates(self, scene_graph: SceneGraph, parse: UtteranceParse) -> Candidates:
        """Every hypothesis of the utterance with its features (see the module docstring)."""
        objects = list(scene_graph.objects)
        boxes = SceneBoxes.of(objects)
        mentions = list(parse.mentions)
        target = next((m for m in mentions if m.role == "target"), None)
        target_name = lemmas(target.noun) if target is not None else ""
        names = [object_names(o) for o in objects]
        name_list = sorted({n for ns in names for n in ns})
        column = {n: j for j, n in enumerate(name_list)}
        first = np.array([column[ns[0]] for ns in names])  # (N,)
        last = np.array([column[ns[-1]] for ns in names])
        name_vectors = self._name_vectors(name_list)  # (U, D)

        # Texts to match: each mention's noun, also with its attribute words ("white board").
        texts: list[str] = []
        rows_of: list[list[int]] = []
        for m in mentions:
            rows_of.append([len(texts)] + ([len(texts) + 1] if m.attributes else []))
            texts += [m.noun, lemmas(m.phrase)] if m.attributes else [m.noun]
        if target_name:
            texts.append(target_name)
        phrase_cosine = (
            self._phrase_vectors(texts) @ name_vectors.T if texts else np.zeros((0, len(name_list)))
        )
        name_level = np.array(
            [[lexical_match(t, n) for n in name_list] for t in texts], dtype=np.int64
        ).reshape(len(texts), len(name_list))
        cosine = np.maximum(phrase_cosine[:, first], phrase_cosine[:, last])  # (T, N)
        levels = np.maximum(name_level[:, first], name_level[:, last])  # (T, N)

        region_ids, _ = parse.region_ids(scene_graph.regions)
        in_region = None if region_ids is None else np.array([o.region_id in region_ids for o in objects])
        vocabulary = frozenset().union(*(object_attribute_words(o) for o in objects))
        region_ignored = False
        matches: list[_PhraseMatch] = []
        for m, text_rows in zip(mentions, rows_of, strict=True):
            phrase_cos = cosine[text_rows].max(axis=0)  # (N,)
            level = levels[text_rows].max(axis=0)
            eligible = (level > 0) | (phrase_cos >= self.params.min_label_similarity)
            if in_region is not None and m.role == "anchor":
                if np.any(eligible & in_region):
                    eligible &= in_region
                elif np.any(eligible):
                    region_ignored = True
            index = np.flatnonzero(eligible)
            index = index[np.lexsort((-phrase_cos[index], -level[index]))][: self.params.max_candidates]
            label_features = np.stack([phrase_cos[index], level[index] == 2, level[index] == 1], axis=1)
            attribute = attribute_scores(
                m.attributes, [objects[i] for i in index], boxes.size[index], vocabulary
            )
            matches.append(_PhraseMatch(index, label_features.astype(np.float64), attribute))

        target_cosine = cosine[-1] if target_name else None  # (N,)
        siblings = np.zeros(len(objects), dtype=bool)
        if target_cosine is not None:  # the target's kind: the same class, or a very close embedding
            siblings = (levels[-1] == 2) | (target_cosine >= self.params.sibling_similarity)
        n_siblings = int(siblings.sum())
        target_box = self._target_box(target_name, boxes, siblings)

        anchor_mentions = [k for k, m in enumerate(mentions) if m.role == "anchor" and not m.negated]
        rows = _Rows()
        n_anchor = len(anchor_mentions)
        region_named = region_ids is not None
        self._anchor_rows(rows, anchor_mentions, mentions, matches, boxes, objects, n_siblings, region_named)
        self._nested_rows(rows, mentions, matches, objects, n_anchor, n_siblings, region_named)

        region_row = np.zeros(len(MENTION_FEATURES))
        region_row[_COLUMN["kind_region"] - N_GEOMETRY] = 1.0
        region_row[_COLUMN["log_target_siblings"] - N_GEOMETRY] = math.log1p(n_siblings)
        region_row[_COLUMN["anchors_in_utterance"] - N_GEOMETRY] = math.log1p(n_anchor)
        region_row[_COLUMN["region_named"] - N_GEOMETRY] = float(region_ids is not None)
        keys = [class_key(o.label) for o in objects]
        features = self._geometry(rows, keys, boxes, siblings, target_box, target_cosine)  # (H, F)
        region_features = np.concatenate([np.zeros(N_GEOMETRY), region_row])[None]

        unknown = [
            m.phrase
            for m, match in zip(mentions, matches, strict=True)
            if m.role == "anchor" and len(match.indices) == 0
        ]
        negated = [k for k, m in enumerate(mentions) if m.role == "anchor" and m.negated]
        reason = None
        if not rows.anchors:
            reason = (
                f"no object in the scene graph matches {', '.join(repr(p) for p in unknown)}"
                if unknown
                else "the utterance names no anchor object"
            )
        best_exact = max((float(r[0, 1]) for r in rows.label), default=0.0)
        best_cosine = max((float(r[:, 0].max()) for r in rows.label), default=0.0)
        utterance_features = np.array(
            [
                1.0,
                float(not rows.anchors),
                float(bool(unknown)),
                best_exact,
                best_cosine,
                float(parse.view_dependent),
                float(bool(negated)),
                math.log(parse.sentences),
                math.log1p(len(rows.anchors)),
                float(target is not None and target.known),
                float(n_siblings > 0),
                float(any(not mentions[k].relation_known for k in anchor_mentions)),
                math.log1p(
                    len(normalise(parse.target).split()) + sum(len(m.phrase.split()) for m in mentions)
                ),
            ]
        )
        return Candidates(
            parse=parse,
            objects=objects,
            anchors=[*rows.anchors, ()],
            relations=[*rows.relations, Relation.IN],
            keys=[*(r.value for r in rows.relations), REGION],
            spreads=[*rows.spreads, None],
            features=np.concatenate([features, region_features]),
            attribute=np.append(np.asarray(rows.attribute, dtype=np.float64), 0.0),
            utterance_features=utterance_features,
            regions=tuple(sorted(region_ids or ())),
            avoid=self._avoided(negated, mentions, matches, objects),
            reason=reason,
            region_ignored=region_ignored,
        )

    def _anchor_rows(
        self,
        rows: _Rows,
        anchor_mentions: list[int],
        mentions: list[Mention],
        matches: list[_PhraseMatch],
        boxes: SceneBoxes,
        objects: list[SceneObject],
        n_siblings: int,
        region_named: bool,
    ) -> None:
        """The rows of the anchor mentions: one per candidate object (and its "closest" reading), or the
        pairs of a "between"."""
        n_anchor = len(anchor_mentions)
        for order, k in enumerate(anchor_mentions):
            m = mentions[k]
            if m.partner is not None and m.partner < k:
                continue  # the pair is made from its first mention
            fit = self._qualifier_fit(k, mentions, matches, boxes)  # (C,)
            base = self._mention_row(m, order, n_anchor, len(matches[k].indices), n_siblings, region_named)
            base[_COLUMN["has_qualifier"] - N_GEOMETRY] = float(
                any(q.head == k and q.role == "qualifier" for q in mentions)
            )
            relation = m.relation or Relation.NEAR
            spread = "view" if m.view_dependent else ("vague" if not m.relation_known else None)
            if relation is Relation.BETWEEN:
                self._pair_rows(rows, k, m, mentions, matches, base, spread)
                continue
            for slot, index in enumerate(matches[k].indices):
                said, vague = _reading(relation, objects[index].label)
                row = base.copy()
                row[_COLUMN["qualifier_fit"] - N_GEOMETRY] = fit[slot]
                if vague:
                    row[_COLUMN["relation_vague"] - N_GEOMETRY] = 1.0
                label = matches[k].label_features[slot][None]
                agreement = float(matches[k].attribute[slot])
                rows.add((int(index),), said, label, agreement, row, spread or ("vague" if vague else None))
                if said is Relation.NEAR and n_siblings and not vague:
                    alternative = row.copy()
                    alternative[_COLUMN["reading_closest"] - N_GEOMETRY] = 1.0
                    rows.add((int(index),), Relation.CLOSEST, label, agreement, alternative, None)

    def _nested_rows(
        self,
        rows: _Rows,
        mentions: list[Mention],
        matches: list[_PhraseMatch],
        objects: list[SceneObject],
        n_anchor: int,
        n_siblings: int,
        region_named: bool,
    ) -> None:
        """The rows of the qualifiers ("the table by the window"), each read as an anchor of the target."""
        for k, m in enumerate(mentions):  # qualifiers read as anchors of the target
            if m.role != "qualifier" or m.negated or m.relation in (None, Relation.BETWEEN):
                continue
            relation = m.relation or Relation.NEAR
            base = self._mention_row(m, n_anchor, n_anchor, len(matches[k].indices), n_siblings, region_named)
            base[_COLUMN["kind_nested"] - N_GEOMETRY] = 1.0
            spread = "view" if m.view_dependent else ("vague" if not m.relation_known else None)
            for slot, index in enumerate(matches[k].indices):
                said, vague = _reading(relation, objects[index].label)
                rows.add(
                    (int(index),),
                    said,
                    matches[k].label_features[slot][None],
                    float(matches[k].attribute[slot]),
                    base,
                    spread or ("vague" if vague else None),
                )

    @staticmethod
    def _mention_row(
        m: Mention, order: int, n_anchor: int, n_candidates: int, n_siblings: int, region_named: bool
    ) -> np.ndarray:
        row = np.zeros(len(MENTION_FEATURES))
        values = {
            "relation_vague": float(not m.relation_known),
            "view_dependent": float(m.view_dependent),
            "later_sentence": float(m.sentence > 0),
            "disjunct": float(m.disjunct),
            "mention_order": math.log1p(order),
            "log_mention_candidates": math.log1p(n_candidates),
            "log_target_siblings": math.log1p(n_siblings),
            "anchors_in_utterance": math.log1p(n_anchor),
            "region_named": float(region_named),
        }
        for name, value in values.items():
            row[_COLUMN[name] - N_GEOMETRY] = value
        return row

    def _pair_rows(
        self,
        rows: _Rows,
        k: int,
        m: Mention,
        mentions: list[Mention],
        matches: list[_PhraseMatch],
        base: np.ndarray,
        spread: str | None,
    ) -> None:
        """ "between" rows: unordered pairs of distinct objects, one per phrase (or two of one plural)."""
        first = matches[k]
        second = matches[m.partner] if m.partner is not None else first
        seen: set[frozenset[int]] = set()
        for (s1, a), (s2, b) in itertools.product(enumerate(first.indices), enumerate(second.indices)):
            key = frozenset((int(a), int(b)))
            if a == b or key in seen:
                continue
            seen.add(key)
            label = np.stack([first.label_features[s1], second.label_features[s2]])
            attribute = 0.5 * float(first.attribute[s1] + second.attribute[s2])
            rows.add((int(a), int(b)), Relation.BETWEEN, label, attribute, base.copy(), spread)

    def _qualifier_fit(
        self, k: int, mentions: list[Mention], matches: list[_PhraseMatch], boxes: SceneBoxes
    ) -> np.ndarray:
        """How well each candidate of mention k satisfies the qualifiers on it, mean over them, in [0, 1]
        (1 - fit for a negated one); 0.5 with no qualifier.

        near and vague relations: exp(-d / 1 m), d the surface distance to the nearest candidate of the
        qualifier; on/in/above/below: whether the candidate stands so to one of them; closest/farthest: the
        candidate's rank among mention k's candidates by distance to the qualifier's nearest candidate.
        """
        own = matches[k].indices
        fits = []
        for q, m in enumerate(mentions):
            if m.head != k or m.role != "qualifier" or m.relation is None or len(matches[q].indices) == 0:
                continue
            other = matches[q].indices
            relation = m.relation
            if relation in (Relation.ON, Relation.IN, Relation.ABOVE, Relation.BELOW):
                # Candidate o stands in `relation` to some qualifier object: o is in related_mask of it.
                related = related_mask(relation, boxes, other)  # (Q, N)
                fit = related[:, own].any(axis=0).astype(np.float64)
            else:
                distance = surface_distances(
                    boxes.lo[own], boxes.hi[own], boxes.lo[other], boxes.hi[other]
                ).min(axis=1)  # (C,)
                if relation in (Relation.CLOSEST, Relation.FARTHEST) and len(own) > 1:
                    rank = np.argsort(np.argsort(distance if relation is Relation.CLOSEST else -distance))
                    fit = 1.0 - rank / (len(own) - 1)
                else:
                    fit = np.exp(-distance)
            fits.append(1.0 - fit if m.negated else fit)
        return np.mean(fits, axis=0) if fits else np.full(len(own), 0.5)

    @staticmethod
    def _geometry(
        rows: _Rows,
        keys: list[str],
        boxes: SceneBoxes,
        siblings: np.ndarray,
        target_box: np.ndarray,
        target_cosine: np.ndarray | None,
    ) -> np.ndarray:
        """(H, F): the geometry features per relation, then the mention features; `keys` are the objects'
        class keys (for "between" pairs of one class)."""
        out = np.zeros((len(rows.anchors), N_FEATURES))
        if not rows.anchors:
            return out
        relations = np.array([r.value for r in rows.relations])
        for relation in Relation:
            for width in (1, 2):
                index = np.flatnonzero(
                    (relations == relation.value) & np.array([len(a) == width for a in rows.anchors])
                )
                if not len(index):
                    continue
                groups = np.array([rows.anchors[i] for i in index], dtype=np.int64)  # (h, k)
                label = np.stack([rows.label[i] for i in index])  # (h, k, 3)
                same_label = None
                if width == 2:
                    same_label = np.array([keys[a] == keys[b] for a, b in groups], dtype=np.float64)
                out[index, :N_GEOMETRY] = hypothesis_features(
                    relation, boxes, groups, label, siblings, target_box, same_label, target_cosine
                )
        out[:, N_GEOMETRY:] = np.stack(rows.mention)
        return out

    def _avoided(
        self,
        negated: list[int],
        mentions: list[Mention],
        matches: list[_PhraseMatch],
        objects: list[SceneObject],
    ) -> tuple[UniformBox, ...]:
        """The areas negated anchors name ("not on the table": just above each table's top)."""
        boxes: list[UniformBox] = []
        for k in negated:
            relation = mentions[k].relation or Relation.NEAR
            for index in matches[k].indices[:_MAX_AVOIDED]:
                o = objects[int(index)]
                lo, hi = (
                    np.asarray(o.min_corner, dtype=np.float64),
                    np.asarray(o.max_corner, dtype=np.float64),
                )
                grow_xy, below, above = _AVOID_GROW.get(relation, (_AVOID_NEAR, _AVOID_NEAR, _AVOID_NEAR))
                low = np.array([lo[0] - grow_xy, lo[1] - grow_xy, (hi[2] if below < 0 else lo[2] - below)])
                high = np.array([hi[0] + grow_xy, hi[1] + grow_xy, (lo[2] if above < 0 else hi[2] + above)])
                if relation is Relation.BELOW:
                    low[2], high[2] = lo[2] - 3.0, hi[2]
                boxes.append(UniformBox.around(low, high))
        return tuple(boxes[: 4 * _MAX_AVOIDED])

    def _target_box(self, target: str, boxes: SceneBoxes, siblings: np.ndarray) -> np.ndarray:
        """The target's likely size and centre height (4,): its siblings' median, else the fitted table's
        (for its label or another name of its class), else the training targets' median."""
        if np.any(siblings):
            height = boxes.center[siblings, 2] - boxes.floor
            return np.append(np.median(boxes.size[siblings], axis=0), np.median(height))
        table = self.params.target_boxes
        for name in (target, *(lemmas(n) for n in other_names(target))):
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


def _reading(relation: Relation, label: str) -> tuple[Relation, bool]:
    """The relation a hypothesis reads for an anchor, and whether it is a vague stand-in: a relation the
    label policy (`app.grounding.box_relations.anchor_allowed`) does not give this anchor ("on the wall",
    "above the drawer") is read as "near", widened, never dropped (dropping it would lose the anchor's
    mass)."""
    if anchor_allowed(relation, lemmas(label)):
        return relation, False
    return Relation.NEAR, relation is not Relation.NEAR


def _spread(params: ProposerParams, name: str | None) -> float:
    return 1.0 if name is None else max(params.spreads.get(name, 1.0), MIN_SPREADS[name])


def softmax(scores: np.ndarray) -> np.ndarray:
    """exp(s_i - max s) / sum_j exp(s_j - max s)."""
    shifted = np.exp(scores - np.max(scores))
    probabilities: np.ndarray = shifted / shifted.sum()
    return probabilities


__all__ = [
    "BACKGROUND_FEATURES",
    "FEATURES",
    "REGION",
    "BuiltinProposer",
    "Candidates",
    "ProposerParams",
    "object_names",
    "softmax",
]
