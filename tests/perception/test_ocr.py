"""The RapidOCR text reader: result conversion through a fake engine, the missing-library error, and (where
`rapidocr_onnxruntime` is installed) a real read of a drawn room number."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from bimfactor.errors import DependencyError
from bimfactor.perception.base import TextReader
from bimfactor.perception.ocr import RapidOcrReader, quad_to_box
from bimfactor.types import Frame


class FakeEngine:
    """Called like RapidOCR: records the images it is given and returns a fixed result."""

    def __init__(self, result: list | None) -> None:
        self.result = result
        self.images: list[np.ndarray] = []

    def __call__(self, image: np.ndarray) -> tuple[list | None, list[float] | None]:
        self.images.append(image.copy())
        return self.result, None if self.result is None else [0.0, 0.0, 0.0]


def frame(rgb: np.ndarray) -> Frame:
    height, width = rgb.shape[:2]
    return Frame(0, 0.0, rgb, np.full((height, width), 2.0, np.float32), np.zeros(3))


def blank_frame(height: int = 60, width: int = 80) -> Frame:
    return frame(np.full((height, width, 3), 200, np.uint8))


def test_quads_become_axis_aligned_boxes_clipped_to_the_image() -> None:
    engine = FakeEngine(
        [
            [[[10.0, 12.0], [40.0, 8.0], [42.0, 30.0], [12.0, 34.0]], "101", 0.9],  # tilted, inside
            [[[-5.0, 10.0], [20.0, 4.0], [22.0, 20.0], [-3.0, 26.0]], "A204", 0.8],  # past the left edge
            [[[70.0, 50.0], [90.0, 50.0], [90.0, 70.0], [70.0, 70.0]], "B3", 0.7],  # past the bottom right
        ]
    )
    readings = RapidOcrReader.from_engine(engine).read(blank_frame())
    assert [r.text for r in readings] == ["101", "A204", "B3"]
    assert [r.box_xyxy.tolist() for r in readings] == [[10, 8, 42, 34], [0, 4, 22, 26], [70, 50, 80, 60]]
    assert all(r.box_xyxy.dtype == float and r.gt_instance_id is None for r in readings)
    assert [r.score for r in readings] == [0.9, 0.8, 0.7]
    assert quad_to_box(np.zeros((4, 2)), 80, 60).tolist() == [0, 0, 0, 0]


def test_low_scores_and_blank_texts_are_dropped() -> None:
    quad = [[1.0, 1.0], [9.0, 1.0], [9.0, 5.0], [1.0, 5.0]]
    engine = FakeEngine(
        [
            [quad, "101", 0.59],  # below min_score
            [quad, " 102 ", 0.6],  # exactly min_score: kept, surrounding blanks stripped
            [quad, "   ", 0.99],  # blank
            [quad, "", 0.99],  # empty
            [quad, "103", 0.95, [["1", "0", "3"]]],  # extra fields (RapidOCR's word boxes) are ignored
        ]
    )
    readings = RapidOcrReader.from_engine(engine, min_score=0.6).read(blank_frame())
    assert [(r.text, r.score) for r in readings] == [("102", 0.6), ("103", 0.95)]


def test_no_text_found_is_no_reading() -> None:
    assert RapidOcrReader.from_engine(FakeEngine(None)).read(blank_frame()) == []
    assert RapidOcrReader.from_engine(FakeEngine([])).read(blank_frame()) == []


def test_the_engine_gets_the_image_as_bgr() -> None:
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 10, 20, 30
    rgb[2, 3] = (255, 0, 0)  # one pure red pixel
    engine = FakeEngine(None)
    reader = RapidOcrReader.from_engine(engine)
    assert isinstance(reader, TextReader)
    reader.read(frame(rgb))
    (image,) = engine.images
    assert image.shape == (6, 8, 3) and image.dtype == np.uint8
    assert image[0, 0].tolist() == [30, 20, 10]
    assert image[2, 3].tolist() == [0, 0, 255]
    assert np.array_equal(image, rgb[..., ::-1])
    assert rgb[0, 0].tolist() == [10, 20, 30]  # the frame itself is untouched


def test_missing_rapidocr_is_a_dependency_error_with_the_install_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rapidocr_onnxruntime", None)  # makes `import rapidocr_onnxruntime` fail
    with pytest.raises(DependencyError, match=r"bimfactor\[ocr\]") as info:
        RapidOcrReader()
    assert "rapidocr_onnxruntime" in str(info.value)


def test_rapidocr_reads_a_drawn_room_number() -> None:
    pytest.importorskip("rapidocr_onnxruntime")
    cv2 = pytest.importorskip("cv2")
    rgb = np.full((240, 320, 3), 235, np.uint8)
    cv2.putText(rgb, "204", (80, 150), cv2.FONT_HERSHEY_SIMPLEX, 2.2, (20, 20, 30), 5, cv2.LINE_AA)
    ys, xs = np.nonzero(rgb[..., 0] < 128)
    ink = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], float)
    assert ink[3] - ink[1] >= 40  # large text: the digits are ~46 px high, the putText line 60 px

    readings = RapidOcrReader().read(frame(rgb))

    matches = [r for r in readings if r.text == "204"]
    assert len(matches) == 1, [(r.text, r.score) for r in readings]
    (reading,) = matches
    x0, y0, x1, y1 = reading.box_xyxy
    assert 0.5 <= reading.score <= 1.0
    cx, cy = (ink[0] + ink[2]) / 2, (ink[1] + ink[3]) / 2
    assert x0 <= cx <= x1 and y0 <= cy <= y1
    # the box covers the drawn digits (a few pixels of slack: the detector's quad hugs the glyphs)
    assert x0 <= ink[0] + 4 and y0 <= ink[1] + 4 and x1 >= ink[2] - 4 and y1 >= ink[3] - 4
    assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 240
