"""The LSM on a tiny config: shapes, PD covariances, the loss, learning, checkpoints, features, the grounder.

Real inputs: tests/resources/lsm/cases.jsonl holds AI2-THOR's living_rooms_01 (the procthor package's
object metadata) with eight hand-written utterances, one per target removed from the scene.
"""

from __future__ import annotations

import dataclasses
import json
import math
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from app.data.cases import CaseTarget, GroundingCase, read_cases
from app.errors import NotFound
from app.evaluation.metrics import anees, nees
from app.grounding.hypotheses import Hypothesis
from app.grounding.parsing import target_noun
from app.grounding.relations import Relation
from app.lsm.checkpoint import file_sha256
from app.lsm.features import (
    PackedSamples,
    SceneArrays,
    label_text,
    make_sample,
    pair_features,
    percentile,
    rotation_z,
    to_world,
)
from app.lsm.grounder import DEFAULT_MODEL_DIR, LSMGrounder
from app.lsm.model import (
    RELATION_INDEX,
    ROLE_ANCHOR,
    ROLE_OTHER,
    LanguageSensorModel,
    LSMConfig,
    LSMOutput,
    load_checkpoint,
    save_checkpoint,
)
from app.lsm.text_encoder import MINILM_SHA256, TextEncoder
from app.scene_graph.model import SceneGraph
from app.training.lsm import (
    Densities,
    apply_calibration,
    density_summary,
    fit_calibration,
    predict,
    target_region,
)
from tests.conftest import moved_scene

CASES = Path(__file__).parent / "resources" / "lsm" / "cases.jsonl"
TINY = {
    "d_model": 32,
    "n_heads": 4,
    "d_ffn": 64,
    "n_spatial_layers": 1,
    "n_fusion_layers": 1,
    "pair_hidden": 16,
    "film_hidden": 16,
    "head_hidden1": 64,
    "head_hidden2": 32,
    "max_objects": 12,
}


def _fake_embed(texts: list[str]) -> np.ndarray:
    """Deterministic stand-in for the text encoder: a unit vector seeded by the text."""
    out = np.empty((len(texts), 384), dtype=np.float32)
    for i, text in enumerate(texts):
        v = np.random.default_rng(zlib.crc32(text.encode())).standard_normal(384)
        out[i] = v / np.linalg.norm(v)
    return out


@pytest.fixture(scope="module")
def cases():
    return list(read_cases(CASES))


@pytest.fixture(scope="module")
def packed(cases) -> PackedSamples:
    cfg = LSMConfig(**TINY)
    samples = [
        make_sample(
            c.scene_graph,
            c.hypotheses[0].anchor_ids,
            c.hypotheses[0].relation,
            c.target.label,
            cfg,
            c.target.position,
        )
        for c in cases
    ]
    return PackedSamples(samples, _fake_embed)


def _tiny_model(seed: int = 0, **overrides) -> LanguageSensorModel:
    torch.manual_seed(seed)
    return LanguageSensorModel(LSMConfig(**(TINY | overrides)))


def _perturb_head(model: LanguageSensorModel) -> None:
    """The head's last layer starts at zero (mu = t, isotropic L); give it weights so outputs vary."""
    with torch.no_grad():
        model.head[-1].weight.normal_(0.0, 0.3)
        model.head[-1].bias.normal_(0.0, 0.3)


def test_forward_shapes_and_positive_definite_covariances(packed):
    model = _tiny_model()
    _perturb_head(model)
    model.eval()
    batch = packed.batch()
    n = len(packed)
    assert batch.label_emb.shape == (n, 12, 384)
    assert batch.pair.shape == (n, 12, 12, 12)
    out = model(batch)
    assert out.mean.shape == (n, 3)
    assert out.chol.shape == (n, 3, 3)
    assert torch.all(torch.triu(out.chol, diagonal=1) == 0)
    cov = out.covariance
    assert torch.allclose(cov, cov.transpose(-1, -2))
    assert torch.all(torch.linalg.eigvalsh(cov.double()) > 0)
    # The tail: wider than the core (Sigma + Delta), with a weight below a_max.
    tail = out.tail_covariance
    assert tail is not None and out.tail_weight is not None
    assert torch.all(torch.linalg.eigvalsh((tail - cov).double()) > 0)
    assert torch.all((out.tail_weight > 0) & (out.tail_weight < 0.5))
    # The sigma floor: diag(L_w) = s * (softplus + 0.05) >= 0.05 s.
    floor = 0.05 * batch.region_scale
    assert torch.all(torch.diagonal(out.chol, dim1=-2, dim2=-1) >= floor - 1e-6)
    # tanh bounds the mean inside the region box t +- s.
    assert torch.all((out.mean - batch.region_shift).abs() <= batch.region_scale + 1e-5)


def test_padding_does_not_change_predictions(packed):
    """A sample predicts the same alone as inside a batch padded to a larger object count."""
    model = _tiny_model()
    _perturb_head(model)
    model.eval()
    with torch.no_grad():
        together = model(packed.batch())
        alone = model(packed.batch(torch.tensor([4])))
    assert torch.allclose(together.mean[4], alone.mean[0], atol=1e-5)
    assert torch.allclose(together.chol[4], alone.chol[0], atol=1e-5)


def test_loss_matches_hand_computed_gaussian_nll_plus_l1():
    model = _tiny_model(tail=False)
    mean = torch.tensor([[0.5, -1.0, 2.0], [0.0, 0.0, 0.0]])
    chol = torch.tensor(
        [
            [[0.3, 0.0, 0.0], [0.1, 0.4, 0.0], [-0.2, 0.05, 0.6]],
            [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.5]],
        ]
    )
    target = torch.tensor([[0.7, -0.6, 1.5], [1.0, -1.0, 0.25]])
    expected = []
    for m, lower, y in zip(mean.numpy(), chol.numpy(), target.numpy(), strict=True):
        nll = -multivariate_normal(mean=m, cov=lower @ lower.T).logpdf(y)
        expected.append(nll + 1.0 * np.abs(m - y).sum())
    loss = model.loss(LSMOutput(mean=mean, chol=chol), target)
    assert loss.item() == pytest.approx(np.mean(expected), rel=1e-5)
    # The second case by hand: diagonal Sigma = diag(1, 4, 0.25), y - mu = (1, -1, 0.25).
    nees = 1.0 + 1.0 / 4.0 + 0.0625 / 0.25
    nll = 0.5 * (math.log(1.0 * 4.0 * 0.25) + nees + 3 * math.log(2 * math.pi))
    assert expected[1] == pytest.approx(nll + 2.25)


