"""`LSMGrounder`: the trained LSM behind the `Grounder` protocol, one Gaussian per hypothesis.

All hypotheses of a call go through the model in one batched forward pass (`LSMInference`: the model's
forward pass in fewer tensor operations, equal to it to float32 rounding). The checkpoint's post-hoc
calibration (a covariance scale c_r per relation, fitted on val_seen so that ANEES_r = 3 there) is applied
to every output: Sigma <- c_r Sigma.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from app.errors import ModelUnavailable
from app.grounding.hypotheses import Hypothesis
from app.grounding.mixture import GaussianMixture, project_to_pd
from app.grounding.parsing import target_noun
from app.lsm.checkpoint import CONFIG_NAME, LSM_NAME, WEIGHTS_NAME, description, file_sha256
from app.lsm.features import PackedSamples, Sample, SceneArrays, make_sample, to_world
from app.lsm.inference import LSMInference
from app.lsm.model import LanguageSensorModel, LSMOutput, load_checkpoint
from app.lsm.text_encoder import TextEncoder
from app.scene_graph.model import SceneGraph

DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[2] / "models" / "lsm"


#: The calibration key of region hypotheses (no anchor object): they are not "in" an object.
REGION_KEY = "region"


def calibration_key(hypothesis: Hypothesis) -> str:
    """The relation's name, or `REGION_KEY` for a region hypothesis."""
    return hypothesis.relation.value if hypothesis.anchor_ids else REGION_KEY


def calibration_scale(calibration: Mapping[str, Any], key: str) -> float:
    """c for this relation (or `REGION_KEY`); the overall scale for keys the calibration set did not hold;
    1 if none."""
    per_relation = calibration.get("per_relation", {})
    return float(per_relation.get(key, calibration.get("overall", 1.0)))


def calibrated_tail_weight(calibration: Mapping[str, Any], a: np.ndarray | float) -> np.ndarray | float:
    """The tail's weight after calibration, a' = a + (1 - a) eps with eps = `tail_floor` (0 if absent).

    The tail is the wide component the model learned for its own errors; on maps unlike its training the
    errors are heavier-tailed than it learned (most of the excess is a few cases far off), so every density
    keeps at least a share eps on its tail. eps is a calibration constant, chosen on one leave-one-source-
    out fold and checked on the other (the model card).
    """
    eps = float(calibration.get("tail_floor", 0.0))
    return a + (1.0 - a) * eps


class LSMGrounder:
    """The learned spatial grounder (`name = "lsm"`)."""

    name = LSM_NAME

    def __init__(
        self, model: LanguageSensorModel, meta: dict[str, Any], encoder: TextEncoder, weights_sha256: str
    ) -> None:
        self.model = model.eval()
        self.inference = LSMInference(self.model)
        self.meta = meta
        self.encoder = encoder
        self.weights_sha256 = weights_sha256
        self.version = str(meta.get("version", "unversioned"))
        self.calibration: dict[str, Any] = meta.get("calibration", {})

    @classmethod
    def load(
        cls,
        model_dir: Path = DEFAULT_MODEL_DIR,
        threads: int | None = None,
        encoder: TextEncoder | None = None,
    ) -> LSMGrounder:
        """Read `model.safetensors` + `config.json` from `model_dir`; the text encoder must match its sha256.

        `threads` sets torch's intra-op threads for the whole process (left alone when None).
        """
        model_dir = Path(model_dir)
        if not (model_dir / WEIGHTS_NAME).is_file() or not (model_dir / CONFIG_NAME).is_file():
            msg = f"no LSM checkpoint in {model_dir} (expected {WEIGHTS_NAME} and {CONFIG_NAME})"
            raise ModelUnavailable(msg)
        if threads is not None:
            torch.set_num_threads(threads)
        model, meta = load_checkpoint(model_dir)
        expected = meta.get("text_encoder", {}).get("sha256")
        if encoder is None:
            encoder = TextEncoder() if expected is None else TextEncoder(expected_sha256=expected)
        elif expected is not None and encoder.sha256 != expected:
            msg = f"text encoder sha256 {encoder.sha256} differs from the LSM's training encoder ({expected})"
            raise ModelUnavailable(msg)
        return cls(model, meta, encoder, file_sha256(model_dir / WEIGHTS_NAME))

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        """One density per hypothesis: the core Gaussian and the tail (a scale mixture), calibrated."""
        if not hypotheses:
            return []
        cfg = self.model.cfg
        scene = SceneArrays.of(scene_graph)
        target = target_noun(utterance, tuple(r.name.lower() for r in scene_graph.regions if r.name))
        samples = [
            make_sample(scene, h.anchor_ids, h.relation, target, cfg, region_id=h.region_id)
            for h in hypotheses
        ]
        out = self.inference(PackedSamples(samples, self.encoder.encode))
        scales = np.array([calibration_scale(self.calibration, calibration_key(h)) for h in hypotheses])
        return self._densities(samples, out, scales)

    def _densities(self, samples: list[Sample], out: LSMOutput, scales: np.ndarray) -> list[GaussianMixture]:
        """Every hypothesis's density in the world frame at once: its covariances scaled by the calibration's
        c, its tail's weight raised to the calibration's floor, repaired onto the PD cone in one batch."""
        covariances = out.covariance.double().numpy()[:, None]  # (K, 1, 3, 3)
        weights = np.ones((len(samples), 1))  # (K, C)
        if out.tail_covariance is not None and out.tail_weight is not None:
            a = np.asarray(calibrated_tail_weight(self.calibration, out.tail_weight.double().numpy()))  # (K,)
            covariances = np.concatenate([covariances, out.tail_covariance.double().numpy()[:, None]], axis=1)
            weights = np.stack([1.0 - a, a], axis=1)
        means, world = to_world(samples, out.mean.double().numpy(), scales[:, None, None, None] * covariances)
        repaired = project_to_pd(world)  # (K, C, 3, 3)
        n_components = weights.shape[1]
        return [
            GaussianMixture(weights[k], np.repeat(means[k : k + 1], n_components, axis=0), repaired[k])
            for k in range(len(samples))
        ]

    def describe(self) -> dict[str, Any]:
        return description(self.meta, self.weights_sha256)
