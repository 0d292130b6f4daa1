"""`LSMInference` (the serving forward pass) equals `LanguageSensorModel.forward` (the training path)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from app.data.cases import read_cases
from app.grounding.relations import Relation
from app.lsm.features import PackedSamples, SceneArrays, make_sample
from app.lsm.grounder import DEFAULT_MODEL_DIR
from app.lsm.inference import LSMInference
from app.lsm.model import LanguageSensorModel, LSMConfig, LSMOutput, load_checkpoint
from app.scene_graph.model import SceneGraph
from tests.test_lsm_model import TINY as TINY_ONE_LAYER
from tests.test_lsm_model import _fake_embed

CASES = Path(__file__).parent / "resources" / "lsm" / "cases.jsonl"
SCENE = Path(__file__).parent / "resources" / "scenes" / "scannet_scene0590_00.json"
#: The model tests' tiny configuration with two layers of each kind (the fast path folds per layer).
TINY = {**TINY_ONE_LAYER, "n_spatial_layers": 2, "n_fusion_layers": 2}


def _reference(model: LanguageSensorModel, packed: PackedSamples) -> LSMOutput:
    with torch.inference_mode():
        return model.eval()(packed.batch())


def _assert_same(actual: LSMOutput, expected: LSMOutput) -> None:
    torch.testing.assert_close(actual.mean, expected.mean, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(actual.chol, expected.chol, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(actual.covariance, expected.covariance, atol=1e-5, rtol=1e-5)


def _perturbed_tiny_model(**overrides: int) -> LanguageSensorModel:
    """Every weight random: the zero-initialised FiLMs, head output and relation prior would hide errors."""
    torch.manual_seed(3)
    model = LanguageSensorModel(LSMConfig(**{**TINY, **overrides}))
    with torch.no_grad():
        for param in model.parameters():
            param.copy_(0.3 * torch.randn_like(param))
    return model.eval()


@pytest.fixture(scope="module")
def perturbed_tiny_model() -> LanguageSensorModel:
    return _perturbed_tiny_model()


@pytest.mark.parametrize("n_fusion_layers", [0, 1, 2])
def test_matches_the_model_on_padded_samples_with_every_relation(n_fusion_layers):
    """Samples with 3 to 12 objects (so the batch is padded), anchors of one or two objects, all relations."""
    model = _perturbed_tiny_model(n_fusion_layers=n_fusion_layers)
    cfg = model.cfg
    cases = list(read_cases(CASES))
    samples = []
    for i, case in enumerate(cases):
        for j, relation in enumerate(Relation):
            truth = case.hypotheses[0]
            anchors = truth.anchor_ids if relation is Relation.BETWEEN else truth.anchor_ids[:1]
            small = dataclasses.replace(cfg, max_objects=3 + (i + j) % 10)
            samples.append(make_sample(case.scene_graph, anchors, relation, case.utterance, small))
    packed = PackedSamples(samples, _fake_embed)
    assert not bool(packed.mask.all())
    _assert_same(LSMInference(model)(packed), _reference(model, packed))


def test_matches_the_model_on_an_unpadded_batch(perturbed_tiny_model):
    """Without padding no attention mask is built; the result must not change."""
    case = next(iter(read_cases(CASES)))
    anchor = case.hypotheses[0].anchor_ids[:1]
    samples = [
        make_sample(case.scene_graph, anchor, relation, case.utterance, perturbed_tiny_model.cfg)
        for relation in (Relation.ON, Relation.NEAR, Relation.FARTHEST)
    ]
    packed = PackedSamples(samples, _fake_embed)
    assert bool(packed.mask.all())
    _assert_same(LSMInference(perturbed_tiny_model)(packed), _reference(perturbed_tiny_model, packed))


def test_matches_the_shipped_model_on_a_60_object_room():
    model, _ = load_checkpoint(DEFAULT_MODEL_DIR)
    scene = SceneArrays.of(SceneGraph.model_validate_json(SCENE.read_text(encoding="utf-8")))
    rng = np.random.default_rng(0)
    samples = []
    for relation in Relation:
        anchors = rng.choice(scene.ids, 2 if relation is Relation.BETWEEN else 1, replace=False)
        samples.append(make_sample(scene, list(anchors), relation, "the mug next to the lamp", model.cfg))
    packed = PackedSamples(samples, _fake_embed)
    _assert_same(LSMInference(model)(packed), _reference(model, packed))