def test_loss_of_the_core_and_tail_density_is_the_mixture_nll():
    model = _tiny_model()
    mean = torch.tensor([[0.5, -1.0, 2.0]])
    chol = torch.tensor([[[0.3, 0.0, 0.0], [0.1, 0.4, 0.0], [-0.2, 0.05, 0.6]]])
    tail_chol = torch.tensor([[[1.0, 0.0, 0.0], [0.2, 1.5, 0.0], [0.0, 0.1, 0.7]]])
    weight = torch.tensor([0.2])
    target = torch.tensor([[1.7, 0.6, 1.5]])
    out = LSMOutput(mean, chol, tail_chol, weight)
    core = (chol @ chol.transpose(-1, -2))[0].numpy()
    wide = core + (tail_chol @ tail_chol.transpose(-1, -2))[0].numpy()
    y, m = target[0].numpy(), mean[0].numpy()
    density = 0.8 * multivariate_normal(m, core).pdf(y) + 0.2 * multivariate_normal(m, wide).pdf(y)
    expected = -math.log(density) + np.abs(m - y).sum()
    assert model.loss(out, target).item() == pytest.approx(expected, rel=1e-5)
    np.testing.assert_allclose(out.moment_covariance()[0].numpy(), 0.8 * core + 0.2 * wide, rtol=1e-5)


def test_one_optimizer_step_lowers_the_loss_on_a_fixed_batch(packed):
    model = _tiny_model(seed=1)
    batch = packed.batch()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    model.eval()  # no dropout when measuring
    before = model.loss(model(batch), batch.target)
    optimizer.zero_grad()
    before.backward()
    optimizer.step()
    with torch.no_grad():
        after = model.loss(model(batch), batch.target)
    assert after.item() < before.item()


def test_checkpoint_round_trip(tmp_path, packed):
    model = _tiny_model(seed=2, relation_embedding=False, sigma_floor=0.07)
    _perturb_head(model)
    model.eval()
    extra = {"version": "test", "calibration": {"overall": 2.0, "per_relation": {"on": 1.5}}}
    weights = save_checkpoint(model, tmp_path, extra=extra)
    assert weights.name == "model.safetensors"
    loaded, meta = load_checkpoint(tmp_path)
    assert loaded.cfg == model.cfg
    assert meta["version"] == "test"
    assert meta["calibration"] == extra["calibration"]
    batch = packed.batch()
    with torch.no_grad():
        a, b = model(batch), loaded(batch)
    assert torch.equal(a.mean, b.mean)
    assert torch.equal(a.chol, b.chol)


def test_label_text_splits_camel_case_and_underscores():
    assert label_text("DiningTable") == "dining table"
    assert label_text("TVStand") == "tv stand"
    assert label_text("kitchen_counter") == "kitchen counter"
    assert label_text("  Trash  can ") == "trash can"


def test_a_composed_sample_embeds_the_target_name_apart_from_the_relation(cases):
    """text_input "composed": the sample's text is the relation-anchor phrase, the target's name is embedded
    on its own, and the sample's embedding is normalize(E(name) + E(phrase)), one row per distinct pair."""
    case = cases[5]  # between the sofa and the TV stand
    truth = case.hypotheses[0]
    cfg = LSMConfig(**TINY, text_input="composed")
    samples = [
        make_sample(case.scene_graph, truth.anchor_ids, truth.relation, name, cfg)
        for name in ("CoffeeTable", "mug", "mug")
    ]
    assert [(s.text, s.target_text) for s in samples] == [
        ("between the sofa and the tv stand", "coffee table"),
        ("between the sofa and the tv stand", "mug"),
        ("between the sofa and the tv stand", "mug"),
    ]
    packed = PackedSamples(samples, _fake_embed)
    for sample, row in zip(samples, packed.text_index.tolist(), strict=True):
        want = _fake_embed([sample.target_text])[0] + _fake_embed([sample.text])[0]
        np.testing.assert_allclose(packed.embeddings[row].numpy(), want / np.linalg.norm(want), atol=1e-6)
    assert packed.text_index[1] == packed.text_index[2] != packed.text_index[0]
    whole = make_sample(case.scene_graph, truth.anchor_ids, truth.relation, "mug", LSMConfig(**TINY))
    assert (whole.text, whole.target_text) == ("the mug between the sofa and the tv stand", None)
    with pytest.raises(ValueError, match="text_input"):
        make_sample(
            case.scene_graph, truth.anchor_ids, truth.relation, "mug", LSMConfig(**TINY, text_input="x")
        )


def test_a_composed_lsm_grounds_a_new_target_name_without_a_text_encoder_pass(cases):
    """With the vocabulary pinned (as the service starts) and the map's phrases seen once, hypotheses about
    a target name never asked for run no MiniLM pass, and ground as an encoder without pins does."""
    torch.manual_seed(0)
    model = LanguageSensorModel(LSMConfig(**TINY, text_input="composed"))
    meta = {"version": "test", "calibration": {}}
    pinned, plain = TextEncoder(cache_size=64), TextEncoder()
    pinned.pin(["kettle", "stapler", "umbrella"])
    passes: list[list[str]] = []
    embed = pinned._embed
    pinned._embed = lambda texts: passes.append(list(texts)) or embed(texts)  # type: ignore[method-assign]
    with_pins, without = LSMGrounder(model, meta, pinned, "0" * 64), LSMGrounder(model, meta, plain, "0" * 64)
    case = cases[5]
    truth = case.hypotheses[0]
    anchor = truth.anchor_ids[:1]
    hypotheses = [Hypothesis(truth.anchor_ids, truth.relation), Hypothesis(anchor, Relation.NEAR)]
    with_pins.ground(case.scene_graph, "the kettle is near the sofa", hypotheses)  # the map's texts, once
    passes.clear()
    for utterance in ["I left the stapler near the sofa", "my umbrella is near the sofa"]:
        got = with_pins.ground(case.scene_graph, utterance, hypotheses)
        want = without.ground(case.scene_graph, utterance, hypotheses)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a.means, b.means, atol=1e-4)
            np.testing.assert_allclose(a.covariances, b.covariances, atol=1e-4)
    assert passes == []


