"""The Language Sensor Model: one hypothesis h = (anchor(s), relation) + the scene graph -> N(mu, Sigma).

Two transformer stages over tokens built by `app.lsm.features`:

1. spatial backbone over [Q_target; objects]: pre-norm self-attention whose logits get a learned pairwise
   bias from a 12-d anchor-centric pair feature (MLP 12 -> 64 -> n_heads, FiLM-conditioned on the text);
2. fusion backbone over [text; Q_target; objects] (standard pre-norm encoder).

The fused target-query token, FiLM-modulated by the anchor region's (s, t), feeds a head 256 -> 1024 -> 512
-> 9: mu = tanh(.) in the region frame, L lower-triangular with softplus diagonal + sigma floor, then
mu_w = s * mu + t, L_w = diag(s) L, Sigma = L_w L_w^T (the reference's appendix table, equation by equation).
Deviations (see models/lsm/MODEL_CARD.md): the relation also enters as an embedding on the text token and
as a per-relation linear map of the region condition added to the head's outputs; and with `tail` (on by
default) each hypothesis's density keeps mass where the model can be wrong, a scale mixture of a core and a
wider Gaussian about the same mean,

    p(y | h) = (1 - a) N(y; mu, Sigma) + a N(y; mu, Sigma + Delta),   Delta = D_w D_w^T,

with D_w = diag(s) D (D lower-triangular, softplus diagonal) and a = a_max sigmoid(.) from 7 more head
outputs (16 in all). Support physics by construction (`decode_head`): the mean of "in" lies inside the
anchor's box, the mean of "on" a plain top (not a seat or a shelf) over its footprint and above its top.

Loss (reference appendix, with the density above), lambda_1 = 1:
    L = -log p(y | h) + lambda_1 ||mu - y||_1,
without the tail:
    L = 1/2 (log|Sigma| + (y - mu)^T Sigma^-1 (y - mu) + 3 log 2 pi)
        + lambda_1 ||mu - y||_1.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from app.grounding.relations import Relation
from app.lsm.checkpoint import CONFIG_NAME, WEIGHTS_NAME

#: Row of each relation in the relation embedding table (enum order; fixed for saved checkpoints).
RELATION_INDEX = {relation: index for index, relation in enumerate(Relation)}
ROLE_QUERY, ROLE_ANCHOR, ROLE_OTHER = 0, 1, 2
_LOG_2PI = math.log(2.0 * math.pi)


#: How a checkpoint turns a hypothesis into its text embedding (`text_input`; see app.lsm.features).
TEXT_INPUTS = ("hypothesis", "composed")


@dataclass
class LSMConfig:
    """Every size of the model and of its input features. Defaults are the reference's sizes."""

    text_dim: int = 384  # frozen MiniLM sentence embedding (utterance and object labels)
    object_feature_dim: int = 13  # 12-d geometry + cosine(label, utterance), see features.object_features
    pair_dim: int = 12  # anchor-centric pair feature, see features.pair_features
    region_cond_dim: int = 10  # features.region_condition: s, t's height, where the room lies around t
    n_relations: int = len(Relation)
    d_model: int = 256
    n_heads: int = 8
    d_ffn: int = 1024
    n_spatial_layers: int = 3
    n_fusion_layers: int = 3
    pair_hidden: int = 64
    film_hidden: int = 64
    head_hidden1: int = 1024
    head_hidden2: int = 512
    dropout: float = 0.1  # inside the transformer blocks
    head_dropout: float = 0.15
    sigma_floor: float = 0.05  # on L's diagonal, in region units (world: 0.05 * s)
    relation_embedding: bool = True  # deviation from the reference: the relation also enters explicitly
    relation_prior: bool = True  # deviation: per-relation affine map region_cond -> head output
    l1_weight: float = 1.0
    tail: bool = True  # deviation: a wider Gaussian per hypothesis with a learned weight
    tail_max_weight: float = 0.5  # a < a_max: the core stays the heavier part
    contained_in: bool = True  # deviation: the mean of "in" lies inside the anchor's box
    resting_on: bool = True  # deviation: the mean of "on" a plain top lies over it, above its top
    on_lift: float = 0.25  # metres: the "on" mean's height above the top is on_lift * softplus(.)
    # Input features (they define the output frame, so they travel with the weights).
    max_objects: int = 150  # nearest to the anchor(s), anchors always kept
    region_margin_xy: float = 1.0  # s = reach of the anchors' joint box from t + margin (metres), per axis
    region_margin_z: float = 1.5
    region_min_half_extent: float = 0.5  # floor on every component of s (metres)
    ordinal_scene_frame: bool = True  # closest/farthest: s grows to reach the whole scene's bounding box
    # How a hypothesis's text embedding is made (TEXT_INPUTS): "hypothesis", one MiniLM pass over
    # "the mug on the table"; "composed", normalize(E("mug") + E("on the table")), the target's name and the
    # relation-anchor phrase embedded apart, so that a new target name costs no pass (names are pinned).
    text_input: str = "hypothesis"

    def __post_init__(self) -> None:
        if self.text_input not in TEXT_INPUTS:
            msg = f"LSM text_input {self.text_input!r} is not one of {TEXT_INPUTS}"
            raise ValueError(msg)

    @property
    def n_outputs(self) -> int:
        """The head's outputs: mean (3), L (6), and with the tail D (6) and the tail's weight (1)."""
        return 16 if self.tail else 9

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> LSMConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            msg = f"unknown LSMConfig fields {unknown}"
            raise ValueError(msg)
        return cls(**values)


