"""The perception stages as small protocols: detect ▸ segment ▸ embed, with interchangeable backends.

A backend implements one stage for one image source: `sim` reads the simulator's instance buffer, `vlm` runs
YOLO-World, SAM and CLIP on the colour image. Every stage takes the whole `Frame`, so a backend can use what
it needs (colour, depth, or the simulator's ground truth) without the caller knowing which.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from bimfactor.types import Frame


@dataclass(frozen=True)
class Detection:
    """One open-vocabulary 2D detection.

    `box_xyxy` (4,) float pixels (x0, y0, x1, y1), x1/y1 exclusive; `box_score` the objectness score and
    `text_score` the region-to-label score. `gt_instance_id` is simulation ground truth for evaluation only
    (the instance it came from, -1 for a false positive); real backends leave it None.
    """

    box_xyxy: np.ndarray
    label: str
    box_score: float
    text_score: float
    gt_instance_id: int | None = None


@runtime_checkable
class Detector(Protocol):
    """Image → 2D region proposals with labels from an open vocabulary, thresholds already applied."""

    def detect(self, frame: Frame) -> list[Detection]:
        """The detections of one frame whose box and text scores pass the thresholds."""
        ...


@runtime_checkable
class Segmenter(Protocol):
    """Box prompts → one binary mask per box."""

    def segment(self, frame: Frame, detections: Sequence[Detection]) -> np.ndarray:
        """(N, H, W) bool masks, one per detection."""
        ...


@runtime_checkable
class Embedder(Protocol):
    """Visual embedder: one unit vector per detected region, in the same space as the BIM text embeddings."""

    name: str
    dim: int

    def embed(self, frame: Frame, detections: Sequence[Detection], masks: np.ndarray) -> np.ndarray:
        """(N, D) float32 unit rows, one per detection (crop of its box; `masks` (N, H, W) may guide it)."""
        ...


@dataclass(frozen=True)
class TextReading:
    """One piece of text read in a colour image, e.g. a door plate's room number.

    `text` as read (not normalised), `box_xyxy` (4,) float pixels (x0, y0, x1, y1), x1/y1 exclusive, `score`
    the reader's confidence in [0, 1]. `gt_instance_id` is simulation ground truth (the plate it came from).
    """

    text: str
    box_xyxy: np.ndarray
    score: float
    gt_instance_id: int | None = None


@runtime_checkable
class TextReader(Protocol):
    """Image → the text it shows, with where (a scene-text reader: OCR). `wants_columns`: whether it reads less when
    told where plates can be (then the localizer forecasts the columns from its belief)."""

    wants_columns: bool

    def read(self, frame: Frame, columns: np.ndarray | None = None) -> list[TextReading]:
        """The readings of one frame whose score passes the reader's threshold; `columns` (W,) bool, where given, are
        the image columns a plate can be in (the belief's forecast): a reader may read only there."""
        ...


def passes_thresholds(detection: Detection, box_threshold: float, text_threshold: float) -> bool:
    """δ_box and δ_text of the paper: a detection is kept only when both scores reach their threshold."""
    return detection.box_score >= box_threshold and detection.text_score >= text_threshold


def box_to_pixels(box_xyxy: np.ndarray, width: int, height: int) -> tuple[int, int, int, int]:
    """Integer pixel bounds (x0, y0, x1, y1) of a box, clipped to the image, x1/y1 exclusive."""
    x0, y0, x1, y1 = np.asarray(box_xyxy, float)
    ix0, iy0 = int(np.clip(np.floor(x0), 0, width)), int(np.clip(np.floor(y0), 0, height))
    ix1, iy1 = int(np.clip(np.ceil(x1), 0, width)), int(np.clip(np.ceil(y1), 0, height))
    return ix0, iy0, max(ix1, ix0), max(iy1, iy0)


def empty_masks(frame: Frame) -> np.ndarray:
    """(0, H, W) bool: the masks of no detection."""
    return np.zeros((0, *frame.depth_m.shape), bool)
