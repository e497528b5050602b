"""Open-vocabulary labels for BIM objects, from the texts an IFC element carries.

The rule table lives in `bimfactor/configs/vocabulary.yaml` (English and German names, IFC predefined types).
Resolution order: rules on name / type name / object type / predefined type, then the label shared by
the element's type siblings, then a specific label its IFC class or type class gives (a radiator, stairs), then
the nearest vocabulary label by text embedding, then a generic class label (furniture, fixture).
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Protocol

import numpy as np
import yaml

from bimfactor.bim.ifc import IfcElement
from bimfactor.errors import ConfigError

_UMLAUTS = str.maketrans({"ä": "ae", "ö": "oe", "ü": "ue", "ß": "ss", "Ä": "ae", "Ö": "oe", "Ü": "ue"})
_SEPARATORS = re.compile(r"[_\-:/.,;()\[\]]+")


class LabelSource(StrEnum):
    """How a label was found, most trustworthy first."""

    RULE = "rule"
    TYPE_SIBLINGS = "type_siblings"
    EMBEDDING = "embedding"
    IFC_CLASS = "ifc_class"


@dataclass(frozen=True)
class ObjectLabel:
    label: str
    source: LabelSource
    raw_text: str


class Embedder(Protocol):
    def encode(self, texts: Sequence[str]) -> np.ndarray: ...


def normalise(text: str) -> str:
    """Lower case, umlauts spelt out, separators as spaces, single-spaced."""
    return " ".join(_SEPARATORS.sub(" ", text.translate(_UMLAUTS).lower()).split())


@dataclass(frozen=True)
class Vocabulary:
    rules: tuple[tuple[re.Pattern[str], str], ...]
    class_labels: tuple[tuple[str, str], ...]

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        data = yaml.safe_load(Path(path).read_text())
        try:
            rules = tuple((re.compile(r["pattern"]), str(r["label"])) for r in data["rules"])
            class_labels = tuple((str(k), str(v)) for k, v in data["class_labels"].items())
        except (KeyError, TypeError, re.error) as exc:
            raise ConfigError(f"{path}: malformed vocabulary ({exc})") from exc
        return cls(rules, class_labels)

    @property
    def labels(self) -> list[str]:
        """Every label a rule can give, in table order, without repeats."""
        return list(dict.fromkeys(label for _, label in self.rules))

    def match_text(self, text: str) -> str | None:
        norm = normalise(text)
        if not norm:
            return None
        for pattern, label in self.rules:
            if pattern.search(norm):
                return label
        return None

    def match_element(self, element: IfcElement) -> str | None:
        for text in (element.name, element.type_name, element.object_type, element.predefined_type):
            label = self.match_text(text)
            if label is not None:
                return label
        return None

    def class_label(self, element: IfcElement) -> str:
        """The label of the most specific listed class among the element's type class and its ancestry."""
        for ifc_class in (element.type_class, *element.ancestry):
            for listed, label in self.class_labels:
                if listed == ifc_class:
                    return label
        return element.ifc_class.removeprefix("Ifc").lower()

    def specific_class_label(self, element: IfcElement) -> str | None:
        """The class label when a rule can give it too (radiator, stairs), not a generic one (furniture)."""
        label = self.class_label(element)
        return label if label in self.labels else None


def label_elements(
    elements: Sequence[IfcElement],
    vocabulary: Vocabulary,
    embedder: Embedder | None = None,
    min_similarity: float = 0.45,
) -> list[ObjectLabel]:
    """One label per element, in the same order, by the resolution order in the module docstring."""
    labels: list[ObjectLabel | None] = [
        ObjectLabel(lbl, LabelSource.RULE, el.raw_text) if (lbl := vocabulary.match_element(el)) else None
        for el in elements
    ]
    # Type siblings: unnamed instances of a type whose other instances the rules did name.
    by_type: dict[tuple[str, str], Counter[str]] = defaultdict(Counter)
    for el, lab in zip(elements, labels, strict=True):
        if lab is not None and el.type_name:
            by_type[(el.type_class, el.type_name)][lab.label] += 1
    for i, el in enumerate(elements):
        votes = by_type.get((el.type_class, el.type_name)) if el.type_name else None
        if labels[i] is None and votes:
            labels[i] = ObjectLabel(votes.most_common(1)[0][0], LabelSource.TYPE_SIBLINGS, el.raw_text)
    # A class that names what the element is (IfcSpaceHeater, IfcStair) outranks a guess from free text.
    for i, el in enumerate(elements):
        if labels[i] is None and (label := vocabulary.specific_class_label(el)) is not None:
            labels[i] = ObjectLabel(label, LabelSource.IFC_CLASS, el.raw_text)
    # Nearest label by embedding, for texts the rules do not know.
    pending = [i for i, lab in enumerate(labels) if lab is None and normalise(elements[i].raw_text)]
    if embedder is not None and pending:
        vocab_labels = vocabulary.labels
        texts = [normalise(elements[i].raw_text) for i in pending]
        sims = embedder.encode(texts) @ embedder.encode(vocab_labels).T
        for row, i in enumerate(pending):
            best = int(np.argmax(sims[row]))
            if sims[row, best] >= min_similarity:
                labels[i] = ObjectLabel(vocab_labels[best], LabelSource.EMBEDDING, elements[i].raw_text)
    return [
        lab if lab is not None else ObjectLabel(vocabulary.class_label(el), LabelSource.IFC_CLASS, el.raw_text)
        for el, lab in zip(elements, labels, strict=True)
    ]
