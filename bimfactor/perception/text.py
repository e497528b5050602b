"""Door-plate text: the simulator's reader, and where a reading is in the robot frame.

`SimTextReader` reads the simulator's door plates from the instance buffer: legible at `sim_min_height_px`, read with a
chance that grows with the characters' width in the image (`read_probability`), each character then misread as a
look-alike, as another, or lost at the rates `tools/calibrate_text_reader.py` fitted to RapidOCR. `locate_readings`
places any reader's readings in the base frame from the depth under their boxes (`TextObservations`).
"""

from __future__ import annotations

import string
from collections.abc import Sequence

import numpy as np

from bimfactor.bim.plates import DOOR_PLATE_LABEL, look_alikes
from bimfactor.config import TextReadingConfig
from bimfactor.perception.base import TextReading, box_to_pixels
from bimfactor.perception.lifting import backproject, transform_points
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta, TextObservations

ALPHABET = string.digits + string.ascii_uppercase  # what a misread character becomes
MAX_POINTS = 400  # depth pixels under a box that place a reading


def read_probability(char_px: np.ndarray | float, most: float, half_px: float, scale_px: float) -> np.ndarray:
    """The sim reader's chance to read a legible plate whose width in the image is `char_px` pixels per character:
    most · logistic((char_px − half_px) / scale_px) (`perception.text.sim_read_probability`, `sim_read_char_px`,
    `sim_read_char_scale_px`)."""
    z = (np.asarray(char_px, float) - half_px) / scale_px
    return most / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))


class SimTextReader:
    """Reads the simulator's door plates in view, with legibility, misses and character errors."""

    wants_columns = False

    def __init__(self, meta: SequenceMeta, cfg: TextReadingConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.plates = {int(r["id"]): str(r["text"]) for r in meta.instances if r.get("label") == DOOR_PLATE_LABEL}

    def read(self, frame: Frame, columns: np.ndarray | None = None) -> list[TextReading]:
        """The plates of this frame that are legible and read, as `TextReading`s with their pixel boxes (`columns`
        is not looked at: the simulator's reader costs nothing to run everywhere)."""
        if not self.plates or frame.instance_ids is None:
            return []
        ids, cfg = frame.instance_ids, self.cfg
        readings = []
        for iid in np.intersect1d(np.unique(ids), np.fromiter(self.plates, np.int64)):
            text = self.plates[int(iid)]
            u_read = self.rng.random()
            rows, cols = np.nonzero(ids == iid)
            box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
            if min(box[2] - box[0], box[3] - box[1]) < cfg.sim_min_height_px:
                continue
            char_px = (box[2] - box[0]) / max(len(text), 1)
            if u_read >= read_probability(
                char_px, cfg.sim_read_probability, cfg.sim_read_char_px, cfg.sim_read_char_scale_px
            ):
                continue
            read = "".join(self._misread(c) for c in text.upper() if c in ALPHABET)
            if read:  # every character lost: nothing was read
                readings.append(TextReading(read, box, 1.0, gt_instance_id=int(iid)))
        return readings

    def _misread(self, char: str) -> str:
        """What is read of one character: itself, a look-alike (if it has one), any other character, or nothing."""
        cfg = self.cfg
        u, pick = self.rng.random(), self.rng.random()
        if u < cfg.sim_look_alike_rate:
            similar = look_alikes(char)
            return similar[int(pick * len(similar))] if similar else char
        if (u := u - cfg.sim_look_alike_rate) < cfg.sim_char_error_rate:
            return ALPHABET[(ALPHABET.index(char) + 1 + int(pick * (len(ALPHABET) - 1))) % len(ALPHABET)]
        return "" if u - cfg.sim_char_error_rate < cfg.sim_drop_rate else char


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