@dataclass
class LSMBatch:
    """Padded model inputs for B hypotheses with up to N objects each (see `app.lsm.features`)."""

    text_emb: torch.Tensor  # (B, E) utterance embedding
    label_emb: torch.Tensor  # (B, N, E) object label embeddings
    object_features: torch.Tensor  # (B, N, F)
    pair: torch.Tensor  # (B, N, N, P)
    roles: torch.Tensor  # (B, N) long: ROLE_ANCHOR or ROLE_OTHER
    mask: torch.Tensor  # (B, N) bool, True for real objects
    relation: torch.Tensor  # (B,) long, RELATION_INDEX
    region_shift: torch.Tensor  # (B, 3) t, metres
    region_scale: torch.Tensor  # (B, 3) s, metres
    anchor_low: torch.Tensor  # (B, 3) the anchors' joint box
    anchor_high: torch.Tensor  # (B, 3)
    plain_top: torch.Tensor  # (B,) bool: one anchor with a plain top surface (not a seat or a shelf)
    region_cond: torch.Tensor  # (B, C)
    target: torch.Tensor | None = None  # (B, 3) metres, for training and evaluation


class LSMOutput(NamedTuple):
    mean: torch.Tensor  # (B, 3) the samples' frame
    chol: torch.Tensor  # (B, 3, 3) lower-triangular L_w, Sigma = L_w L_w^T (the core)
    tail_chol: torch.Tensor | None = None  # (B, 3, 3) D_w: the tail's covariance is Sigma + D_w D_w^T
    tail_weight: torch.Tensor | None = None  # (B,) a

    @property
    def covariance(self) -> torch.Tensor:
        return self.chol @ self.chol.transpose(-1, -2)  # (B, 3, 3)

    @property
    def tail_covariance(self) -> torch.Tensor | None:
        if self.tail_chol is None:
            return None
        return self.covariance + self.tail_chol @ self.tail_chol.transpose(-1, -2)  # (B, 3, 3)

    def moment_covariance(self) -> torch.Tensor:
        """The density's covariance, (1 - a) Sigma + a (Sigma + Delta) = Sigma + a Delta, (B, 3, 3)."""
        if self.tail_chol is None or self.tail_weight is None:
            return self.covariance
        delta = self.tail_chol @ self.tail_chol.transpose(-1, -2)
        return self.covariance + self.tail_weight[:, None, None] * delta


class Block(nn.Module):
    """Pre-norm transformer block; `attn_bias` (B, H, T, T) is added to the attention logits."""

    def __init__(self, cfg: LSMConfig) -> None:
        super().__init__()
        self.n_heads = cfg.n_heads
        self.ln1 = nn.LayerNorm(cfg.d_model)
        self.qkv = nn.Linear(cfg.d_model, 3 * cfg.d_model)
        self.proj = nn.Linear(cfg.d_model, cfg.d_model)
        self.ln2 = nn.LayerNorm(cfg.d_model)
        self.fc = nn.Linear(cfg.d_model, cfg.d_ffn)
        self.fc_out = nn.Linear(cfg.d_ffn, cfg.d_model)
        self.dropout = cfg.dropout

    def forward(self, x: torch.Tensor, attn_bias: torch.Tensor) -> torch.Tensor:
        bsz, seq, dim = x.shape
        q, k, v = self.qkv(self.ln1(x)).split(dim, dim=-1)  # (B, T, D) each
        q, k, v = (
            t.view(bsz, seq, self.n_heads, dim // self.n_heads).transpose(1, 2) for t in (q, k, v)
        )  # (B, H, T, d)
        p = self.dropout if self.training else 0.0
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_bias, dropout_p=p)  # (B, H, T, d)
        x = x + F.dropout(self.proj(y.transpose(1, 2).reshape(bsz, seq, dim)), p, self.training)
        return x + F.dropout(self.fc_out(F.gelu(self.fc(self.ln2(x)))), p, self.training)


