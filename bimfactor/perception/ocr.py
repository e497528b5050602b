"""A real scene-text reader for door plates: RapidOCR (PP-OCRv4 detection + recognition on ONNX Runtime).

`RapidOcrReader` implements the `TextReader` protocol with the models the `rapidocr-onnxruntime` wheel ships (offline;
a missing library is a DependencyError with the install hint; `from_engine` wraps a built engine, for tests).
`PlateReader` reads only where a door plate can be: `plate_region` boxes the surfaces at plate height
(`PLATE_HEIGHTS_M`) within `READ_RANGE_M` in the columns where the belief holds a plate (`plate_columns`), and
RapidOCR reads that box at the scale it would give the whole frame (`OCR_FOCAL_PX`). docs/perception.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from bimfactor import errors
from bimfactor.perception.base import TextReading
from bimfactor.types import CameraIntrinsics, Frame

INSTALL_HINT = "bash tools/setup.sh, or pip install 'bimfactor[ocr]' && pip install --no-deps rapidocr-onnxruntime"
PLATE_HEIGHTS_M = (1.15, 1.75)
"""Where door plates hang above the floor: accessibility codes put a room sign's text 1.22–1.52 m up (ADA), European
practice centres it at 1.2–1.6 m; the range holds both with a plate's own height."""
READ_RANGE_M = 2.8
"""Farthest a plate is read from: a 15 cm plate is 26 px high at `OCR_FOCAL_PX` there, its characters ~10 px."""
OCR_FOCAL_PX = 490.0
"""The focal length (pixels) the plate region is scaled to for text detection: RapidOCR's own scale on a whole
320 × 240 frame of a 90° camera (its shorter side to 736 px: 160 px × 3.07). A camera with a longer focal length is
not scaled down."""
PAD_PX = 8
"""The plate region is grown by this many pixels on each side (a plate's edge is at the band's edge)."""
MIN_REGION_PX = 20
"""A frame with fewer plate-surface pixels than this is not read."""
SAMPLE_PX = 2
"""The plate region is found from every this-many-th row and column of the depth (a box, padded: no finer needed)."""
STROKE_M = 0.03
"""Text strokes are at most this wide at 1 m: the top-hat and black-hat kernel that finds them (5 px at f = 160 px)."""
STROKE_CONTRAST = 40
"""A stroke differs from the plate around it by at least this many grey levels (of 255): printed, legible text."""
MIN_STROKE_PX = 20
"""A plate region with fewer stroke pixels than this holds no legible text and is not read (a few characters' worth
at the simulator's resolution; a flat or smoothly shaded wall has none)."""


def quad_to_box(quad: Sequence[Sequence[float]], width: int, height: int) -> np.ndarray:
    """(4,) float (x0, y0, x1, y1): the axis-aligned hull of a quadrilateral's corners, clipped to the image."""
    points = np.asarray(quad, float).reshape(-1, 2)
    x0, y0 = points.min(axis=0)
    x1, y1 = points.max(axis=0)
    return np.array(
        [np.clip(x0, 0, width), np.clip(y0, 0, height), np.clip(x1, 0, width), np.clip(y1, 0, height)], float
    )


def engine_readings(
    result: Any, min_score: float, width: int, height: int, offset: tuple[int, int] = (0, 0)
) -> list[TextReading]:
    """RapidOCR's `result` (None, or `[quad, text, score]` items) as readings with non-blank text and score ≥
    `min_score`, each quad shifted by the (x, y) `offset` of the image RapidOCR read into the frame's pixels."""
    readings = []
    for quad, text, score, *_ in result or []:
        text = str(text).strip()
        if text and float(score) >= min_score:
            box = quad_to_box(np.asarray(quad, float).reshape(-1, 2) + np.asarray(offset, float), width, height)
            readings.append(TextReading(text, box, float(score)))
    return readings


