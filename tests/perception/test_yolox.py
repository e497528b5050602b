"""The shipped detector: YOLOX-Nano's file, its decoding, its COCO → vocabulary table, and what it finds in a real
frame."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from bimfactor.bim.vocabulary import Vocabulary
from bimfactor.config import Config, config_file
from bimfactor.perception.yolox import (
    COCO_CLASSES,
    INPUT_SIZE,
    MODEL_SHA256,
    PAD_VALUE,
    LabelTable,
    YoloxDetector,
    coco_label_table,
    decode,
    letterbox,
    model_path,
)
from bimfactor.types import Frame


def test_the_model_ships_inside_the_package() -> None:
    path = model_path()
    assert path.is_file() and path.parent.name == "models" and path.parent.parent.name == "bimfactor"
    assert hashlib.sha256(path.read_bytes()).hexdigest() == MODEL_SHA256
    assert (path.parent / "LICENSE-yolox").is_file()


def test_letterbox_scales_into_the_square_and_pads_bottom_right() -> None:
    bgr = np.full((480, 640, 3), 7, np.uint8)
    blob, r = letterbox(bgr)
    assert blob.shape == (1, 3, INPUT_SIZE, INPUT_SIZE) and blob.dtype == np.float32
    assert r == pytest.approx(INPUT_SIZE / 640)
    assert np.all(blob[0, :, : round(480 * r), :] == 7) and np.all(blob[0, :, round(480 * r) :, :] == PAD_VALUE)


def test_decode_maps_a_cell_to_image_pixels_and_suppresses_overlaps() -> None:
    """Two rows of the stride-8 grid, cell (10, 20) and its neighbour, say "chair" for one 32 × 64 px box (in the
    416 input); a third says "couch" for the same box with a lower score, and NMS across classes keeps the first."""
    rows = np.zeros((52 * 52 + 26 * 26 + 13 * 13, 85), np.float32)
    chair, couch = COCO_CLASSES.index("chair"), COCO_CLASSES.index("couch")
    for row, dx, score, cls in ((20 * 52 + 10, 0.5, 0.9, chair), (20 * 52 + 11, -0.5, 0.6, couch)):
        rows[row, :4] = [dx, 0.5, np.log(4.0), np.log(8.0)]  # centre (10.5 · 8, 20.5 · 8), size 32 × 64
        rows[row, 4], rows[row, 5 + cls] = 1.0, score
    r = 0.5  # the image was scaled by a half into the input
    keep = np.ones(80, bool)
    boxes, scores, classes = decode(rows.copy(), r, 0.25, keep)
    assert classes.tolist() == [chair] and scores.tolist() == pytest.approx([0.9])
    np.testing.assert_allclose(boxes[0], np.array([84 - 16, 164 - 32, 84 + 16, 164 + 32]) / r)
    keep[chair] = False  # a class that maps to nothing is never reported
    _, _, classes = decode(rows.copy(), r, 0.25, keep)
    assert classes.tolist() == [couch]


def test_coco_classes_map_to_the_vocabulary_by_its_rules_then_the_encoder(text_embedder) -> None:
    vocabulary = Vocabulary.load(config_file("vocabulary.yaml"))
    table = coco_label_table(vocabulary, text_embedder, 0.7)
    kept = table.kept
    assert kept["chair"] == "chair" and kept["couch"] == "sofa" and kept["tv"] == "television"
    assert kept["toilet"] == "water closet" and kept["potted plant"] == "plant" and kept["oven"] == "stove"
    assert kept["laptop"] == "computer" and table.how[COCO_CLASSES.index("laptop")].startswith("embedding")
    for dropped in ("person", "car", "keyboard", "book", "cup", "mouse"):
        assert dropped not in kept
    assert set(kept.values()) <= set(vocabulary.labels)
    assert coco_label_table(vocabulary, text_embedder, 0.99).kept.get("laptop") is None  # the threshold decides


def test_the_decoder_finds_the_chairs_and_the_table_of_a_real_dining_room(real_recording, test_config: Config) -> None:
    """slambook-dining frame 1: seven chairs (one an armchair) around a dining table; YOLOX-Nano finds at least
    five of the chairs and the table (measured: 8 chair boxes, one spanning two chairs, and the table)."""
    bgr = cv2.imread(str(real_recording("slambook-dining") / "rgb" / "1.png"))
    detector = YoloxDetector(LabelTable.coco(), test_config.perception.box_threshold)
    frame = Frame(0, 0.0, np.ascontiguousarray(bgr[..., ::-1]), np.zeros(bgr.shape[:2], np.float32), np.zeros(3))
    labels = [d.label for d in detector.detect(frame)]
    assert labels.count("chair") >= 5 and labels.count("dining table") == 1
    assert all(0 <= d.box_xyxy[0] < d.box_xyxy[2] <= 640 and 0 <= d.box_xyxy[1] < d.box_xyxy[3] <= 480
               for d in detector.detect(frame))  # fmt: skip


def test_a_missing_model_file_is_a_dependency_error(tmp_path: Path) -> None:
    from bimfactor.errors import DependencyError

    with pytest.raises(DependencyError, match="YOLOX model file is missing"):
        YoloxDetector(LabelTable.coco(), 0.25, tmp_path / "none.onnx")