class LanguageSensorModel(nn.Module):
    def __init__(self, cfg: LSMConfig) -> None:
        super().__init__()
        self.cfg = cfg
        dim = cfg.d_model
        self.text_proj = nn.Linear(cfg.text_dim, dim)
        self.label_proj = nn.Linear(cfg.text_dim, dim)
        self.feature_proj = nn.Sequential(
            nn.Linear(cfg.object_feature_dim, dim), nn.GELU(), nn.Linear(dim, dim)
        )
        self.role_emb = nn.Embedding(3, dim)  # target-query / anchor / other
        self.modality_emb = nn.Embedding(2, dim)  # text / object
        self.relation_emb = nn.Embedding(cfg.n_relations, dim) if cfg.relation_embedding else None
        self.query = nn.Parameter(torch.zeros(dim))
        # Pairwise attention bias: 12 -> 64 -> n_heads, the hidden layer FiLM-modulated by the text token.
        self.pair_in = nn.Linear(cfg.pair_dim, cfg.pair_hidden)
        self.pair_film = nn.Linear(dim, 2 * cfg.pair_hidden)
        self.pair_out = nn.Linear(cfg.pair_hidden, cfg.n_heads)
        self.spatial = nn.ModuleList(Block(cfg) for _ in range(cfg.n_spatial_layers))
        self.fusion = nn.ModuleList(Block(cfg) for _ in range(cfg.n_fusion_layers))
        self.ln_f = nn.LayerNorm(dim)
        # Head FiLM: the region (s, t) scales and shifts the pooled context.
        self.region_film = nn.Sequential(
            nn.Linear(cfg.region_cond_dim, cfg.film_hidden), nn.GELU(), nn.Linear(cfg.film_hidden, 2 * dim)
        )
        # Deviation: a per-relation affine map of the region condition added to the head's output. The
        # shared head did not learn relation-specific displacements such as "farthest" -> across the room.
        self.relation_prior = (
            nn.Linear(cfg.region_cond_dim, cfg.n_outputs * cfg.n_relations) if cfg.relation_prior else None
        )
        self.head = nn.Sequential(
            nn.Linear(dim, cfg.head_hidden1),
            nn.GELU(),
            nn.Dropout(cfg.head_dropout),
            nn.Linear(cfg.head_hidden1, cfg.head_hidden2),
            nn.GELU(),
            nn.Dropout(cfg.head_dropout),
            nn.Linear(cfg.head_hidden2, cfg.n_outputs),
        )
        self.apply(self._init_weights)
        # Start every FiLM at identity and every prediction at (mu = t, L = (softplus(0) + floor) I).
        for layer in (self.pair_film, self.region_film[-1], self.head[-1], self.relation_prior):
            if layer is None:
                continue
            assert isinstance(layer, nn.Linear)
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, mean=0.0, std=0.02)
            nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding):
            nn.init.normal_(module.weight, mean=0.0, std=0.02)

    def forward(self, batch: LSMBatch) -> LSMOutput:
        cfg = self.cfg
        bsz, n_obj, _ = batch.label_emb.shape
        text = self.text_proj(batch.text_emb) + self.modality_emb.weight[0]  # (B, D)
        if self.relation_emb is not None:
            text = text + self.relation_emb(batch.relation)
        objects = (
            self.label_proj(batch.label_emb)
            + self.feature_proj(batch.object_features)
            + self.role_emb(batch.roles)
            + self.modality_emb.weight[1]
        )  # (B, N, D)
        query = (self.query + self.role_emb.weight[ROLE_QUERY]).expand(bsz, 1, -1)  # (B, 1, D)

        # Spatial backbone over [Q; objects] with the text-conditioned pairwise bias (zero for Q's row/col).
        # pair_out(h * (1 + gamma) + beta) = h (W diag(1 + gamma))^T + (W beta + c): folding the FiLM into
        # per-sample output weights spares two passes over the (B, N, N, 64) hidden tensor.
        gamma, beta = self.pair_film(text).chunk(2, dim=-1)  # (B, 64) each
        hidden = F.gelu(self.pair_in(batch.pair)).view(bsz, n_obj * n_obj, -1)  # (B, N*N, 64)
        w_out = self.pair_out.weight[None] * (1.0 + gamma[:, None, :])  # (B, H, 64)
        b_out = beta @ self.pair_out.weight.T + self.pair_out.bias  # (B, H)
        pair_bias = torch.baddbmm(b_out[:, None, :], hidden, w_out.transpose(1, 2))  # (B, N*N, H)
        pair_bias = pair_bias.view(bsz, n_obj, n_obj, -1).permute(0, 3, 1, 2)  # (B, H, N, N)
        pad = torch.zeros(
            bsz, cfg.n_heads, n_obj + 1, n_obj + 1, dtype=pair_bias.dtype, device=pair_bias.device
        )
        pad[:, :, 1:, 1:] = pair_bias
        key_ok = torch.cat([batch.mask.new_ones(bsz, 1), batch.mask], dim=1)  # (B, 1 + N)
        spatial_bias = pad.masked_fill(~key_ok[:, None, None, :], float("-inf"))  # (B, H, 1 + N, 1 + N)
        x = torch.cat([query, objects], dim=1)  # (B, 1 + N, D)
        for block in self.spatial:
            x = block(x, spatial_bias)

        # Fusion backbone over [text; Q; objects].
        x = torch.cat([text[:, None, :], x], dim=1)  # (B, 2 + N, D)
        fusion_ok = torch.cat([batch.mask.new_ones(bsz, 1), key_ok], dim=1)  # (B, 2 + N)
        fusion_bias = torch.zeros(bsz, 1, 1, n_obj + 2, dtype=x.dtype, device=x.device)
        fusion_bias = fusion_bias.masked_fill(~fusion_ok[:, None, None, :], float("-inf"))  # (B, 1, 1, 2 + N)
        for block in self.fusion:
            x = block(x, fusion_bias)
        pooled = self.ln_f(x[:, 1])  # (B, D): the target-query token

        scale, shift = self.region_film(batch.region_cond).chunk(2, dim=-1)  # (B, D) each
        out = self.head(pooled * (1.0 + scale) + shift)  # (B, O)
        if self.relation_prior is not None:
            prior = self.relation_prior(batch.region_cond).view(bsz, cfg.n_relations, cfg.n_outputs)
            out = out + prior[torch.arange(bsz), batch.relation]  # (B, O)
        box = AnchorBox(batch.relation, batch.anchor_low, batch.anchor_high, batch.plain_top)
        return decode_head(out, batch.region_shift, batch.region_scale, cfg, box)

    def loss(self, output: LSMOutput, target: torch.Tensor) -> torch.Tensor:
        """Mean over the batch of the density's NLL (nats) + l1_weight * ||mu - y||_1."""
        return (density_nll(output, target) + self.cfg.l1_weight * l1_error(output.mean, target)).mean()