def test_make_sample_keeps_anchors_first_and_the_nearest_objects(cases):
    case = cases[5]  # between the sofa and the TV stand
    cfg = LSMConfig(**TINY)
    truth = case.hypotheses[0]
    sample = make_sample(
        case.scene_graph, truth.anchor_ids, truth.relation, "coffee table", cfg, case.target.position
    )
    assert sample.text == "the coffee table between the sofa and the tv stand"
    assert len(sample.labels) == cfg.max_objects
    assert sample.labels[:2] == ("sofa", "tv stand")
    assert sample.roles.tolist() == [ROLE_ANCHOR] * 2 + [ROLE_OTHER] * (cfg.max_objects - 2)
    anchors = np.array([case.scene_graph.object(i).center for i in truth.anchor_ids])
    dist = np.array([np.min(np.linalg.norm(anchors - o.center, axis=1)) for o in case.scene_graph.objects])
    world = np.array([sample.to_world(c.astype(np.float64), np.eye(3))[0] for c in sample.centers])
    kept_others = np.min(np.linalg.norm(anchors[None] - world[2:, None], axis=-1), axis=1)
    dropped = np.sort(dist)[cfg.max_objects :]
    assert kept_others.max() <= dropped.min() + 1e-5
    # The local frame: its origin the anchors' midpoint, the region reaching the margin beyond their joint
    # box (an axis-aligned scene keeps axis-aligned boxes: the frame turns by quarter turns only).
    sofa, tv_stand = (case.scene_graph.object(i) for i in truth.anchor_ids)
    midpoint = 0.5 * (np.asarray(sofa.center) + np.asarray(tv_stand.center))
    np.testing.assert_allclose(sample.origin, midpoint, atol=1e-9)
    assert sample.yaw % (math.pi / 2) == pytest.approx(0.0, abs=1e-12) or sample.yaw % (math.pi / 2) == (
        pytest.approx(math.pi / 2, abs=1e-12)
    )
    np.testing.assert_allclose(sample.region_shift, 0.0)
    low = np.minimum(sofa.min_corner, tv_stand.min_corner) - midpoint
    high = np.maximum(sofa.max_corner, tv_stand.max_corner) - midpoint
    turn = np.abs(np.round(rotation_z(sample.yaw)[:2, :2]))
    reach = np.maximum(high, -low)
    reach[:2] = turn.T @ reach[:2]
    np.testing.assert_allclose(sample.region_scale, reach + np.array([1.0, 1.0, 1.5]), atol=1e-5)
    np.testing.assert_allclose(
        sample.to_world(sample.target.astype(np.float64), np.eye(3))[0], case.target.position, atol=1e-5
    )


def test_ordinal_relations_get_a_scene_wide_frame(cases):
    case = cases[0]
    cfg = LSMConfig(**TINY)
    anchor = case.hypotheses[0].anchor_ids
    near = make_sample(case.scene_graph, anchor, Relation.NEAR, "remote", cfg)
    farthest = make_sample(case.scene_graph, anchor, Relation.FARTHEST, "remote", cfg)
    np.testing.assert_allclose(farthest.origin, near.origin)
    assert np.all(-farthest.region_scale <= farthest.scene_low + 1e-5)
    assert np.all(farthest.region_scale >= farthest.scene_high - 1e-5)
    assert np.all(farthest.region_scale >= near.region_scale)


def test_a_region_hypothesis_is_anchored_on_the_region_box(cases):
    case = cases[0]
    cfg = LSMConfig(**TINY)
    region = case.scene_graph.regions[0] if case.scene_graph.regions else None
    sample = make_sample(
        case.scene_graph, (), Relation.IN, "remote", cfg, region_id=region.id if region else None
    )
    assert sample.roles[0] == ROLE_ANCHOR and (sample.roles[1:] == ROLE_OTHER).all()
    low = np.min([o.min_corner for o in case.scene_graph.objects], axis=0)
    high = np.max([o.max_corner for o in case.scene_graph.objects], axis=0)
    expected_centre = region.center if region else 0.5 * (low + high)
    np.testing.assert_allclose(sample.origin, expected_centre, atol=1e-9)
    assert sample.text.startswith("the remote in the ")


def test_make_sample_rejects_unknown_anchor(cases):
    with pytest.raises(NotFound, match="no-such-object"):
        make_sample(cases[0].scene_graph, ["no-such-object"], Relation.ON, "x", LSMConfig(**TINY))


@pytest.mark.parametrize(
    ("yaw", "offset"),
    [
        (0.3, (5.0, -3.0, 0.0)),
        (2.0, (120.0, 40.0, -1.2)),
        (-1.2, (0.0, 0.0, 3.1)),
        (math.pi / 2, (1.0, 1.0, 1.0)),
    ],
)
def test_predictions_move_with_the_scene(tiny_checkpoint, encoder, cases, yaw, offset):
    """Turning the whole scene by any yaw, shifting it and raising its floor moves every density by the same
    rigid motion: the model sees only the local frame."""
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    case = cases[5]
    still = moved_scene(case.scene_graph, 0.0, np.zeros(3))
    moved = moved_scene(case.scene_graph, yaw, np.asarray(offset))
    sofa, tv_stand = case.hypotheses[0].anchor_ids
    hypotheses = [
        Hypothesis((sofa, tv_stand), Relation.BETWEEN),
        Hypothesis((sofa,), Relation.ON),
        Hypothesis((tv_stand,), Relation.FARTHEST),
        Hypothesis((), Relation.IN),
    ]
    turn = rotation_z(yaw)
    for before, after in zip(
        grounder.ground(still, case.utterance, hypotheses),
        grounder.ground(moved, case.utterance, hypotheses),
        strict=True,
    ):
        np.testing.assert_allclose(after.weights, before.weights, atol=1e-6)
        np.testing.assert_allclose(after.means, before.means @ turn.T + np.asarray(offset), atol=1e-4)
        np.testing.assert_allclose(after.covariances, turn @ before.covariances @ turn.T, atol=1e-6)


def test_words_that_do_not_constrain_position_do_not_move_the_density(tiny_checkpoint, encoder, cases):
    """The model reads the hypothesis ("the mug on the table"), not the rest of the utterance."""
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    case = cases[5]
    sofa, _ = case.hypotheses[0].anchor_ids
    hypothesis = [Hypothesis((sofa,), Relation.ON)]
    plain = grounder.ground(case.scene_graph, "the remote is on the sofa", hypothesis)[0]
    for said in (
        "the remote is on the sofa near the lamp",
        "I think my black remote is on the sofa, you know",
    ):
        other = grounder.ground(case.scene_graph, said, hypothesis)[0]
        assert np.abs(other.means - plain.means).max() < 0.05
        np.testing.assert_allclose(other.covariances, plain.covariances, atol=1e-9)


