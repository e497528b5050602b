"""The RapidOCR text reader: result conversion through a fake engine, the missing-library error, and (where
`rapidocr_onnxruntime` is installed) a real read of a drawn room number."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from bimfactor.errors import DependencyError
from bimfactor.perception.base import TextReader
from bimfactor.perception.ocr import (
    OCR_FOCAL_PX,
    PAD_PX,
    PLATE_HEIGHTS_M,
    READ_RANGE_M,
    PlateReader,
    RapidOcrReader,
    has_strokes,
    plate_columns,
    plate_region,
    quad_to_box,
)
from bimfactor.types import CameraIntrinsics, Frame


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


# ------------------------------------------------------------------------------------------ reading where plates are

SIM_K = CameraIntrinsics(320, 240, 160.0, 160.0, 159.5, 119.5)  # the simulator's 90° camera
LEVEL_MOUNT = np.array([[0.0, 0.0, 1.0, 0.15], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0]])


def wall_depth(distance_m: float, k: CameraIntrinsics = SIM_K) -> np.ndarray:
    """The depth of a wall straight ahead of the level camera, `distance_m` from it."""
    return np.full((k.height, k.width), distance_m, np.float32)


@pytest.mark.parametrize("distance_m", [1.5, 2.0, 2.6])
def test_the_plate_region_is_the_wall_band_at_plate_heights(distance_m: float) -> None:
    """A wall ahead: the region spans the image's width and the rows where the wall is 1.15–1.75 m up (the camera is
    0.5 m up, so 0.65–1.25 m above its axis: rows cy − fy·h/d), grown by the pad."""
    x0, y0, x1, y1 = plate_region(wall_depth(distance_m), SIM_K, LEVEL_MOUNT)
    top = SIM_K.cy - SIM_K.fy * (PLATE_HEIGHTS_M[1] - 0.5) / distance_m
    bottom = SIM_K.cy - SIM_K.fy * (PLATE_HEIGHTS_M[0] - 0.5) / distance_m
    assert (x0, x1) == (0, SIM_K.width)
    assert y0 == pytest.approx(max(top - PAD_PX, 0), abs=1.5) and y1 == pytest.approx(bottom + PAD_PX, abs=1.5)


def test_a_wall_beyond_reading_range_or_a_floor_alone_gives_no_region() -> None:
    assert plate_region(wall_depth(READ_RANGE_M + 0.5), SIM_K, LEVEL_MOUNT) is None
    floor = wall_depth(2.0)
    floor[:] = np.nan  # nothing at plate height: only the floor's lower rows return
    floor[180:] = 1.0
    assert plate_region(floor, SIM_K, LEVEL_MOUNT) is None


def test_the_belief_s_columns_narrow_the_region_and_none_skip_the_frame() -> None:
    columns = np.zeros(SIM_K.width, bool)
    columns[100:140] = True
    x0, _, x1, _ = plate_region(wall_depth(2.0), SIM_K, LEVEL_MOUNT, columns)
    assert (x0, x1) == (100 - PAD_PX, 140 + PAD_PX)
    engine = FakeEngine(None)
    reader = PlateReader(SIM_K, LEVEL_MOUNT, engine=engine)
    frame = Frame(0, 0.0, np.full((240, 320, 3), 200, np.uint8), wall_depth(2.0), np.zeros(3))
    assert reader.read(frame, np.zeros(SIM_K.width, bool)) == [] and engine.images == []


def test_the_plate_reader_reads_the_region_and_reports_frame_pixels() -> None:
    """The region goes to the engine as it is (its detector told to scale it to the OCR focal length: 160 px → 490
    px, × 3.06); a quad read in the region comes back in the frame's pixels."""
    engine = FakeEngine([[[[30.0, 10.0], [60.0, 10.0], [60.0, 20.0], [30.0, 20.0]], "204", 0.9]])
    reader = PlateReader(SIM_K, LEVEL_MOUNT, engine=engine)
    assert isinstance(reader, TextReader) and reader.wants_columns
    assert reader.scale == pytest.approx(OCR_FOCAL_PX / 160.0)
    x0, y0, x1, y1 = plate_region(wall_depth(2.0), SIM_K, LEVEL_MOUNT)
    rgb = plate_on_wall(((x0 + x1) // 2, (y0 + y1) // 2))
    (reading,) = reader.read(Frame(0, 0.0, rgb, wall_depth(2.0), np.zeros(3)))
    (image,) = engine.images
    assert image.shape[:2] == (y1 - y0, x1 - x0)
    np.testing.assert_allclose(reading.box_xyxy, [x0 + 30, y0 + 10, x0 + 60, y0 + 20])
    assert PlateReader(CameraIntrinsics(640, 480, 600.0, 600.0, 320, 240), LEVEL_MOUNT, engine=engine).scale == 1.0
    engine.images.clear()
    assert reader.read(Frame(0, 0.0, rgb, wall_depth(5.0), np.zeros(3))) == [] and engine.images == []


def plate_on_wall(at: tuple[int, int]) -> np.ndarray:
    """A flat light wall with a room number printed at pixel `at` (its text's bottom left)."""
    rgb = np.full((240, 320, 3), 200, np.uint8)
    cv2.putText(rgb, "204", at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
    return rgb


def test_a_region_without_strokes_of_text_is_not_read() -> None:
    """A flat wall, or one smoothly shaded, holds no legible text: the text detector is not run; printed digits are
    strokes, at the simulator's resolution as at a Kinect's."""
    engine = FakeEngine([[[[30.0, 10.0], [60.0, 10.0], [60.0, 20.0], [30.0, 20.0]], "204", 0.9]])
    reader = PlateReader(SIM_K, LEVEL_MOUNT, engine=engine)
    shaded = np.repeat(np.linspace(120, 220, 320).astype(np.uint8)[None, :, None], 240, axis=0).repeat(3, axis=2)
    for rgb in (np.full((240, 320, 3), 200, np.uint8), shaded):
        assert reader.read(Frame(0, 0.0, rgb, wall_depth(2.0), np.zeros(3))) == [] and engine.images == []
    x0, y0, x1, y1 = plate_region(wall_depth(2.0), SIM_K, LEVEL_MOUNT)
    assert has_strokes(plate_on_wall((x0 + 20, y1 - 10))[y0:y1, x0:x1], SIM_K.fx)
    kinect = np.full((480, 640, 3), 200, np.uint8)
    cv2.putText(kinect, "204", (300, 100), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (20, 20, 20), 3, cv2.LINE_AA)
    assert has_strokes(kinect[60:120, 250:450], 525.0) and not has_strokes(kinect[200:300, 250:450], 525.0)


def test_the_belief_forecasts_the_columns_of_a_plate_ahead() -> None:
    """A plate 2 m straight ahead of one pose (facing it) lands in the image's middle columns; the poses behind its
    wall, on another storey or turned away hold none, and the columns carry each pose's weight."""
    ends = np.array([[[2.15, -0.5], [2.15, 0.5]]])  # a wall segment 2 m ahead of the camera (15 cm ahead of the base)
    normals = np.array([[-1.0, 0.0]])  # facing back at the robot
    poses = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 0.0, np.pi], [0.0, 0.0, 0.0]])
    weights = np.array([0.4, 0.3, 0.2, 0.1])
    columns = plate_columns(ends, normals, np.array([0]), poses, np.array([0, 0, 0, 1]), weights, SIM_K, LEVEL_MOUNT)
    span = np.flatnonzero(columns > 0)
    half = SIM_K.fx * 0.5 / 2.0  # ±0.5 m at 2 m
    assert span[0] == pytest.approx(SIM_K.cx - half, abs=2) and span[-1] == pytest.approx(SIM_K.cx + half, abs=2)
    np.testing.assert_allclose(columns[span], 0.4)
