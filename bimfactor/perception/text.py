"""Door-plate text: the simulator's reader, and where a reading is in the robot frame.

`SimTextReader` reads the door plates the simulator hung (`sim.door_plates`, `bim.plates`) from the instance
buffer: a plate at least `sim_min_height_px` high and wide is legible, read with `sim_read_probability`, and each
character is replaced by another letter or digit with `sim_char_error_rate`. Real images go through
`perception.ocr.RapidOcrReader`. `locate_readings` places any reader's readings in the robot base frame from the
depth under their boxes: the `TextObservations` the localizer weighs (`localization.text`).
"""

from __future__ import annotations

import string
from collections.abc import Sequence

import numpy as np

from bimfactor.config import TextReadingConfig
from bimfactor.perception.base import TextReading, box_to_pixels
from bimfactor.perception.lifting import backproject, transform_points
from bimfactor.sim.world import DOOR_PLATE_LABEL
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta, TextObservations

ALPHABET = string.digits + string.ascii_uppercase  # what a misread character becomes
MAX_POINTS = 400  # depth pixels under a box that place a reading


class SimTextReader:
    """Reads the simulator's door plates in view, with legibility, misses and character errors."""

    def __init__(self, meta: SequenceMeta, cfg: TextReadingConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.plates = {int(r["id"]): str(r["text"]) for r in meta.instances if r.get("label") == DOOR_PLATE_LABEL}

    def read(self, frame: Frame) -> list[TextReading]:
        """The plates of this frame that are legible and read, as `TextReading`s with their pixel boxes."""
        if not self.plates or frame.instance_ids is None:
            return []
        ids = frame.instance_ids
        readings = []
        for iid in np.intersect1d(np.unique(ids), np.fromiter(self.plates, np.int64)):
            text = self.plates[int(iid)]
            u_read, u_chars = self.rng.random(), self.rng.random(len(text))
            shifts = self.rng.integers(1, len(ALPHABET), len(text))
            rows, cols = np.nonzero(ids == iid)
            box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
            if min(box[2] - box[0], box[3] - box[1]) < self.cfg.sim_min_height_px:
                continue
            if u_read >= self.cfg.sim_read_probability:
                continue
            read = "".join(
                ALPHABET[(ALPHABET.index(c) + int(k)) % len(ALPHABET)] if u < self.cfg.sim_char_error_rate else c
                for c, u, k in zip(text.upper(), u_chars, shifts, strict=True)
                if c in ALPHABET
            )
            readings.append(TextReading(read, box, 1.0, gt_instance_id=int(iid)))
        return readings


def locate_readings(
    readings: Sequence[TextReading],
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_base_camera: np.ndarray,
    max_depth_m: float,
) -> TextObservations:
    """Each reading's range and bearing in the robot base frame: the median of the depth points under its box.

    A reading with no depth return under its box (within `max_depth_m`) is dropped.
    """
    height, width = depth_m.shape
    texts, ranges, bearings = [], [], []
    for reading in readings:
        x0, y0, x1, y1 = box_to_pixels(reading.box_xyxy, width, height)
        mask = np.zeros(depth_m.shape, bool)
        mask[y0:y1, x0:x1] = True
        points = backproject(depth_m, mask, intrinsics, max_depth_m, MAX_POINTS)
        if len(points) == 0:
            continue
        x, y, _ = transform_points(np.asarray(T_base_camera, float), np.median(points, axis=0)[None])[0]
        texts.append(reading.text)
        ranges.append(float(np.hypot(x, y)))
        bearings.append(float(np.arctan2(y, x)))
    return TextObservations(texts, np.asarray(ranges, float), np.asarray(bearings, float))