def test_pair_features_are_anchor_centric():
    centers = torch.tensor([[[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]]])  # (1, 2, 3)
    sizes = torch.tensor([[[2.0, 2.0, 2.0], [1.0, 1.0, 1.0]]])
    shift, scale = torch.zeros(1, 3), torch.full((1, 3), 2.0)
    pair = pair_features(centers, sizes, shift, scale)  # (1, 2, 2, 12)
    np.testing.assert_allclose(
        pair[0, 0, 1].numpy(), [1.5, 2.0, 0.0, 0.5, 0.5, 0.5, 0.25, 0.25, 0.25, 5.0, 0.0, 5.0]
    )
    np.testing.assert_allclose(pair[0, 1, 0, :3].numpy(), [-1.5, -2.0, 0.0])


@pytest.fixture(scope="module")
def encoder() -> TextEncoder:
    return TextEncoder()


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    model = _tiny_model(seed=3)
    _perturb_head(model)
    directory = tmp_path_factory.mktemp("lsm")
    save_checkpoint(
        model,
        directory,
        extra={
            "version": "tiny-test",
            "calibration": {"overall": 2.0, "per_relation": {"between": 4.0}, "tail_floor": 0.3},
            "text_encoder": {"sha256": MINILM_SHA256},
        },
    )
    return directory


def test_grounder_returns_one_core_and_tail_density_per_hypothesis(tiny_checkpoint, encoder, cases):
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    case = cases[5]
    sofa, tv_stand = case.hypotheses[0].anchor_ids
    hypotheses = [
        Hypothesis(anchor_ids=(sofa, tv_stand), relation=Relation.BETWEEN),
        Hypothesis(anchor_ids=(sofa,), relation=Relation.ON),
        Hypothesis(anchor_ids=(tv_stand,), relation=Relation.NEAR),
    ]
    densities = grounder.ground(case.scene_graph, case.utterance, hypotheses)
    assert len(densities) == 3
    for d in densities:
        assert d.weights.shape == (2,) and d.weights.sum() == pytest.approx(1.0) and d.weights[1] < 0.5
        np.testing.assert_allclose(d.means[0], d.means[1])
        for g in d.components:
            assert np.allclose(g.covariance, g.covariance.T)
            assert np.all(np.linalg.eigvalsh(g.covariance) > 0)
        assert np.all(np.linalg.eigvalsh(d.covariances[1] - d.covariances[0]) > -1e-9)
    assert grounder.ground(case.scene_graph, case.utterance, []) == []
    with pytest.raises(NotFound):
        grounder.ground(
            case.scene_graph, case.utterance, [Hypothesis(anchor_ids=("nope",), relation=Relation.ON)]
        )


def test_grounder_applies_calibration_and_matches_the_batched_evaluation_path(
    tiny_checkpoint, encoder, cases
):
    """Served densities = training-time predictions with every covariance scaled by c_r (between 4,
    others 2) and every tail weight a raised to a + (1 - a) 0.3: what `apply_calibration` scores."""
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    model, _ = load_checkpoint(tiny_checkpoint)
    samples, served = [], []
    for case in cases:
        truth = case.hypotheses[0]
        h = Hypothesis(anchor_ids=tuple(truth.anchor_ids), relation=truth.relation)
        served.append(grounder.ground(case.scene_graph, case.utterance, [h])[0])
        samples.append(
            make_sample(
                case.scene_graph,
                truth.anchor_ids,
                truth.relation,
                target_noun(case.utterance),
                model.cfg,
            )
        )
    predicted = predict(model, PackedSamples(samples, encoder.encode), samples, batch_size=3)
    groups = [case.hypotheses[0].relation.value for case in cases]
    scored = apply_calibration(predicted, groups, grounder.calibration)
    for k, (case, density) in enumerate(zip(cases, served, strict=True)):
        scale = 4.0 if case.hypotheses[0].relation is Relation.BETWEEN else 2.0
        np.testing.assert_allclose(density.means[0], predicted.means[k], atol=1e-4)
        np.testing.assert_allclose(density.covariances[0], scale * predicted.core[k], rtol=1e-3, atol=1e-6)
        np.testing.assert_allclose(density.covariances[1], scale * predicted.tail[k], rtol=1e-3, atol=1e-6)
        a = predicted.weights[k]
        np.testing.assert_allclose(density.weights[1], a + (1.0 - a) * 0.3, atol=1e-6)
        np.testing.assert_allclose(density.weights[1], scored.weights[k], atol=1e-6)
        np.testing.assert_allclose(density.covariances[1], scored.tail[k], rtol=1e-3, atol=1e-6)


def test_grounder_describe_names_the_weights(tiny_checkpoint, encoder):
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    info = grounder.describe()
    assert set(info) == {"name", "version", "config", "checksum"}
    assert info["name"] == "lsm" and info["version"] == "tiny-test"
    assert info["checksum"] == "sha256:" + file_sha256(tiny_checkpoint / "model.safetensors")
    assert info["config"]["model"]["d_model"] == 32


def test_shipped_model_grounds_every_relation(encoder, cases):
    """The weights in models/lsm load and give a core and a tail near the anchors for each fixture case."""
    grounder = LSMGrounder.load(DEFAULT_MODEL_DIR, encoder=encoder)
    assert (DEFAULT_MODEL_DIR / "MODEL_CARD.md").is_file()
    assert grounder.model.cfg.tail and grounder.model.cfg.contained_in and grounder.model.cfg.resting_on
    assert set(grounder.calibration["per_relation"]) >= {*(r.value for r in Relation), "region"}
    for case in cases:
        truth = case.hypotheses[0]
        hypothesis = Hypothesis(anchor_ids=tuple(truth.anchor_ids), relation=truth.relation)
        (density,) = grounder.ground(case.scene_graph, case.utterance, [hypothesis])
        assert len(density.weights) == 2 and density.weights[1] < 0.5
        assert np.all(np.linalg.eigvalsh(density.covariances) > 0)
        anchors = np.array([case.scene_graph.object(i).center for i in truth.anchor_ids])
        assert np.linalg.norm(density.mean() - anchors.mean(axis=0)) < 3.0


