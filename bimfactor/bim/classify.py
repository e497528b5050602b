"""Language-encoded room classification (CoarseBIMLoc, Sec. II.A).

A room's object labels, joined into one sentence, are encoded and matched by cosine against the room-category pool
(`bimfactor/configs/room_categories.yaml`). A room with an architect's name (IfcSpace LongName or Name) is typed by
that name first when its best category scores `name_min_score` and leads the next by `name_margin`; a generic or
unknown name falls back to the objects.
"""

from __future__ import annotations

import itertools
import logging
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from bimfactor.bim.vocabulary import normalise
from bimfactor.config import ClassifyConfig, config_file
from bimfactor.embed.text import TextEmbedder
from bimfactor.errors import ConfigError

logger = logging.getLogger(__name__)

UNKNOWN = "unknown"

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
    room_names: tuple[tuple[str, ...], ...] = ()  # per category: the names a room of it is given
    room_name_embeddings: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32), repr=False)
    room_name_category: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    name_min_score: float = 1.0
    name_margin: float = 0.0

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
        min_score, name_min_score, name_margin = (
            _unit_number(path, data, key, default) for key, default in (("min_score", 0.0), ("name_min_score", 1.0),
                                                                        ("name_margin", 0.0))
        )  # fmt: skip
        room_names = _room_names(path, data.get("names", {}), names)

        # One batch for every prompt, then one normalised mean per category.
        flat = [sentence for group in prompts for sentence in group]
        vectors = embedder.encode(flat)
        bounds = np.cumsum([0, *(len(group) for group in prompts)])
        means = np.stack([vectors[a:b].mean(axis=0) for a, b in itertools.pairwise(bounds)])
        means /= np.linalg.norm(means, axis=1, keepdims=True)
        flat_names = [normalise(name) for group in room_names for name in group]
        logger.debug("room-category pool %s: %d categories, %d prompts, %d names", path.name, len(names), len(flat),
                     len(flat_names))  # fmt: skip
        return cls(
            tuple(names),
            tuple(prompts),
            means.astype(np.float32),
            embedder,
            min_score,
            room_names,
            embedder.encode(flat_names).astype(np.float32),
            np.repeat(np.arange(len(names)), [len(group) for group in room_names]),
            name_min_score,
            name_margin,
        )


def _unit_number(path: Path, data: dict[str, Any], key: str, default: float) -> float:
    value = data.get(key, default)
    if not isinstance(value, int | float) or not -1.0 <= value <= 1.0:
        raise ConfigError(f"{path}: '{key}' must be a number in [-1, 1]")
    return float(value)


def _room_names(path: Path, table: Any, categories: Sequence[str]) -> tuple[tuple[str, ...], ...]:
    """Per category, its own name and the names the pool file lists for it."""
    if not isinstance(table, dict) or not all(isinstance(v, list) for v in table.values()):
        raise ConfigError(f"{path}: 'names' must be a mapping of category → list of room names")
    unknown = sorted(set(table) - set(categories))
    if unknown:
        raise ConfigError(f"{path}: 'names' lists categories that are not in 'categories': {', '.join(unknown)}")
    return tuple(tuple(dict.fromkeys([category, *map(str, table.get(category, []))])) for category in categories)


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


_ROMAN = re.compile(r"^[ivx]+$")
WORD_MIN_SCORE = 0.9  # a single word of a name decides only when it is one of the pool's names, near enough


def _name_texts(name: str) -> tuple[str, list[str]]:
    """The texts a room name is matched by: the whole name without numbers, and each word of two letters or more
    that is not a roman numeral ("WC Herren III" → "wc herren iii"; "wc", "herren")."""
    words = [w for w in re.sub(r"\d+", " ", normalise(name)).split() if w.isalpha()]
    return " ".join(words), [w for w in dict.fromkeys(words) if len(w) >= 2 and not _ROMAN.match(w)]


def classify_room_names(names: Sequence[str], pool: RoomCategoryPool) -> list[RoomClassification | None]:
    """Type rooms by their architects' names (module docstring); None where a name does not decide. A single word
    counts only where it is nearly one of the pool's names (`WORD_MIN_SCORE`): "Kitchen Storage" is not typed by
    "storage" alone, nor "Umkleide Herren" by a loose likeness of "herren"."""
    texts = [[whole, *words] if whole else [] for whole, words in map(_name_texts, names)]
    flat = [t for group in texts for t in group]
    results: list[RoomClassification | None] = [None] * len(names)
    if not flat:
        return results
    similarity = pool.embedder.encode(flat) @ pool.room_name_embeddings.T  # (texts, pool names)
    per_category = np.full((len(flat), len(pool.names)), -1.0)
    np.maximum.at(per_category.T, pool.room_name_category, similarity.T)
    start = 0
    for i, group in enumerate(texts):
        if not group:
            continue
        block = per_category[start : start + len(group)]
        start += len(group)
        words = block[1:]
        scores = np.maximum(block[0], np.where(words >= WORD_MIN_SCORE, words, -1.0).max(axis=0, initial=-1.0))
        order = np.argsort(-scores)
        best, second = float(scores[order[0]]), float(scores[order[1]]) if len(order) > 1 else -1.0
        if best >= pool.name_min_score and best - second >= pool.name_margin:
            all_scores = dict(zip(pool.names, map(float, scores), strict=True))
            results[i] = RoomClassification(pool.names[order[0]], best, f'(name: "{names[i]}")', all_scores)
    return results


def type_rooms(
    room_labels: Sequence[Sequence[str]],
    room_names: Sequence[str],
    room_neighbours: Sequence[int],
    pool: RoomCategoryPool,
    cfg: ClassifyConfig,
    *,
    use_names: bool = True,
) -> list[RoomClassification]:
    """Every room's type: by its name where the name decides, else by its objects (the paper), and an object-less
    room that joins `cfg.hallway_min_doors` or more places is a hallway. `room_labels` leave out ignored labels."""
    results = classify_rooms(room_labels, pool, min_objects=cfg.min_objects)
    if cfg.hallway_min_doors > 0:
        for i, (labels, neighbours) in enumerate(zip(room_labels, room_neighbours, strict=True)):
            if not labels and neighbours >= cfg.hallway_min_doors:
                results[i] = RoomClassification("hallway", 0.0, f"(topology: joins {neighbours} places)", {})
    if use_names:
        for i, by_name in enumerate(classify_room_names(room_names, pool)):
            if by_name is not None:
                results[i] = by_name
    return results
