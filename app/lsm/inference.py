"""`LSMInference`: the LSM's forward pass for serving, equal to `LanguageSensorModel.forward` to float32
rounding but with a fraction of its tensor operations.

The model's forward pass (the training path) takes an `LSMBatch`: every object's 384-d label embedding,
the (B, N, N, 12) pair features, and one module call per layer. At serving sizes (5 hypotheses of up to
32 objects) its cost is mostly per-operation overhead and passes over the (B, N, N, 64) pair tensor, so
this module computes the same function from a `PackedSamples` directly:

- label and utterance projections (and the label-utterance cosines) are computed once per distinct text
  and gathered, instead of once per (hypothesis, object);
- every constant added to a token (biases, role and modality embeddings, the query) is summed once here;
- the pair MLP's first layer is linear in per-object terms except for the pair distance, so
  W f_ij + b = r_i + c_j + d_ij w_d with r, c computed per object: the (B, N, N, 12) feature tensor and
  its GEMM are never built;
- the last fusion block computes keys and values for every token but the rest (query, projection, FFN)
  only for the target-query token, the one token the head reads;
- attention masks are only built when some sample is padded.

The model must not change after this object is built (its weights are read once). Eval mode only: no
dropout.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from app.lsm.features import PackedSamples, object_geometry, region_condition
from app.lsm.model import ROLE_QUERY, AnchorBox, Block, LanguageSensorModel, LSMOutput, decode_head


class LSMInference:
    """A frozen view of a `LanguageSensorModel` for inference; call it on `PackedSamples`."""

    def __init__(self, model: LanguageSensorModel) -> None:
        self.model = model.eval()
        self.cfg = cfg = model.cfg
        dim = cfg.d_model
        self.feature_in, self.feature_out = _linears(model.feature_proj)
        self.film_in, self.film_out = _linears(model.region_film)
        self.head = _linears(model.head)
        self.spatial = [_as_block(b) for b in model.spatial]
        self.fusion = [_as_block(b) for b in model.fusion]
        with torch.no_grad():
            # One GEMM projects every distinct text both ways: rows [label_proj; text_proj].
            self.text_weights = torch.cat([model.label_proj.weight, model.text_proj.weight]).t().contiguous()
            text_bias = model.text_proj.bias + model.modality_emb.weight[0]  # (D,)
            if model.relation_emb is not None:
                self.text_bias = text_bias + model.relation_emb.weight  # (R, D): per relation
            else:
                self.text_bias = text_bias.expand(cfg.n_relations, dim).clone()
            # Everything an object token adds besides its label and geometry, per role.
            self.object_bias = (
                model.role_emb.weight
                + model.modality_emb.weight[1]
                + model.label_proj.bias
                + self.feature_out.bias
            )  # (3, D)
            self.query = model.query + model.role_emb.weight[ROLE_QUERY]  # (D,)
            # pair_in on f_ij = [(c_j - c_i)/s, h_i, h_j (3 each), ||c_j - c_i||, a_i, a_j], split by object:
            # row term r_i = [c_i/s, h_i, a_i] @ [-W_rel, W_hi, w_ai]^T + b,
            # column term c_j = [c_j/s, h_j, a_j] @ [W_rel, W_hj, w_aj]^T.
            w, b = model.pair_in.weight, model.pair_in.bias  # (P, 12), (P,)
            rel, half_i, half_j, to_i, to_j = w[:, 0:3], w[:, 3:6], w[:, 6:9], w[:, 10:11], w[:, 11:12]
            row_w = torch.cat([-rel, half_i, to_i], dim=1)  # (P, 7)
            col_w = torch.cat([rel, half_j, to_j], dim=1)  # (P, 7)
            self.pair_terms_weight = torch.cat([row_w, col_w])  # (2P, 7)
            self.pair_terms_bias = torch.cat([b, torch.zeros_like(b)])[:, None]  # (2P, 1)
            self.pair_dist_weight = w[:, 9, None, None].clone()  # (P, 1, 1)

    def __call__(self, packed: PackedSamples) -> LSMOutput:
        with torch.inference_mode():
            return self._forward(packed)

    def _forward(self, packed: PackedSamples) -> LSMOutput:
        model, cfg = self.model, self.cfg
        mask = packed.mask  # (B, N)
        bsz, n_obj = mask.shape
        dim = cfg.d_model
        padded = not bool(mask.all())
        centers, sizes = packed.centers, packed.sizes  # (B, N, 3)
        shift, scale, floor_z = packed.shift, packed.scale, packed.floor_z

        # Texts: label and utterance projections of each distinct text, then gathered.
        projected = packed.embeddings @ self.text_weights  # (U, 2D)
        label_tokens, text_tokens = projected[:, :dim], projected[:, dim:]
        utterance_emb = packed.embeddings[packed.text_index]  # (B, E)
        text = text_tokens[packed.text_index] + self.text_bias[packed.relation]  # (B, D)
        relevance = (packed.embeddings @ utterance_emb.t()).t().gather(1, packed.label_index)  # (B, N)

        # Object tokens: label + feature MLP + role/modality/bias constants.
        geometry = object_geometry(centers, sizes, shift, scale, floor_z)  # (B, N, 12)
        features = torch.cat([geometry, relevance[..., None]], dim=-1)  # (B, N, 13)
        hidden = F.gelu(F.linear(features, self.feature_in.weight, self.feature_in.bias))  # (B, N, D)
        base = label_tokens[packed.label_index] + self.object_bias[packed.roles]  # (B, N, D)
        objects = torch.addmm(base.view(-1, dim), hidden.view(-1, dim), self.feature_out.weight.t())
        objects = objects.view(bsz, n_obj, dim)

        spatial_bias = self._spatial_bias(centers, sizes, shift, scale, text, mask if padded else None)
        x = torch.cat([self.query.expand(bsz, 1, dim), objects], dim=1)  # (B, 1 + N, D)
        for block in self.spatial:
            x = _block(block, x, spatial_bias)

        x = torch.cat([text[:, None, :], x], dim=1)  # (B, 2 + N, D)
        fusion_bias = None
        if padded:
            key_ok = torch.cat([mask.new_ones(bsz, 2), mask], dim=1)  # (B, 2 + N)
            fusion_bias = torch.zeros(bsz, 1, 1, n_obj + 2).masked_fill(~key_ok[:, None, None, :], -torch.inf)
        query_out = x[:, 1]  # (B, D): the target-query token, all the head reads
        if self.fusion:
            for block in self.fusion[:-1]:
                x = _block(block, x, fusion_bias)
            query_out = _block_for_token(self.fusion[-1], x, fusion_bias, token=1)
        pooled = F.layer_norm(query_out, (dim,), model.ln_f.weight, model.ln_f.bias, model.ln_f.eps)

        cond = region_condition(shift, scale, floor_z, packed.scene_low, packed.scene_high)  # (B, C)
        film = F.gelu(F.linear(cond, self.film_in.weight, self.film_in.bias))
        film = F.linear(film, self.film_out.weight, self.film_out.bias)
        film_scale, film_shift = film.chunk(2, dim=-1)  # (B, D) each
        out = pooled * (1.0 + film_scale) + film_shift
        for layer in self.head[:-1]:  # GELU after each hidden layer (dropout is off in eval mode)
            out = F.gelu(F.linear(out, layer.weight, layer.bias))
        out = F.linear(out, self.head[-1].weight, self.head[-1].bias)  # (B, O)
        if model.relation_prior is not None:
            prior = F.linear(cond, model.relation_prior.weight, model.relation_prior.bias)
            out = out + prior.view(bsz, cfg.n_relations, cfg.n_outputs)[torch.arange(bsz), packed.relation]
        box = AnchorBox(packed.relation, packed.anchor_low, packed.anchor_high, packed.plain_top)
        return decode_head(out, shift, scale, cfg, box)

    def _spatial_bias(
        self,
        centers: torch.Tensor,
        sizes: torch.Tensor,
        shift: torch.Tensor,
        scale: torch.Tensor,
        text: torch.Tensor,
        mask: torch.Tensor | None,
    ) -> torch.Tensor:
        """The spatial layers' attention bias (B, H, 1 + N, 1 + N): the text-conditioned pair MLP for object
        pairs, zero for the query's row and column, -inf for padded keys (mask given when any)."""
        model = self.model
        bsz, n_obj, _ = centers.shape
        n_hidden = self.pair_dist_weight.shape[0]
        s = scale[:, None, :]  # (B, 1, 3)
        to_anchor = torch.linalg.vector_norm(centers - shift[:, None, :], dim=-1)  # (B, N)
        per_object = torch.cat([centers / s, 0.5 * sizes / s, to_anchor[..., None]], dim=-1)  # (B, N, 7)
        # Channel-first (B, P, N, N): the broadcast sums and the contraction to H heads run fastest so.
        terms = torch.matmul(self.pair_terms_weight, per_object.transpose(1, 2)) + self.pair_terms_bias
        row, col = terms.split(n_hidden, dim=1)  # (B, P, N) each
        dist = torch.linalg.vector_norm(centers[:, None, :, :] - centers[:, :, None, :], dim=-1)  # (B, N, N)
        # pair_out(h * (1 + gamma) + beta) with the FiLM folded into per-sample output weights (as the model).
        gamma, beta = F.linear(text, model.pair_film.weight, model.pair_film.bias).chunk(2, dim=-1)  # (B, P)
        w_out = model.pair_out.weight[None] * (1.0 + gamma[:, None, :])  # (B, H, P)
        b_out = beta @ model.pair_out.weight.t() + model.pair_out.bias  # (B, H)
        hidden = row[:, :, :, None] + col[:, :, None, :]  # (B, P, N, N)
        hidden.addcmul_(dist[:, None, :, :], self.pair_dist_weight)
        hidden = F.gelu(hidden).view(bsz, n_hidden, n_obj * n_obj)
        pair_bias = torch.baddbmm(b_out[:, :, None], w_out, hidden)  # (B, H, N*N)
        pair_bias = pair_bias.view(bsz, -1, n_obj, n_obj)
        bias = F.pad(pair_bias, (1, 0, 1, 0))  # (B, H, 1 + N, 1 + N)
        if mask is not None:
            key_ok = torch.cat([mask.new_ones(bsz, 1), mask], dim=1)  # (B, 1 + N)
            bias = bias.masked_fill(~key_ok[:, None, None, :], -torch.inf)
        return bias