def _gaussians(means: np.ndarray, covs: np.ndarray) -> Densities:
    return Densities(means, covs, covs, np.zeros(len(means)))


def test_fit_calibration_brings_anees_to_three_and_shrinks_small_relations():
    rng = np.random.default_rng(5)
    n_big, n_small = 4000, 10
    relations = ["near"] * n_big + ["in"] * n_small
    n = n_big + n_small
    true_cov = np.diag([0.2, 0.1, 0.05])
    targets = rng.multivariate_normal(np.zeros(3), true_cov, size=n)
    means = np.zeros((n, 3))
    covs = np.tile(true_cov / 4.0, (n, 1, 1))  # 4x overconfident
    covs[n_big:] *= 0.25  # "in" 16x overconfident, but only 10 cases
    calibration = fit_calibration(_gaussians(means, covs), targets, relations, prior_cases=50.0)
    # For one Gaussian the NLL-optimal scale is ANEES / 3.
    assert calibration["per_relation"]["near"] == pytest.approx(
        nees(means[:n_big], covs[:n_big], targets[:n_big]).mean() / 3.0, rel=1e-4
    )
    scaled = apply_calibration(_gaussians(means, covs), relations, calibration)
    assert anees(means[:n_big], scaled.core[:n_big], targets[:n_big]) == pytest.approx(3.0, rel=0.01)
    # "in": own estimate ~16, pooled ~4; shrunk in log space with 10 own cases against 50 pooled pseudo-cases.
    own = nees(means[n_big:], covs[n_big:], targets[n_big:]).mean() / 3.0
    pooled = calibration["overall"]
    expected = math.exp((10 * math.log(own) + 50 * math.log(pooled)) / 60)
    assert calibration["per_relation"]["in"] == pytest.approx(expected, rel=1e-3)
    assert pooled < calibration["per_relation"]["in"] < own


def test_densities_score_a_calibrated_scale_mixture_at_nominal_coverage():
    """Targets drawn from the core-and-tail density itself: coverage at every mass, moment ANEES 3."""
    rng = np.random.default_rng(11)
    n = 3000
    core = np.tile(np.diag([0.04, 0.09, 0.01]), (n, 1, 1))
    tail = core * 16.0
    weights = np.full(n, 0.2)
    in_tail = rng.uniform(size=n) < weights
    noise = np.where(
        in_tail[:, None],
        rng.multivariate_normal(np.zeros(3), tail[0], size=n),
        rng.multivariate_normal(np.zeros(3), core[0], size=n),
    )
    means = rng.normal(size=(n, 3))
    densities = Densities(means, core, tail, weights)
    covered = densities.coverage(means + noise, np.random.default_rng(1))
    np.testing.assert_allclose(covered.mean(axis=0), [0.5, 0.9, 0.95], atol=0.03)
    assert anees(means, densities.moment_covariances, means + noise) == pytest.approx(3.0, rel=0.08)


def test_scene_arrays_match_the_scene_graph():
    """Boxes, the map's box and the floor height on a real 60-object ScanNet room; a turned copy of it
    has the turn as its dominant yaw."""
    scene_file = Path(__file__).parent / "resources" / "scenes" / "scannet_scene0590_00.json"
    scene_graph = SceneGraph.model_validate_json(scene_file.read_text(encoding="utf-8"))
    arrays = SceneArrays.of(scene_graph)
    low = np.min([o.min_corner for o in scene_graph.objects], axis=0)
    high = np.max([o.max_corner for o in scene_graph.objects], axis=0)
    np.testing.assert_allclose(arrays.map_box[0], 0.5 * (low + high))
    np.testing.assert_allclose(arrays.map_box[1], high - low)
    np.testing.assert_allclose(arrays.dims, [o.size for o in scene_graph.objects])
    bottoms = [o.min_corner[2] for o in scene_graph.objects]
    assert arrays.floor_z == pytest.approx(np.percentile(bottoms, 10))
    assert arrays.dominant_yaw == 0.0
    turned = SceneArrays.of(moved_scene(scene_graph, 0.4, np.zeros(3)))
    assert turned.dominant_yaw == pytest.approx(0.4)
    np.testing.assert_allclose(turned.map_box[1], arrays.map_box[1], atol=1e-9)
    assert turned.floor_z == pytest.approx(arrays.floor_z)


