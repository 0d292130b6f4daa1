"""The LSM on a tiny config: shapes, PD covariances, the loss, learning, checkpoints, features, the grounder.

Real inputs: tests/resources/lsm/cases.jsonl holds AI2-THOR's living_rooms_01 (the procthor package's
object metadata) with eight hand-written utterances, one per target removed from the scene.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from app.data.cases import read_cases
from app.errors import NotFound
from app.evaluation.metrics import anees, nees
from app.grounding.hypotheses import Hypothesis
from app.grounding.relations import Relation
from app.lsm.features import (
    PackedSamples,
    SceneArrays,
    label_text,
    make_sample,
    pair_features,
    percentile,
)
from app.lsm.grounder import DEFAULT_MODEL_DIR, LSMGrounder
from app.lsm.model import (
    ROLE_ANCHOR,
    ROLE_OTHER,
    LanguageSensorModel,
    LSMConfig,
    LSMOutput,
    load_checkpoint,
    save_checkpoint,
)
from app.lsm.text_encoder import MINILM_SHA256, TextEncoder, file_sha256
from app.lsm.train import apply_calibration, fit_calibration, predict
from app.scene_graph.model import SceneGraph

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
            c.utterance,
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
    model = _tiny_model()
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


def test_make_sample_keeps_anchors_first_and_the_nearest_objects(cases):
    case = cases[5]  # between the sofa and the TV stand
    cfg = LSMConfig(**TINY)
    truth = case.hypotheses[0]
    sample = make_sample(
        case.scene_graph, truth.anchor_ids, truth.relation, case.utterance, cfg, case.target.position
    )
    assert len(sample.labels) == cfg.max_objects
    assert sample.labels[:2] == ("sofa", "tv stand")
    assert sample.roles.tolist() == [ROLE_ANCHOR] * 2 + [ROLE_OTHER] * (cfg.max_objects - 2)
    anchors = np.array([case.scene_graph.object(i).center for i in truth.anchor_ids])
    dist = np.array([np.min(np.linalg.norm(anchors - o.center, axis=1)) for o in case.scene_graph.objects])
    kept_others = np.min(np.linalg.norm(anchors[None] - sample.centers[2:, None], axis=-1), axis=1)
    dropped = np.sort(dist)[cfg.max_objects :]
    assert kept_others.max() <= dropped.min()
    # The region frame: centred on the anchors' midpoint, reaching the margin beyond their joint box.
    sofa, tv_stand = (case.scene_graph.object(i) for i in truth.anchor_ids)
    midpoint = 0.5 * (np.asarray(sofa.center) + np.asarray(tv_stand.center))
    np.testing.assert_allclose(sample.region_shift, midpoint, atol=1e-6)
    low = np.minimum(sofa.min_corner, tv_stand.min_corner)
    high = np.maximum(sofa.max_corner, tv_stand.max_corner)
    reach = np.maximum(high - midpoint, midpoint - low) + np.array([1.0, 1.0, 1.5])
    np.testing.assert_allclose(sample.region_scale, reach, atol=1e-5)


def test_ordinal_relations_get_a_scene_wide_frame(cases):
    case = cases[0]
    cfg = LSMConfig(**TINY)
    anchor = case.hypotheses[0].anchor_ids
    near = make_sample(case.scene_graph, anchor, Relation.NEAR, case.utterance, cfg)
    farthest = make_sample(case.scene_graph, anchor, Relation.FARTHEST, case.utterance, cfg)
    np.testing.assert_allclose(farthest.region_shift, near.region_shift)
    low, high = case.scene_graph.bounds()
    assert np.all(farthest.region_shift - farthest.region_scale <= low + 1e-5)
    assert np.all(farthest.region_shift + farthest.region_scale >= high - 1e-5)
    assert np.all(farthest.region_scale >= near.region_scale)


def test_make_sample_rejects_unknown_anchor(cases):
    with pytest.raises(NotFound, match="no-such-object"):
        make_sample(cases[0].scene_graph, ["no-such-object"], Relation.ON, "x", LSMConfig(**TINY))


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
            "calibration": {"overall": 2.0, "per_relation": {"between": 4.0}},
            "text_encoder": {"sha256": MINILM_SHA256},
        },
    )
    return directory


def test_grounder_returns_one_pd_gaussian_per_hypothesis(tiny_checkpoint, encoder, cases):
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    case = cases[5]
    sofa, tv_stand = case.hypotheses[0].anchor_ids
    hypotheses = [
        Hypothesis(anchor_ids=(sofa, tv_stand), relation=Relation.BETWEEN),
        Hypothesis(anchor_ids=(sofa,), relation=Relation.ON),
        Hypothesis(anchor_ids=(tv_stand,), relation=Relation.NEAR),
    ]
    gaussians = [d.components[0] for d in grounder.ground(case.scene_graph, case.utterance, hypotheses)]
    assert len(gaussians) == 3
    for g in gaussians:
        assert g.mean.shape == (3,) and np.all(np.isfinite(g.mean))
        assert np.allclose(g.covariance, g.covariance.T)
        assert np.all(np.linalg.eigvalsh(g.covariance) > 0)
    assert grounder.ground(case.scene_graph, case.utterance, []) == []
    with pytest.raises(NotFound):
        grounder.ground(
            case.scene_graph, case.utterance, [Hypothesis(anchor_ids=("nope",), relation=Relation.ON)]
        )


def test_grounder_applies_calibration_and_matches_the_batched_evaluation_path(
    tiny_checkpoint, encoder, cases
):
    """Served Gaussians = training-time predictions with Sigma scaled by c_r (between 4, others 2)."""
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    model, _ = load_checkpoint(tiny_checkpoint)
    samples, served = [], []
    for case in cases:
        truth = case.hypotheses[0]
        h = Hypothesis(anchor_ids=tuple(truth.anchor_ids), relation=truth.relation)
        served.append(grounder.ground(case.scene_graph, case.utterance, [h])[0].components[0])
        samples.append(
            make_sample(case.scene_graph, truth.anchor_ids, truth.relation, case.utterance, model.cfg)
        )
    means, covs = predict(model, PackedSamples(samples, encoder.encode), batch_size=3)
    for case, g, m, c in zip(cases, served, means, covs, strict=True):
        scale = 4.0 if case.hypotheses[0].relation is Relation.BETWEEN else 2.0
        np.testing.assert_allclose(g.mean, m, atol=1e-4)
        np.testing.assert_allclose(g.covariance, scale * c, rtol=1e-3, atol=1e-6)


def test_grounder_describe_names_the_weights(tiny_checkpoint, encoder):
    grounder = LSMGrounder.load(tiny_checkpoint, encoder=encoder)
    info = grounder.describe()
    assert set(info) == {"name", "version", "config", "checksum"}
    assert info["name"] == "lsm" and info["version"] == "tiny-test"
    assert info["checksum"] == "sha256:" + file_sha256(tiny_checkpoint / "model.safetensors")
    assert info["config"]["model"]["d_model"] == 32


def test_shipped_model_grounds_every_relation(encoder, cases):
    """The weights in models/lsm load and give a PD Gaussian near the anchors for each fixture case."""
    grounder = LSMGrounder.load(DEFAULT_MODEL_DIR, encoder=encoder)
    assert (DEFAULT_MODEL_DIR / "MODEL_CARD.md").is_file()
    assert set(grounder.calibration["per_relation"]) >= {"on", "in", "near", "between", "above", "below"}
    for case in cases:
        truth = case.hypotheses[0]
        hypothesis = Hypothesis(anchor_ids=tuple(truth.anchor_ids), relation=truth.relation)
        ((g,),) = (d.components for d in grounder.ground(case.scene_graph, case.utterance, [hypothesis]))
        assert np.all(np.linalg.eigvalsh(g.covariance) > 0)
        anchors = np.array([case.scene_graph.object(i).center for i in truth.anchor_ids])
        assert np.linalg.norm(g.mean - anchors.mean(axis=0)) < 3.0


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
    calibration = fit_calibration(means, covs, targets, relations, prior_cases=50.0)
    assert calibration["per_relation"]["near"] == pytest.approx(4.0, rel=0.05)
    scaled = apply_calibration(covs, relations, calibration)
    assert anees(means[:n_big], scaled[:n_big], targets[:n_big]) == pytest.approx(3.0, rel=0.05)
    # "in": own estimate ~16, pooled ~4; shrunk with 10 own cases against 50 pooled pseudo-cases.
    own = nees(means[n_big:], covs[n_big:], targets[n_big:]).mean() / 3.0
    pooled = calibration["overall"]
    expected = (10 * own + 50 * pooled) / 60
    assert calibration["per_relation"]["in"] == pytest.approx(expected)
    assert pooled < calibration["per_relation"]["in"] < own


def test_scene_arrays_match_the_scene_graph():
    """Bounds (objects and regions), boxes and floor height on a real 60-object ScanNet room."""
    scene_file = Path(__file__).parent / "resources" / "scenes" / "scannet_scene0590_00.json"
    scene_graph = SceneGraph.model_validate_json(scene_file.read_text(encoding="utf-8"))
    assert scene_graph.regions
    arrays = SceneArrays.of(scene_graph)
    low, high = scene_graph.bounds()
    np.testing.assert_allclose(arrays.bounds[0], low)
    np.testing.assert_allclose(arrays.bounds[1], high)
    np.testing.assert_allclose(arrays.sizes, [2.0 * o.half_extent for o in scene_graph.objects])
    bottoms = [o.min_corner[2] for o in scene_graph.objects]
    assert arrays.floor_z == pytest.approx(np.percentile(bottoms, 10))


@pytest.mark.parametrize("n", [1, 2, 7, 60, 151])
def test_percentile_equals_numpy(n):
    values = np.random.default_rng(n).normal(size=n)
    for q in (0.0, 10.0, 50.0, 97.5, 100.0):
        assert percentile(values, q) == pytest.approx(float(np.percentile(values, q)), rel=1e-12, abs=1e-12)