class RapidOcrReader:
    """RapidOCR on a frame's whole colour image; keeps readings with score ≥ `min_score` and non-blank text.

    The engine is called like RapidOCR's: `engine(bgr_image) -> (result, elapse)`, `result` None (no text)
    or a list of `[quad (4 corner points), text, score]`.
    """

    wants_columns = False

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

    def read(self, frame: Frame, columns: np.ndarray | None = None) -> list[TextReading]:
        """The text in the frame's whole colour image, each with its axis-aligned box, filtered by `min_score`
        (`columns` is not looked at: this reader reads everything)."""
        height, width = frame.rgb.shape[:2]
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])  # RapidOCR takes a 3-channel numpy image as OpenCV BGR
        result, _elapse = self.engine(bgr)
        return engine_readings(result, self.min_score, width, height)


def plate_columns(
    plate_ends: np.ndarray,
    plate_normals: np.ndarray,
    plate_storeys: np.ndarray,
    poses: np.ndarray,
    storeys: np.ndarray,
    weights: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_base_camera: np.ndarray,
    range_m: float = READ_RANGE_M,
) -> np.ndarray:
    """(W,) the belief's weight on a door plate being in each image column: Σ over the (N, 3) poses (on (N,) storeys,
    with (N,) weights) of the weight of those from which a plate can be read there.

    A plate p spans the wall segment between (P, 2, 2) `plate_ends` (where on its door's wall face it can hang),
    facing along (P, 2) `plate_normals`; it can be read from a pose on its storey, on the side it faces, within
    `range_m` of it and in front of the camera, at the columns its segment's `PLATE_HEIGHTS_M` band projects to."""
    width = intrinsics.width
    out = np.zeros(width + 1)
    poses = np.asarray(poses, float).reshape(-1, 3)
    if not len(plate_ends) or not len(poses):
        return out[:width]
    T_camera_base = np.linalg.inv(np.asarray(T_base_camera, float))
    along = np.linspace(0.0, 1.0, 5)
    points_xy = plate_ends[:, :1] + along[None, :, None] * (plate_ends[:, 1:] - plate_ends[:, :1])  # (P, 5, 2)
    for storey in np.unique(storeys):
        on = (storeys == storey) & (weights > 0)
        plates = np.flatnonzero(plate_storeys == storey)
        if not on.any() or not len(plates):
            continue
        pose, w = poses[on], weights[on]
        rel = points_xy[plates][None] - pose[:, None, None, :2]  # (N, P, 5, 2)
        c, s = np.cos(pose[:, 2])[:, None, None], np.sin(pose[:, 2])[:, None, None]
        bx, by = c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]
        facing = np.einsum("npk,pk->np", rel[:, :, 2], plate_normals[plates]) < 0  # the pose is on the side it faces
        near = np.hypot(bx, by).min(axis=2) <= range_m
        us = []
        for h in PLATE_HEIGHTS_M:
            p = np.stack([bx, by, np.full_like(bx, h), np.ones_like(bx)], axis=-1) @ T_camera_base.T
            ahead = p[..., 2] > 0.05
            u = intrinsics.fx * p[..., 0] / np.where(ahead, p[..., 2], 1.0) + intrinsics.cx
            us.append(np.where(ahead, u, np.nan))
        u = np.concatenate(us, axis=2)  # (N, P, 10)
        seen = facing & near & np.any((u >= 0) & (u < width), axis=2)
        n, k = np.nonzero(seen)
        if not len(n):
            continue
        lo = np.clip(np.floor(np.nanmin(u[n, k], axis=1)), 0, width).astype(np.int64)
        hi = np.clip(np.ceil(np.nanmax(u[n, k], axis=1)) + 1, 0, width).astype(np.int64)
        np.add.at(out, lo, w[n])
        np.add.at(out, hi, -w[n])
    return np.cumsum(out)[:width]


