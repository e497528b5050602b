"""Language-encoded room classification (CoarseBIMLoc, Sec. II.A).

The object labels inside a room are joined into one sentence ("sink, toilet, bathtub"), encoded with a
sentence encoder, and matched by cosine similarity against a pool of room-category embeddings; the best
match is the room's type. The pool lives in `bimfactor/configs/room_categories.yaml`.

`bimfactor/configs/room_names_eval.yaml` maps architects' room names to the same categories. It is for evaluation
only (scoring the classifier on real IFC models); the classifier never reads room names.
"""

from __future__ import annotations

import itertools
import logging
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from bimfactor.config import ClassifyConfig, config_file
from bimfactor.embed.text import TextEmbedder
from bimfactor.errors import ConfigError

logger = logging.getLogger(__name__)

UNKNOWN = "unknown"
ROOM_NAMES_EVAL_FILE = "room_names_eval.yaml"

SentenceStyle = Literal["counted", "unique", "list"]
_PREPOSITION = re.compile(r" (with|of|for|on|in|w) ")
_NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


def _read_yaml_mapping(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"table not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc.__class__.__name__})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    return data


# --- the sentence ----------------------------------------------------------------------------------------


def _plural_word(word: str) -> str:
    if re.search(r"(s|x|z|ch|sh)$", word):
        return word + "es"
    if re.search(r"[^aeiou]y$", word):
        return word[:-1] + "ies"
    if word.endswith("fe"):
        return word[:-2] + "ves"
    if word.endswith("f") and word not in {"roof", "chief", "proof"}:
        return word[:-1] + "ves"
    return word + "s"


def _plural(label: str) -> str:
    """Plural of the head noun: "office chair" → "office chairs", "unit with sink" → "units with sink"."""
    match = _PREPOSITION.search(label)
    head, tail = (label[: match.start()], label[match.start() :]) if match else (label, "")
    before, space, last = head.rpartition(" ")
    return before + space + _plural_word(last) + tail


def _count_phrase(label: str, count: int) -> str:
    if count == 1:
        return label
    number = _NUMBER_WORDS[count] if count < len(_NUMBER_WORDS) else str(count)
    return f"{number} {_plural(label)}"


def room_sentence(labels: Sequence[str], style: SentenceStyle = "counted") -> str:
    """Join a room's object labels into the sentence that is encoded.

    "counted": each distinct label once, with its count ("toilet, two sinks"); "unique": each distinct
    label once; "list": every label as given. Labels keep their first-seen order in all styles.
    """
    cleaned = [" ".join(label.lower().split()) for label in labels]
    cleaned = [label for label in cleaned if label]
    if style == "list":
        return ", ".join(cleaned)
    counts = Counter(cleaned)
    distinct = list(dict.fromkeys(cleaned))
    if style == "unique":
        return ", ".join(distinct)
    if style == "counted":
        return ", ".join(_count_phrase(label, counts[label]) for label in distinct)
    raise ValueError(f"unknown sentence style {style!r}")


# --- the category pool -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RoomCategoryPool:
    """Room categories and their embeddings: `embeddings[i]` (D,) is the unit mean of `names[i]`'s prompts."""

    names: tuple[str, ...]
    prompts: tuple[tuple[str, ...], ...]
    embeddings: np.ndarray
    embedder: TextEmbedder = field(repr=False)
    min_score: float = 0.0

    @classmethod
    def load(cls, path: str | Path, embedder: TextEmbedder) -> RoomCategoryPool:
        """Read the pool file (format: the header of `bimfactor/configs/room_categories.yaml`) and embed its prompts."""
        path = Path(path)
        data = _read_yaml_mapping(path)
        categories = data.get("categories")
        if not isinstance(categories, dict) or not categories:
            raise ConfigError(f"{path}: 'categories' must be a non-empty mapping of name → prompt list")
        names: list[str] = []
        prompts: list[tuple[str, ...]] = []
        for name, sentences in categories.items():
            if not isinstance(name, str) or name == UNKNOWN:
                raise ConfigError(f"{path}: category name {name!r} is not allowed")
            if isinstance(sentences, str):
                sentences = [sentences]
            if not isinstance(sentences, list) or not sentences or not all(isinstance(s, str) for s in sentences):
                raise ConfigError(f"{path}: category '{name}' needs a non-empty list of prompt sentences")
            names.append(name)
            prompts.append(tuple(sentences))
        min_score = data.get("min_score", 0.0)
        if not isinstance(min_score, int | float) or not -1.0 <= min_score <= 1.0:
            raise ConfigError(f"{path}: 'min_score' must be a number in [-1, 1]")

        # One batch for every prompt, then one normalised mean per category.
        flat = [sentence for group in prompts for sentence in group]
        vectors = embedder.encode(flat)
        bounds = np.cumsum([0, *(len(group) for group in prompts)])
        means = np.stack([vectors[a:b].mean(axis=0) for a, b in itertools.pairwise(bounds)])
        means /= np.linalg.norm(means, axis=1, keepdims=True)
        logger.debug("room-category pool %s: %d categories, %d prompts", path.name, len(names), len(flat))
        return cls(tuple(names), tuple(prompts), means.astype(np.float32), embedder, float(min_score))


def load_room_category_pool(cfg: ClassifyConfig, embedder: TextEmbedder) -> RoomCategoryPool:
    """The pool that `bim.classify.room_categories_file` names (relative to bimfactor/configs/)."""
    return RoomCategoryPool.load(config_file(cfg.room_categories_file), embedder)


# --- classification --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RoomClassification:
    """A room's best category, its cosine score, the encoded sentence and the score of every category.

    `scores` is empty when the room had too few objects to be encoded.
    """

    category: str
    score: float
    sentence: str
    scores: dict[str, float]


def classify_rooms(
    rooms_labels: Sequence[Sequence[str]],
    pool: RoomCategoryPool,
    *,
    min_objects: int = 1,
    style: SentenceStyle = "counted",
) -> list[RoomClassification]:
    """Classify many rooms from their object labels, encoding all sentences in one batch.

    A room with fewer than `min_objects` labels, or whose best score is below the pool's `min_score`,
    is typed "unknown" (score 0 for the former).
    """
    sentences = [room_sentence(labels, style) for labels in rooms_labels]
    counts = [sum(1 for label in labels if label.strip()) for labels in rooms_labels]
    known = [i for i, count in enumerate(counts) if count >= max(min_objects, 1)]
    results = [RoomClassification(UNKNOWN, 0.0, sentences[i], {}) for i in range(len(sentences))]
    if not known:
        return results
    similarity = pool.embedder.encode([sentences[i] for i in known]) @ pool.embeddings.T  # (K, C)
    for row, i in zip(similarity, known, strict=True):
        best = int(np.argmax(row))
        scores = {name: float(s) for name, s in zip(pool.names, row, strict=True)}
        category = pool.names[best] if row[best] >= pool.min_score else UNKNOWN
        results[i] = RoomClassification(category, float(row[best]), sentences[i], scores)
    return results


def classify_room(
    labels: Sequence[str],
    pool: RoomCategoryPool,
    *,
    min_objects: int = 1,
    style: SentenceStyle = "counted",
) -> RoomClassification:
    """Classify one room from its object labels (see `classify_rooms`)."""
    return classify_rooms([labels], pool, min_objects=min_objects, style=style)[0]


# --- evaluation-only room-name table ---------------------------------------------------------------------


@dataclass(frozen=True)
class RoomNameTable:
    """Ordered (pattern, category) rules; the first pattern found in a room name gives its category."""

    rules: tuple[tuple[re.Pattern[str], str], ...]

    def category(self, name: str) -> str | None:
        """The category of an architect's room name, or None when no rule matches."""
        for pattern, category in self.rules:
            if pattern.search(name):
                return category
        return None

    @property
    def categories(self) -> set[str]:
        return {category for _, category in self.rules}


def load_room_name_table(path: str | Path | None = None) -> RoomNameTable:
    """Read the evaluation table of room names (default `bimfactor/configs/room_names_eval.yaml`)."""
    path = Path(path) if path is not None else config_file(ROOM_NAMES_EVAL_FILE)
    return _load_room_name_table(path.resolve())


@cache
def _load_room_name_table(path: Path) -> RoomNameTable:
    data = _read_yaml_mapping(path)
    categories = data.get("categories")
    if not isinstance(categories, dict):
        raise ConfigError(f"{path}: 'categories' must be a mapping of category → list of name patterns")
    rules: list[tuple[re.Pattern[str], str]] = []
    for category, patterns in categories.items():
        if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
            raise ConfigError(f"{path}: category '{category}' needs a list of pattern strings")
        for pattern in patterns:
            try:
                rules.append((re.compile(pattern, re.IGNORECASE), str(category)))
            except re.error as exc:
                raise ConfigError(f"{path}: bad pattern {pattern!r} for '{category}': {exc}") from exc
    return RoomNameTable(tuple(rules))


def room_name_to_category(name: str, table: RoomNameTable | None = None) -> str | None:
    """Evaluation only: the category an architect's room name (IfcSpace LongName) stands for, or None."""
    return (table or load_room_name_table()).category(name)