def _block_for_token(
    block: Block, x: torch.Tensor, attn_bias: torch.Tensor | None, token: int
) -> torch.Tensor:
    """`Block.forward(x)[:, token]` (B, D): every token's keys and values, but one query, one projection and
    one FFN row; the model only reads the target-query token after the last block."""
    bsz, seq, dim = x.shape
    heads = block.n_heads
    h = F.layer_norm(x, (dim,), block.ln1.weight, block.ln1.bias, block.ln1.eps)  # (B, T, D)
    w, b = block.qkv.weight, block.qkv.bias  # (3D, D), (3D,): rows q, k, v
    q = F.linear(h[:, token], w[:dim], b[:dim]).view(bsz, heads, 1, dim // heads)  # (B, H, 1, d)
    kv = F.linear(h, w[dim:], b[dim:])  # (B, T, 2D)
    k, v = kv.view(bsz, seq, 2, heads, dim // heads).permute(2, 0, 3, 1, 4)  # (B, H, T, d) each
    if attn_bias is not None and attn_bias.shape[-2] > 1:
        attn_bias = attn_bias[..., token : token + 1, :]
    y = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_bias).view(bsz, dim)  # (B, D)
    out = torch.addmm(x[:, token] + block.proj.bias, y, block.proj.weight.t())  # (B, D)
    h = F.layer_norm(out, (dim,), block.ln2.weight, block.ln2.bias, block.ln2.eps)
    h = F.gelu(F.linear(h, block.fc.weight, block.fc.bias))  # (B, F)
    return torch.addmm(out + block.fc_out.bias, h, block.fc_out.weight.t())


def _linears(stack: nn.Sequential) -> list[nn.Linear]:
    """The linear layers of an MLP stack, in order (its GELUs are applied between them, dropout is off)."""
    layers = [m for m in stack if isinstance(m, nn.Linear)]
    others = {type(m).__name__ for m in stack if not isinstance(m, nn.Linear | nn.GELU | nn.Dropout)}
    if others:
        msg = f"LSMInference expects Linear/GELU/Dropout stacks, found {sorted(others)}"
        raise TypeError(msg)
    return layers


def _as_block(module: nn.Module) -> Block:
    if not isinstance(module, Block):
        msg = f"LSMInference expects transformer Blocks, found {type(module).__name__}"
        raise TypeError(msg)
    return module


def _block(block: Block, x: torch.Tensor, attn_bias: torch.Tensor | None) -> torch.Tensor:
    """`Block.forward` in eval mode, through the functional API (no module calls)."""
    bsz, seq, dim = x.shape
    heads = block.n_heads
    h = F.layer_norm(x, (dim,), block.ln1.weight, block.ln1.bias, block.ln1.eps)
    qkv = F.linear(h, block.qkv.weight, block.qkv.bias)  # (B, T, 3D)
    q, k, v = qkv.view(bsz, seq, 3, heads, dim // heads).permute(2, 0, 3, 1, 4)  # (B, H, T, d) each
    y = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_bias)  # (B, H, T, d)
    y = y.transpose(1, 2).reshape(bsz * seq, dim)
    x = torch.addmm(x.reshape(bsz * seq, dim) + block.proj.bias, y, block.proj.weight.t())  # (B*T, D)
    h = F.layer_norm(x, (dim,), block.ln2.weight, block.ln2.bias, block.ln2.eps)
    h = F.gelu(F.linear(h, block.fc.weight, block.fc.bias))  # (B*T, F)
    x = torch.addmm(x + block.fc_out.bias, h, block.fc_out.weight.t())
    return x.view(bsz, seq, dim)