def _lower(diag: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
    """Lower-triangular (B, 3, 3) from a diagonal (B, 3) and (L_10, L_20, L_21) (B, 3)."""
    zero = torch.zeros_like(diag[:, 0])
    return torch.stack(
        [diag[:, 0], zero, zero, off[:, 0], diag[:, 1], zero, off[:, 1], off[:, 2], diag[:, 2]], dim=-1
    ).view(-1, 3, 3)


class AnchorBox(NamedTuple):
    """What the head's physics reads of each sample: its relation and its anchors' joint box."""

    relation: torch.Tensor  # (B,) RELATION_INDEX
    low: torch.Tensor  # (B, 3)
    high: torch.Tensor  # (B, 3)
    plain_top: torch.Tensor  # (B,) bool


def decode_head(
    out: torch.Tensor,
    shift: torch.Tensor,
    scale: torch.Tensor,
    cfg: LSMConfig,
    box: AnchorBox | None = None,
) -> LSMOutput:
    """The head's outputs (B, O) as the density: mu = s tanh(.) + t, L_w = diag(s) L, and the tail.

    With the anchors' `box` (centre c, half sides h, top z_top), support physics by construction:
    - "in" (`cfg.contained_in`): mu = c + h tanh(.), inside the container's box;
    - "on" a plain top (`cfg.resting_on`): mu_xy = c_xy + h_xy tanh(.) over its footprint and
      mu_z = z_top + on_lift softplus(.) above its top surface.
    """
    squashed = torch.tanh(out[:, :3])  # (B, 3) region frame
    chol = _lower(F.softplus(out[:, 3:6]) + cfg.sigma_floor, out[:, 6:9])  # (B, 3, 3)
    s, t = scale, shift  # (B, 3) each
    mean = s * squashed + t
    if box is not None:
        centre, half = 0.5 * (box.low + box.high), 0.5 * (box.high - box.low)  # (B, 3) each
        inside = centre + half * squashed
        if cfg.contained_in:
            mean = torch.where((box.relation == RELATION_INDEX[Relation.IN])[:, None], inside, mean)
        if cfg.resting_on:
            lifted = box.high[:, 2] + cfg.on_lift * F.softplus(out[:, 2])  # (B,)
            resting = torch.cat([inside[:, :2], lifted[:, None]], dim=1)
            rows = (box.relation == RELATION_INDEX[Relation.ON]) & box.plain_top
            mean = torch.where(rows[:, None], resting, mean)
    tail_chol = tail_weight = None
    if cfg.tail:
        tail_chol = s[:, :, None] * _lower(F.softplus(out[:, 9:12]) + cfg.sigma_floor, out[:, 12:15])
        tail_weight = cfg.tail_max_weight * torch.sigmoid(out[:, 15])  # (B,)
    return LSMOutput(mean, s[:, :, None] * chol, tail_chol, tail_weight)


def density_nll(output: LSMOutput, target: torch.Tensor) -> torch.Tensor:
    """-log p(y | h) per row, (B,): the core Gaussian's NLL, or the core-and-tail mixture's."""
    core = gaussian_nll(output.mean, output.chol, target)
    if output.tail_chol is None or output.tail_weight is None:
        return core
    tail_cov = output.tail_covariance
    assert tail_cov is not None
    tail = gaussian_nll(output.mean, torch.linalg.cholesky(tail_cov), target)
    a = output.tail_weight
    return -torch.logsumexp(torch.stack([torch.log1p(-a) - core, torch.log(a) - tail]), dim=0)


def gaussian_nll(mean: torch.Tensor, chol: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1/2 (log|Sigma| + (y - mu)^T Sigma^-1 (y - mu) + 3 log 2 pi), Sigma = L L^T, per row; shape (B,)."""
    diff = (target - mean).unsqueeze(-1)  # (B, 3, 1)
    z = torch.linalg.solve_triangular(chol, diff, upper=False).squeeze(-1)  # (B, 3): L^-1 (y - mu)
    log_det = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)  # (B,)
    nll: torch.Tensor = 0.5 * (log_det + (z * z).sum(-1) + 3 * _LOG_2PI)
    return nll


def l1_error(mean: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """||mu - y||_1 per row; shape (B,)."""
    return (mean - target).abs().sum(-1)


def save_checkpoint(model: LanguageSensorModel, directory: Path, extra: dict[str, Any] | None = None) -> Path:
    """Write `model.safetensors` and `config.json`: the model config plus `extra` (calibration, ...)."""
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(directory / WEIGHTS_NAME))
    meta = {"model": asdict(model.cfg), **(extra or {})}
    (directory / CONFIG_NAME).write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return directory / WEIGHTS_NAME


def load_checkpoint(directory: Path) -> tuple[LanguageSensorModel, dict[str, Any]]:
    """Rebuild the model from `config.json`, load the weights (strict); returns (eval-mode model, config)."""
    from safetensors.torch import load_file

    directory = Path(directory)
    meta = json.loads((directory / CONFIG_NAME).read_text(encoding="utf-8"))
    # A checkpoint's config lists every field; one without "tail" predates the tail (one Gaussian), one
    # without "contained_in" or "resting_on" the box constraints of "in" and "on".
    older = {"tail": False, "contained_in": False, "resting_on": False}
    model = LanguageSensorModel(LSMConfig.from_dict(older | meta["model"]))
    model.load_state_dict(load_file(str(directory / WEIGHTS_NAME)), strict=True)
    model.eval()
    return model, meta