def plate_region(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_base_camera: np.ndarray,
    columns: np.ndarray | None = None,
) -> tuple[int, int, int, int] | None:
    """The pixel box (x0, y0, x1, y1; x1, y1 exclusive) where a door plate can be in a frame: the rows of the depth
    returns `PLATE_HEIGHTS_M` above the floor (the base frame's z) within `READ_RANGE_M` horizontally (found on a
    `SAMPLE_PX` grid), grown by `PAD_PX`, across the image or across the (W,) bool `columns` where a plate can be
    (`plate_columns`; None: any); None with fewer than `MIN_REGION_PX` such returns. The whole width, not the returns'
    own columns: a plate at the edge of reading range, or on a door's frame, is read with the wall beside it."""
    height, width = depth_m.shape
    sampled = depth_m[::SAMPLE_PX, ::SAMPLE_PX]
    with np.errstate(invalid="ignore"):
        v, u = np.nonzero((sampled > 0) & (sampled <= 2 * READ_RANGE_M))  # deeper is farther (pitch below 60°)
    z = sampled[v, u]
    v, u = v * SAMPLE_PX, u * SAMPLE_PX
    points = intrinsics.backproject(u, v, z)
    T = np.asarray(T_base_camera, float)
    base = points @ T[:3, :3].T + T[:3, 3]
    low, high = PLATE_HEIGHTS_M
    near = (base[:, 2] >= low) & (base[:, 2] <= high) & (np.hypot(base[:, 0], base[:, 1]) <= READ_RANGE_M)
    if columns is not None:
        near &= np.asarray(columns, bool)[u]
    if near.sum() * SAMPLE_PX**2 < MIN_REGION_PX:
        return None
    v = v[near]
    x0, x1 = 0, width
    if columns is not None:
        inside = np.flatnonzero(columns)
        x0, x1 = max(int(inside[0]) - PAD_PX, 0), min(int(inside[-1]) + 1 + PAD_PX, width)
    return x0, max(int(v.min()) - PAD_PX, 0), x1, min(int(v.max()) + 1 + PAD_PX, height)


def has_strokes(rgb: np.ndarray, focal_px: float) -> bool:
    """Whether an image region holds the thin, high-contrast strokes of printed text: at least `MIN_STROKE_PX` pixels
    whose grey level stands `STROKE_CONTRAST` above or below their neighbourhood's (morphological top-hat and black-hat
    with a kernel of a stroke's width, `STROKE_M` at 1 m). About 0.1 ms: the text detector is run only where it can
    find something."""
    import cv2

    size = max(3, int(focal_px * STROKE_M) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    light = cv2.morphologyEx(grey, cv2.MORPH_TOPHAT, kernel)
    dark = cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel)
    return int(np.count_nonzero(np.maximum(light, dark) >= STROKE_CONTRAST)) >= MIN_STROKE_PX


class PlateReader:
    """Door plates read where they can be (module docstring): the `TextReader` of real frames, with the sequence's
    `intrinsics` and `T_base_camera`; readings with score ≥ `min_score` and non-blank text are kept, their boxes in the
    frame's pixels."""

    wants_columns = True

    def __init__(
        self, intrinsics: CameraIntrinsics, T_base_camera: np.ndarray, min_score: float = 0.5, engine: Any | None = None
    ) -> None:
        if engine is None:
            rapidocr = errors.import_optional("rapidocr_onnxruntime", "The RapidOCR text reader", INSTALL_HINT)
            engine = rapidocr.RapidOCR(text_score=min_score, use_cls=False)  # no angle classifier: plates hang upright
        self.engine = engine
        self.intrinsics = intrinsics
        self.T_base_camera = np.asarray(T_base_camera, float)
        self.min_score = float(min_score)
        self.scale = max(1.0, OCR_FOCAL_PX / min(intrinsics.fx, intrinsics.fy))

    def read(self, frame: Frame, columns: np.ndarray | None = None) -> list[TextReading]:
        """The text read in the frame's plate region (within the (W,) bool `columns` where plates can be: nothing is
        read where none can), each with its box in the frame's pixels."""
        height, width = frame.rgb.shape[:2]
        region = None if columns is not None and not np.any(columns) else plate_region(
            frame.depth_m, self.intrinsics, self.T_base_camera, columns
        )  # fmt: skip
        if region is None:
            return []
        x0, y0, x1, y1 = region
        if not has_strokes(frame.rgb[y0:y1, x0:x1], self.intrinsics.fx):
            return []
        detector = getattr(self.engine, "text_det", None)
        if detector is not None:  # RapidOCR's detector scales an image's shorter side to this many pixels
            detector.limit_side_len = round(min(y1 - y0, x1 - x0) * self.scale)
        result, _elapse = self.engine(np.ascontiguousarray(frame.rgb[y0:y1, x0:x1, ::-1]))  # BGR, as RapidOCR takes it
        return engine_readings(result, self.min_score, width, height, offset=(x0, y0))