def _box_corners(center: np.ndarray, size: np.ndarray, yaw: float) -> np.ndarray:
    """The 8 corners (8, 3) of a box turned by yaw about its centre."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    return center + (0.5 * signs * size) @ rotation_z(yaw).T


@pytest.mark.parametrize("yaw", [0.0, 0.4, -2.9])
def test_a_samples_scene_box_is_the_box_of_every_corner_in_its_local_frame(yaw):
    """The scene box of each hypothesis (objects' and regions' boxes, computed once per frame yaw) equals
    the min and max of every box's corners carried into the sample's local frame, on a turned, shifted room
    with regions, for every anchor."""
    scene_file = Path(__file__).parent / "resources" / "scenes" / "scannet_scene0000_00.json"
    offset = np.array([3.0, -7.0, 1.5])
    room = SceneGraph.model_validate_json(scene_file.read_text(encoding="utf-8"))
    moved = moved_scene(room, yaw, offset)
    # Region boxes stay axis-aligned in the world; one of them reaches past every object.
    regions = [r.model_copy(update={"center": (r.center + offset).tolist()}) for r in room.regions]
    hall = regions[0].model_copy(update={"id": "hall", "center": (offset + np.array([9.0, 0, 0])).tolist()})
    scene_graph = moved.model_copy(update={"regions": [*regions, hall]})
    corners = np.concatenate(
        [_box_corners(np.asarray(o.center), np.asarray(o.size), o.yaw) for o in scene_graph.objects]
        + [_box_corners(np.asarray(r.center), np.asarray(r.size), 0.0) for r in scene_graph.regions]
    )  # (8 (M + R), 3)
    arrays = SceneArrays.of(scene_graph)
    cfg = LSMConfig(max_objects=8)
    for obj in scene_graph.objects:
        sample = make_sample(arrays, [obj.id], Relation.NEAR, "mug", cfg)
        local = (corners - sample.origin) @ rotation_z(sample.yaw)
        np.testing.assert_allclose(sample.scene_low, local.min(axis=0), atol=1e-5)
        np.testing.assert_allclose(sample.scene_high, local.max(axis=0), atol=1e-5)
    assert 1 <= len(arrays._turned_boxes) <= 5  # the dominant yaw plus -2 to 2 quarter turns


def test_samples_to_world_equals_turning_each_one():
    """`to_world` over a batch (each sample's frame, one or two covariances each) equals R mu + o and
    R Sigma R^T sample by sample."""
    scene_file = Path(__file__).parent / "resources" / "scenes" / "scannet_scene0590_00.json"
    scene_graph = moved_scene(
        SceneGraph.model_validate_json(scene_file.read_text(encoding="utf-8")), 0.7, np.array([2.0, 1.0, 0.5])
    )
    samples = [
        make_sample(scene_graph, [o.id], Relation.ON, "mug", LSMConfig()) for o in scene_graph.objects[:9]
    ]
    assert len({round(s.yaw, 6) for s in samples}) > 1  # the batch mixes frames
    rng = np.random.default_rng(0)
    means = rng.normal(size=(9, 3))
    factors = rng.normal(size=(9, 2, 3, 3))
    covariances = factors @ np.swapaxes(factors, -1, -2)  # (9, 2, 3, 3)
    world_means, world = to_world(samples, means, covariances)
    for k, sample in enumerate(samples):
        turn = rotation_z(sample.yaw)
        np.testing.assert_allclose(world_means[k], turn @ means[k] + sample.origin, atol=1e-12)
        for c in range(2):
            np.testing.assert_allclose(world[k, c], turn @ covariances[k, c] @ turn.T, atol=1e-12)
        mean, pair = sample.to_world(means[k], covariances[k])
        np.testing.assert_allclose(mean, world_means[k], atol=1e-12)
        np.testing.assert_allclose(pair, world[k], atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 7, 60, 151])
def test_percentile_equals_numpy(n):
    values = np.random.default_rng(n).normal(size=n)
    for q in (0.0, 10.0, 50.0, 97.5, 100.0):
        assert percentile(values, q) == pytest.approx(float(np.percentile(values, q)), rel=1e-12, abs=1e-12)


def _saturated(seed: int) -> LanguageSensorModel:
    """A tiny model with large head outputs: tanh saturates at the boxes' faces, softplus runs far."""
    model = _tiny_model(seed=seed)
    with torch.no_grad():
        model.head[-1].weight.normal_(0.0, 3.0)
        model.head[-1].bias.normal_(0.0, 3.0)
    return model.eval()


def test_the_mean_of_in_lies_inside_the_anchors_box(packed):
    """With contained_in, "in" means c + h tanh(.) over the anchor's box, whatever the head outputs."""
    model = _saturated(4)
    batch = dataclasses.replace(
        packed.batch(), relation=torch.full((len(packed),), RELATION_INDEX[Relation.IN])
    )
    with torch.no_grad():
        out = model(batch)
    assert torch.all(out.mean >= batch.anchor_low - 1e-5) and torch.all(out.mean <= batch.anchor_high + 1e-5)
    free = LanguageSensorModel(dataclasses.replace(model.cfg, contained_in=False))
    free.load_state_dict(model.state_dict())
    free.eval()
    with torch.no_grad():
        assert not torch.all(free(batch).mean <= batch.anchor_high + 1e-5)


def test_the_mean_of_on_a_plain_top_rests_above_it_and_over_its_footprint(packed):
    model = _saturated(5)
    on = RELATION_INDEX[Relation.ON]
    batch = dataclasses.replace(packed.batch(), relation=torch.full((len(packed),), on))
    plain = batch.plain_top
    assert plain.any() and (~plain).any()  # the fixture holds plain tops and seats (the sofa)
    with torch.no_grad():
        out = model(batch)
    top = batch.anchor_high[:, 2]
    assert torch.all(out.mean[plain, 2] > top[plain])
    assert torch.all(out.mean[plain, 2] <= top[plain] + model.cfg.on_lift * 20)
    assert torch.all(out.mean[plain, :2] >= batch.anchor_low[plain, :2] - 1e-5)
    assert torch.all(out.mean[plain, :2] <= batch.anchor_high[plain, :2] + 1e-5)
    # A seat keeps things inside its box (under the backrest): no constraint there.
    free = dataclasses.replace(model.cfg, resting_on=False)
    unconstrained = LanguageSensorModel(free)
    unconstrained.load_state_dict(model.state_dict())
    unconstrained.eval()
    with torch.no_grad():
        other = unconstrained(batch)
    torch.testing.assert_close(out.mean[~plain], other.mean[~plain])


def test_on_labels_rest_on_plain_tops_but_not_inside_seats(cases):
    from app.data.cases import CaseHypothesis
    from app.training.lsm import resting_position

    case = next(c for c in cases if c.hypotheses[0].relation is Relation.ON)
    anchor = case.scene_graph.object(case.hypotheses[0].anchor_ids[0])
    top = float(anchor.max_corner[2])
    sunk = case.model_copy(
        update={
            "target": case.target.model_copy(update={"position": [*case.target.position[:2], top - 0.05]})
        }
    )
    size_z = float(case.target.size[2])
    plain = sunk.model_copy(
        update={
            "scene_graph": sunk.scene_graph.model_copy(
                update={
                    "objects": [
                        o.model_copy(update={"label": "table"}) if o.id == anchor.id else o
                        for o in sunk.scene_graph.objects
                    ]
                }
            )
        }
    )
    assert resting_position(plain)[2] == pytest.approx(top + 0.5 * size_z)
    seat = plain.model_copy(
        update={
            "scene_graph": plain.scene_graph.model_copy(
                update={
                    "objects": [
                        o.model_copy(update={"label": "sofa"}) if o.id == anchor.id else o
                        for o in plain.scene_graph.objects
                    ]
                }
            )
        }
    )
    assert resting_position(seat)[2] == pytest.approx(top - 0.05)  # a seat holds things inside its box
    near = plain.model_copy(
        update={"hypotheses": [CaseHypothesis(anchor_ids=[anchor.id], relation=Relation.NEAR)]}
    )
    assert resting_position(near) == list(near.target.position)


def test_resting_on_moves_the_train_split_s_on_labels_and_no_other_split_s(tmp_path, cases):
    from app.training.lsm import TrainConfig, _load_splits, resting_position

    moved = [c for c in cases if resting_position(c) != list(c.target.position)]
    assert moved  # the fixture holds an "on" case whose target sinks into its plain top
    data = {"train": str(CASES), "calib": str(CASES), "val_unseen": str(CASES), "region_rate": 0.0}
    own = np.array([c.target.position for c in cases])
    for resting_on in (False, True):
        config = TrainConfig.from_dict({"data": {**data, "resting_on": resting_on}, "model": TINY})
        splits = _load_splits(config)
        expected = np.array([resting_position(c) for c in cases]) if resting_on else own
        np.testing.assert_allclose(splits["train"].targets, expected, atol=1e-6)
        np.testing.assert_allclose(splits["calib"].targets, own, atol=1e-6)
        np.testing.assert_allclose(splits["val_unseen"].targets, own, atol=1e-6)


def test_a_training_run_writes_its_own_history_only(tmp_path):
    from app.training.lsm import TrainConfig, train

    config = TrainConfig.from_dict(
        {
            "data": {"train": str(CASES), "calib": str(CASES), "embedding_cache": str(tmp_path / "emb.npz")},
            "model": TINY,
            "optim": {"epochs": 1, "batch_size": 4, "eval_every_steps": 1, "threads": 1},
        }
    )
    for _ in range(2):  # the second run into the same folder replaces the first's history
        report = train(config, tmp_path / "run")
    lines = (tmp_path / "run" / "history.jsonl").read_text(encoding="utf-8").splitlines()
    assert [json.loads(line)["step"] for line in lines] == list(range(1, report["training"]["steps"] + 1))


def test_max_train_cases_counts_cases_not_their_region_samples():
    from app.training.lsm import load_split

    split = load_split("t", str(CASES), LSMConfig(**TINY), limit=3, region_rate=1.0)
    assert len(split.samples) == 6 and split.groups.count("region") == 3


def test_a_checkpoint_is_scored_on_features_made_as_its_own_config_says(tiny_checkpoint, tmp_path):
    from app.training.lsm import TrainConfig, evaluate_checkpoint

    data = {"train": str(CASES), "calib": str(CASES), "embedding_cache": str(tmp_path / "emb.npz")}
    own = TrainConfig.from_dict({"data": data, "model": TINY})
    other = TrainConfig.from_dict(
        {"data": data, "model": {**TINY, "max_objects": 4, "region_margin_xy": 3.0}}
    )
    scored = [
        evaluate_checkpoint(tiny_checkpoint, c)["splits"]["calib"]["lsm"]["overall"] for c in (own, other)
    ]
    assert scored[0] == scored[1]


def test_the_calibration_margin_multiplies_every_scale():
    rng = np.random.default_rng(3)
    targets = rng.normal(size=(500, 3))
    covs = np.tile(np.eye(3), (500, 1, 1))
    relations = ["near"] * 250 + ["on"] * 250
    plain = fit_calibration(_gaussians(np.zeros((500, 3)), covs), targets, relations)
    wider = fit_calibration(_gaussians(np.zeros((500, 3)), covs), targets, relations, margin=1.25)
    assert wider["margin"] == 1.25 and wider["overall"] == pytest.approx(1.25 * plain["overall"])
    for relation in ("near", "on"):
        assert wider["per_relation"][relation] == pytest.approx(1.25 * plain["per_relation"][relation])
    own = fit_calibration(
        _gaussians(np.zeros((500, 3)), covs), targets, relations, margin=1.1, margins={"near": 1.4}
    )
    assert own["per_relation"]["near"] == pytest.approx(1.4 * plain["per_relation"]["near"])
    assert own["per_relation"]["on"] == pytest.approx(1.1 * plain["per_relation"]["on"])


def test_the_tail_floor_raises_every_tail_weight_before_the_scales_are_fitted():
    """Targets from a density with a 20% tail; the model says 0%: with a floor of 0.2 the fitted densities
    are the true ones (scale 1), without it the fitted scale has to stretch the core instead."""
    rng = np.random.default_rng(7)
    n = 6000
    core, tail = np.tile(np.eye(3) * 0.04, (n, 1, 1)), np.tile(np.eye(3) * 1.0, (n, 1, 1))
    in_tail = rng.uniform(size=n) < 0.2
    targets = np.where(in_tail[:, None], rng.normal(size=(n, 3)) * 1.0, rng.normal(size=(n, 3)) * 0.2)
    model = Densities(np.zeros((n, 3)), core, tail, np.zeros(n))
    relations = ["near"] * n
    floored = fit_calibration(model, targets, relations, tail_floor=0.2)
    plain = fit_calibration(model, targets, relations)
    assert floored["tail_floor"] == 0.2 and plain["tail_floor"] == 0.0
    assert floored["per_relation"]["near"] == pytest.approx(1.0, abs=0.05)
    assert plain["per_relation"]["near"] > 3.0
    served = apply_calibration(model, relations, floored)
    np.testing.assert_allclose(served.weights, 0.2)
    assert (
        np.mean(served.nll(targets)) < np.mean(apply_calibration(model, relations, plain).nll(targets)) - 0.3
    )


def test_the_nees_fit_makes_each_relations_moment_anees_three_where_the_nll_fit_does_not():
    """Targets from a core with a 5% wide tail; the model serves a 20% tail, as a floor would. The NLL-optimal
    scale fits the core and leaves the moment-matched ANEES far under 3 (the wide tail carries the moments);
    the NEES-consistent scale makes it 3 / margin per relation (one pooled group, so no shrinkage)."""
    rng = np.random.default_rng(13)
    n = 8000
    core, tail = np.tile(np.eye(3) * 0.04, (n, 1, 1)), np.tile(np.eye(3) * 1.0, (n, 1, 1))
    in_tail = rng.uniform(size=n) < 0.05
    targets = np.where(in_tail[:, None], rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) * 0.2)
    model = Densities(np.zeros((n, 3)), core, tail, np.full(n, 0.2))
    relations = ["below"] * n

    def served_anees(calibration: dict[str, Any]) -> float:
        served = apply_calibration(model, relations, calibration)
        return anees(served.means, served.moment_covariances, targets)

    by_nll = fit_calibration(model, targets, relations)
    by_nees = fit_calibration(model, targets, relations, margin=1.25, fit="nees")
    assert by_nees["fit"] == "nees" and by_nll["fit"] == "nll"
    assert served_anees(by_nees) == pytest.approx(3.0 / 1.25, rel=1e-9)
    assert served_anees(by_nll) < 2.0
    with pytest.raises(ValueError, match="calibration fit"):
        fit_calibration(model, targets, relations, fit="ece")


