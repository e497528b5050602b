"""The contact sheet: a valid PNG of the expected layout, written atomically."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from bimfactor.io.preview import instance_colours, preview_indices, write_preview
from bimfactor.io.sequence import read_sequence, write_sequence
from tests.io.synthetic import make_frames, make_meta


def test_preview_indices_spread_evenly() -> None:
    assert preview_indices(100, 5).tolist() == [0, 25, 50, 74, 99]
    assert preview_indices(3, 12).tolist() == [0, 1, 2]
    assert preview_indices(0, 12).tolist() == []


def test_instance_colours_are_fixed_per_id_and_black_for_nothing() -> None:
    ids = np.array([[-1, 0, 1], [1, 0, -1]])
    colours = instance_colours(ids)
    assert colours.shape == (2, 3, 3) and colours.dtype == np.uint8
    assert (colours[0, 0] == 0).all() and (colours[1, 2] == 0).all()
    np.testing.assert_array_equal(colours[0, 1], colours[1, 1])
    assert colours[0, 1].max() >= 40 and colours[0, 2].max() >= 40


def test_write_preview(tmp_path: Path) -> None:
    write_sequence(tmp_path / "seq", make_meta(), make_frames(6))
    seq = read_sequence(tmp_path / "seq")
    out = write_preview(seq, tmp_path / "out" / "preview.png", max_frames=4)
    assert out == tmp_path / "out" / "preview.png"
    assert sorted(p.name for p in out.parent.iterdir()) == ["preview.png"]  # no temporary file left
    image = cv2.imread(str(out), cv2.IMREAD_COLOR)
    assert image is not None
    height, width = image.shape[:2]
    # three 3.2-inch panels at 100 dpi per row, four rows of 32x24 images (plus titles)
    assert 900 <= width <= 1000
    assert 4 * 240 <= height <= 4 * 300 + 100
    assert image.std() > 10  # not a blank canvas
    # the depth column's colour bar under the last row: dark blue (near) on the left to dark red (far) on the right
    column = image[-100:, width // 3 : 2 * width // 3].astype(int)  # BGR
    rows = np.flatnonzero(column.std(axis=2).max(axis=1) > 30)
    bar = column[rows[-1] - 3]  # the lowest coloured stripe: the bar, below the last depth image
    span = np.flatnonzero(bar.std(axis=1) > 30)
    left, right = bar[span[0] + len(span) // 10], bar[span[-1] - len(span) // 10]
    assert left[0] > left[2] + 50 and right[2] > right[0] + 50

    # without instance images: two columns
    frames = make_frames(3)
    for f in frames:
        f.instance_ids = None
    write_sequence(tmp_path / "plain", make_meta(), frames)
    out = write_preview(read_sequence(tmp_path / "plain"), tmp_path / "plain.png")
    assert 600 <= cv2.imread(str(out)).shape[1] <= 680


def test_panels_are_reduced_to_their_pixel_width_keeping_holes_and_ids() -> None:
    from bimfactor.io.preview import DPI, PANEL_WIDTH_IN, panel_image

    width = int(PANEL_WIDTH_IN * DPI)
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:, :320] = np.nan  # the left half has no return
    small = panel_image(depth, smooth=False)
    assert small.shape == (240, width)
    assert np.isnan(small[:, : width // 2 - 1]).all() and (small[:, width // 2 + 1 :] == 2.0).all()
    ids = np.arange(640, dtype=np.int32)[None].repeat(480, axis=0) % 7
    assert set(np.unique(panel_image(ids, smooth=False))) <= set(range(7))  # ids are picked, never blended
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[:, 1::2] = 200
    assert panel_image(rgb, smooth=True).shape == (240, width, 3) and (panel_image(rgb, smooth=True) == 100).all()
    narrow = np.zeros((120, 160), np.float32)
    assert panel_image(narrow, smooth=False) is narrow
