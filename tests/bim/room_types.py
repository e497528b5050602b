"""Scoring the prior's room typing against architects' room names (IfcSpace LongName) by regular expressions
(`room_names_eval.yaml`), and its rooms against IfcSpace: evaluation only, never read by the prior itself."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import yaml

from bimfactor.bim.prior import BimPrior, classify_prior_rooms
from bimfactor.config import Config
from bimfactor.embed.text import TextEmbedder
from bimfactor.errors import ConfigError

ROOM_NAMES_EVAL_FILE = Path(__file__).with_name("room_names_eval.yaml")


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
    """Read the table of architects' room names (default `room_names_eval.yaml` beside this file)."""
    return _load_room_name_table(Path(path or ROOM_NAMES_EVAL_FILE).resolve())


@cache
def _load_room_name_table(path: Path) -> RoomNameTable:
    data = yaml.safe_load(path.read_text())
    categories = data.get("categories") if isinstance(data, dict) else None
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


@dataclass
class RoomTypeRow:
    room_id: int
    space_name: str
    expected: str
    predicted: str
    sentence: str

    @property
    def correct(self) -> bool:
        return self.expected == self.predicted


@dataclass
class RoomTypeAccuracy:
    """Language-encoded room types against the architects' names, on rooms with enough labelled objects."""

    rows: list[RoomTypeRow] = field(default_factory=list)

    @property
    def evaluated(self) -> int:
        return len(self.rows)

    @property
    def correct(self) -> int:
        return sum(r.correct for r in self.rows)

    @property
    def accuracy(self) -> float:
        return self.correct / self.evaluated if self.rows else float("nan")


def room_type_accuracy(
    prior: BimPrior,
    ignore_labels: tuple[str, ...] = ("door", "window"),
    min_objects: int = 2,
    table: RoomNameTable | None = None,
    types: Sequence[tuple[str, str]] | None = None,
) -> RoomTypeAccuracy:
    """Score rooms that carry an architect's name the evaluation table knows and ≥ `min_objects` labels.

    `types`: (category, sentence) per room to score instead of the prior's own (e.g. typed without names).
    """
    table = table or load_room_name_table()
    types = types or [(room.category, room.sentence) for room in prior.rooms]
    result = RoomTypeAccuracy()
    for room, (category, sentence) in zip(prior.rooms, types, strict=True):
        expected = table.category(room.space_name) if room.space_name else None
        labelled = [i for i in room.object_ids if prior.objects[i].label not in ignore_labels]
        if expected is None or len(labelled) < min_objects:
            continue
        result.rows.append(RoomTypeRow(room.id, room.space_name, expected, category, sentence))
    return result


def object_only_types(prior: BimPrior, cfg: Config, embedder: TextEmbedder) -> list[tuple[str, str]]:
    """Each room's (category, sentence) typed from its objects and doors alone, as the paper does."""
    rooms = classify_prior_rooms(prior.rooms, prior.objects, prior.doors, cfg, embedder, use_names=False)
    return [(r.category, r.sentence) for r in rooms]


def ifcspace_matched_share(prior: BimPrior) -> float:
    """Share of IfcSpace rooms (> 2 m²) matched by a flood-fill room at the configured IoU, all storeys."""
    pairs = [(iou, m.threshold) for m in prior.room_matches for iou in m.ious]
    return sum(iou >= t for iou, t in pairs) / len(pairs) if pairs else float("nan")