def test_a_training_config_names_its_calibration_fit_and_an_unknown_one_fails_before_training():
    from app.training.lsm import TrainConfig

    data = {"train": "train.jsonl", "calib": "calib.jsonl"}
    assert TrainConfig.from_dict({"data": data}).calibration_fit == "nll"
    assert TrainConfig.from_dict({"data": data, "calibration_fit": "nees"}).calibration_fit == "nees"
    with pytest.raises(ValueError, match="calibration_fit must be one of"):
        TrainConfig.from_dict({"data": data, "calibration_fit": "ece"})


def test_recalibrate_keeps_the_weights_and_writes_its_calibration_and_config(tiny_checkpoint, tmp_path):
    from app.training.lsm import TrainConfig, recalibrate

    config = TrainConfig.from_dict(
        {
            "data": {"train": str(CASES), "calib": str(CASES), "embedding_cache": str(tmp_path / "emb.npz")},
            "model": TINY,
            "version": "tiny-recalibrated",
            "calibration_margin": 1.25,
            "calibration_fit": "nees",
        }
    )
    out = tmp_path / "recalibrated"
    report = recalibrate(tiny_checkpoint, config, out)
    before, _ = load_checkpoint(tiny_checkpoint)
    after, meta = load_checkpoint(out)
    for name, tensor in before.state_dict().items():
        assert torch.equal(tensor, after.state_dict()[name])
    assert meta["version"] == "tiny-recalibrated" and meta["calibration"]["fit"] == "nees"
    assert meta["calibration"]["margin"] == 1.25 and meta["calibration"] == report["calibration"]
    written = json.loads((out / "train_config.json").read_text(encoding="utf-8"))
    assert written["calibration_fit"] == "nees" and written["version"] == "tiny-recalibrated"
    assert (out / "metrics.md").is_file() and "calib" in report["splits"]


