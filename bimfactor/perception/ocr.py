"""A real scene-text reader for door plates: RapidOCR (PP-OCRv4 detection + recognition on ONNX Runtime).

`RapidOcrReader` implements the `TextReader` protocol: it finds text in a frame's colour image and reads it,
e.g. the room numbers "101" or "A204" on door plates. The PP-OCRv4 ONNX models ship inside the
`rapidocr-onnxruntime` wheel, so it runs offline with no weight files to provide and nothing downloaded.
The library is imported inside the constructor; a missing one is a DependencyError with the install hint.
`from_engine` wraps an already built engine, so tests can inject a fake one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from bimfactor import errors
from bimfactor.perception.base import TextReading
from bimfactor.types import Frame

INSTALL_HINT = "bash tools/setup.sh, or pip install 'bimfactor[ocr]' && pip install --no-deps rapidocr-onnxruntime"


def quad_to_box(quad: Sequence[Sequence[float]], width: int, height: int) -> np.ndarray:
    """(4,) float (x0, y0, x1, y1): the axis-aligned hull of a quadrilateral's corners, clipped to the image."""
    points = np.asarray(quad, float).reshape(-1, 2)
    x0, y0 = points.min(axis=0)
    x1, y1 = points.max(axis=0)
    return np.array(
        [np.clip(x0, 0, width), np.clip(y0, 0, height), np.clip(x1, 0, width), np.clip(y1, 0, height)], float
    )


class RapidOcrReader:
    """RapidOCR on a frame's colour image; keeps readings with score ≥ `min_score` and non-blank text.

    The engine is called like RapidOCR's: `engine(bgr_image) -> (result, elapse)`, `result` None (no text)
    or a list of `[quad (4 corner points), text, score]`.
    """

    def __init__(self, min_score: float = 0.5, engine: Any | None = None) -> None:
        if engine is None:
            rapidocr = errors.import_optional("rapidocr_onnxruntime", "The RapidOCR text reader", INSTALL_HINT)
            # RapidOCR drops readings below its own text_score (0.5 by default) before returning; set it to ours.
            engine = rapidocr.RapidOCR(text_score=min_score)
        self.engine = engine
        self.min_score = float(min_score)

    @classmethod
    def from_engine(cls, engine: Any, min_score: float = 0.5) -> RapidOcrReader:
        """Wrap an already built engine (a `rapidocr_onnxruntime.RapidOCR`, or anything called like one)."""
        return cls(min_score, engine)

    def read(self, frame: Frame) -> list[TextReading]:
        """The text in the frame's colour image, each with its axis-aligned box, filtered by `min_score`."""
        height, width = frame.rgb.shape[:2]
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])  # RapidOCR takes a 3-channel numpy image as OpenCV BGR
        result, _elapse = self.engine(bgr)
        readings = []
        for quad, text, score, *_ in result or []:
            text = str(text).strip()
            if text and float(score) >= self.min_score:
                readings.append(TextReading(text, quad_to_box(quad, width, height), float(score)))
        return readings