def test_a_split_knows_each_samples_room_and_convention_and_the_report_uses_them(tmp_path, cases):
    """Region samples share their case's room; the report's ANEES interval is the one over those rooms, and
    its per-convention rows hold the object samples of each convention's cases."""
    from app.data.cases import write_cases
    from app.evaluation.metrics import clustered_interval
    from app.training.lsm import load_split, summarize

    rooms = ["room_a" if i < len(cases) // 2 else "room_b" for i in range(len(cases))]
    path = tmp_path / "cases.jsonl"
    conventions = ["sr3d" if i % 2 else "vla3d" for i in range(len(cases))]
    moved = [
        c.model_copy(update={"meta": {"scene_id": r, "convention": k, "source": f"source_{r}"}})
        for c, r, k in zip(cases, rooms, conventions, strict=True)
    ]
    write_cases(path, moved)
    split = load_split("t", str(path), LSMConfig(**TINY), region_rate=1.0)
    assert len(split.rooms) == len(split.samples) == 2 * len(cases)
    assert split.rooms == [r for r in rooms for _ in range(2)]  # each case, then its region sample
    n = len(split.samples)
    rng = np.random.default_rng(0)
    spread = np.repeat(rng.uniform(0.5, 2.0, size=n), 9).reshape(n, 3, 3) * np.eye(3)
    densities = Densities(split.targets + rng.normal(size=(n, 3)), spread, spread, np.zeros(n))
    report = summarize(densities, split, None)
    objects = np.asarray(split.groups) != "region"
    per_case = nees(densities.means, densities.moment_covariances, split.targets)[objects]
    expected = clustered_interval(per_case, np.asarray(split.rooms)[objects])
    assert expected is not None and report["overall"]["anees_ci90"] == pytest.approx(list(expected))
    # Per source and group: every sample of the source in that group, region samples included.
    sources = np.asarray(split.sources)
    assert {k.rsplit(" ", 1)[0] for k in report["per_source_group"]} == {"source_room_a", "source_room_b"}
    for key, summary in report["per_source_group"].items():
        source, group = key.rsplit(" ", 1)
        assert summary["n"] == int(np.sum((sources == source) & (np.asarray(split.groups) == group)))
    # Per convention and relation: the object samples the cases of that convention made, and no other.
    relations = [c.hypotheses[0].relation.value for c in cases]
    expected_keys = {f"{k} {r}" for k, r in zip(conventions, relations, strict=True)}
    assert set(report["per_convention"]) == expected_keys
    for key, summary in report["per_convention"].items():
        assert summary["n"] == sum(f"{k} {r}" == key for k, r in zip(conventions, relations, strict=True))


def test_a_region_sample_names_the_room_the_case_says_not_an_overlapping_neighbour() -> None:
    """Turned rooms' boxes overlap near a shared wall: the smaller box there is the neighbour's."""
    rooms = [
        {"id": "2", "name": "living room", "center": [0.0, 0.0, 1.2], "size": [6.0, 6.0, 2.4]},
        {"id": "4", "name": "hall", "center": [3.2, 0.0, 1.2], "size": [1.0, 4.0, 2.4]},
    ]
    scene = SceneGraph.model_validate({"regions": rooms, "objects": []})
    target = CaseTarget(label="mug", position=[2.9, 0.0, 0.8])
    said = GroundingCase(
        case_id="c", scene_graph=scene, utterance="u", target=target, meta={"target_region_id": 2}
    )
    assert target_region(said) == "2"
    unsaid = GroundingCase(case_id="c", scene_graph=scene, utterance="u", target=target)
    assert target_region(unsaid) == "4"  # without the case's word, the smallest box holding it


def test_the_training_report_scores_the_no_language_baseline_as_the_evaluation_does() -> None:
    """A target outside the map box has no uniform density: left out of the baseline's mean and counted as
    better, as `vlmap eval static` counts it (the report had used the box's volume for it)."""
    means = np.zeros((2, 3))
    covariances = np.repeat(np.eye(3)[None], 2, axis=0)
    densities = Densities(means, covariances, covariances, np.zeros(2))
    baseline = np.array([4.0, math.inf])  # `no_language_nll` of a target inside, and of one outside
    summary = density_summary(densities, np.zeros((2, 3)), baseline, None)
    assert summary["uniform_nll"] == 4.0 and summary["uniform_outside"] == 1
    assert summary["better_than_uniform"] == 1.0  # NLL 2.76 < 4, and anything < inf
