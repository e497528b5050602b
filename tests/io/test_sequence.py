"""The sequence folder format: exact round trips, atomic writes and one-line errors for corrupt input."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from bimfactor.errors import FormatError, InputError
from bimfactor.io.sequence import (
    FRAME_COLUMNS,
    Sequence,
    associate_nearest,
    quantize_depth_m,
    read_sequence,
    write_sequence,
)
from bimfactor.io.tum import read_tum_trajectory
from bimfactor.types import STOREY_CHANGE, wrap_angle
from tests.io.synthetic import expected_depth, make_frames, make_meta


@pytest.fixture
def written(tmp_path: Path) -> tuple[Path, list]:
    frames = make_frames()
    path = tmp_path / "seq"
    write_sequence(path, make_meta(), frames)
    return path, frames


def _one_line_error(exc_info: pytest.ExceptionInfo) -> str:
    message = str(exc_info.value)
    assert "\n" not in message
    return message


def test_round_trip_is_exact(written: tuple[Path, list]) -> None:
    path, frames = written
    meta = make_meta()
    seq = read_sequence(path)

    assert len(seq) == len(frames)
    assert seq.meta.name == meta.name and seq.meta.source == meta.source
    assert seq.meta.intrinsics == meta.intrinsics
    np.testing.assert_array_equal(seq.meta.T_base_camera, meta.T_base_camera)
    assert seq.meta.prior_sha256 == meta.prior_sha256
    assert seq.meta.instances == meta.instances
    assert seq.meta.extras == meta.extras
    np.testing.assert_array_equal(seq.timestamps(), [f.timestamp_s for f in frames])
    np.testing.assert_array_equal(seq.odometry(), np.array([f.odom_pose for f in frames]))
    gt = seq.ground_truth()
    assert np.isnan(gt[1]).all()
    np.testing.assert_array_equal(gt[[0, 2, 3, 4]], np.array([frames[k].gt_pose for k in (0, 2, 3, 4)]))

    for got, want in zip(seq, frames, strict=True):
        assert got.index == want.index
        assert got.timestamp_s == want.timestamp_s
        assert got.rgb.dtype == np.uint8
        np.testing.assert_array_equal(got.rgb, want.rgb)
        assert got.depth_m.dtype == np.float32
        np.testing.assert_array_equal(got.depth_m, expected_depth(want.depth_m))
        assert np.nanmax(np.abs(got.depth_m - want.depth_m)) <= 0.0005 + 1e-6
        np.testing.assert_array_equal(got.odom_pose, want.odom_pose)
        if want.gt_pose is None:
            assert got.gt_pose is None
        else:
            np.testing.assert_array_equal(got.gt_pose, want.gt_pose)
        assert got.gt_storey == want.gt_storey
        if want.instance_ids is None:
            assert got.instance_ids is None
        else:
            assert got.instance_ids.dtype == np.int32
            np.testing.assert_array_equal(got.instance_ids, want.instance_ids)
        assert got.extras == want.extras

    # depth details: 0.4 mm rounds to no return, 65.535 m is the largest depth kept
    assert np.isnan(seq[0].depth_m[0, 0])
    assert seq[0].depth_m[0, 1] == np.float32(65535) / np.float32(1000)
    np.testing.assert_array_equal(quantize_depth_m(frames[3].depth_m), expected_depth(frames[3].depth_m))


def test_in_memory_sequence_matches_the_frames() -> None:
    frames = make_frames(4)
    seq = Sequence.from_frames(make_meta(), frames)
    assert len(seq) == 4 and seq[1].gt_pose is None and seq.ground_truth_storeys()[1] is None
    np.testing.assert_array_equal(seq.odometry(), np.array([f.odom_pose for f in frames]))
    np.testing.assert_array_equal(seq[2].gt_pose, frames[2].gt_pose)
    assert [f.extras for f in seq] == [f.extras for f in frames]


def test_a_subset_keeps_the_chosen_frames_and_their_indices(written: tuple[Path, list]) -> None:
    path, frames = written
    seq = read_sequence(path)
    part = seq.subset(np.array([1, 3, 4]))
    assert len(part) == 3 and [f.index for f in part] == [frames[i].index for i in (1, 3, 4)]
    np.testing.assert_array_equal(part.timestamps(), seq.timestamps()[[1, 3, 4]])
    np.testing.assert_array_equal(part.odometry(), seq.odometry()[[1, 3, 4]])
    np.testing.assert_array_equal(part[1].rgb, frames[3].rgb)
    np.testing.assert_array_equal(part[2].depth_m, seq[4].depth_m)
    assert part.ground_truth_storeys() == [seq.ground_truth_storeys()[i] for i in (1, 3, 4)]
    for rows in ([3, 1], [0, len(frames)], [-1, 2]):
        with pytest.raises(ValueError, match="rows must increase"):
            seq.subset(np.array(rows))


def test_random_access_and_index_errors(written: tuple[Path, list]) -> None:
    path, frames = written
    seq = read_sequence(path)
    assert seq[-1].index == frames[-1].index
    np.testing.assert_array_equal(seq[3].rgb, frames[3].rgb)
    with pytest.raises(IndexError):
        seq[len(frames)]


def test_tum_side_files_match_frames(written: tuple[Path, list]) -> None:
    path, frames = written
    t_odom, odom = read_tum_trajectory(path / "odometry.txt")
    np.testing.assert_array_equal(t_odom, [f.timestamp_s for f in frames])
    want = np.array([f.odom_pose for f in frames])
    np.testing.assert_array_equal(odom[:, :2], want[:, :2])
    np.testing.assert_allclose(wrap_angle(odom[:, 2] - want[:, 2]), 0.0, atol=1e-12)
    t_gt, gt = read_tum_trajectory(path / "groundtruth.txt")
    with_gt = [f for f in frames if f.gt_pose is not None]  # frame 1 has no ground truth
    np.testing.assert_array_equal(t_gt, [f.timestamp_s for f in with_gt])
    np.testing.assert_array_equal(gt[:, :2], np.array([f.gt_pose[:2] for f in with_gt]))


def test_writer_accepts_a_generator_and_no_odometry(tmp_path: Path) -> None:
    frames = make_frames(3)
    for f in frames:
        f.odom_pose = np.full(3, np.nan)
        f.gt_pose = None
    write_sequence(tmp_path / "seq", make_meta(), (f for f in frames))
    seq = read_sequence(tmp_path / "seq")
    assert seq.odometry() is None and seq.ground_truth() is None
    assert np.isnan(seq[0].odom_pose).all()
    assert not (tmp_path / "seq" / "odometry.txt").exists()
    assert not (tmp_path / "seq" / "groundtruth.txt").exists()


# ------------------------------------------------------------------------------------------ writer refusals


def _refused(tmp_path: Path, frames: list, match: str) -> None:
    with pytest.raises(InputError, match=match) as exc_info:
        write_sequence(tmp_path / "seq", make_meta(), frames)
    _one_line_error(exc_info)
    assert list(tmp_path.iterdir()) == []  # atomic: neither the folder nor a temporary one is left


def test_writer_refuses_negative_depth(tmp_path: Path) -> None:
    frames = make_frames(3)
    frames[2].depth_m[5, 5] = -0.1
    _refused(tmp_path, frames, r"frame 2 \(index 14\): negative depth")


@pytest.mark.parametrize("dt", [0.0, -0.05], ids=["duplicate", "out-of-order"])
def test_writer_refuses_bad_timestamps(tmp_path: Path, dt: float) -> None:
    frames = make_frames(3)
    frames[2].timestamp_s = frames[1].timestamp_s + dt
    _refused(tmp_path, frames, "frame 2 .* is not after the previous one")


def test_writer_refuses_wrong_image_shape_and_partial_odometry(tmp_path: Path) -> None:
    frames = make_frames(3)
    frames[1].rgb = frames[1].rgb[:, :-1]
    _refused(tmp_path, frames, "frame 1 .*: rgb has shape")
    frames = make_frames(3)
    frames[2].odom_pose = np.full(3, np.nan)
    _refused(tmp_path, frames, "odometry must be known for every frame or for none")
    frames = make_frames(3)
    frames[0].instance_ids[0, 0] = -2
    _refused(tmp_path, frames, "instance ids must lie in")
    _refused(tmp_path, [], "no frames")


def test_writer_clamps_far_depth_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    frames = make_frames(2)
    frames[0].depth_m[3, 3] = 70.0
    frames[0].depth_m[3, 4] = np.inf
    with caplog.at_level(logging.WARNING):
        write_sequence(tmp_path / "seq", make_meta(), frames)
    assert "2 depth pixels in 1 frames beyond 65.535 m" in caplog.text
    depth = read_sequence(tmp_path / "seq")[0].depth_m
    assert np.isnan(depth[3, 3]) and np.isnan(depth[3, 4])


def test_writer_does_not_overwrite_unless_asked(written: tuple[Path, list]) -> None:
    path, _ = written
    with pytest.raises(InputError, match="exists already"):
        write_sequence(path, make_meta(), make_frames(2))
    write_sequence(path, make_meta("second"), make_frames(2), overwrite=True)
    seq = read_sequence(path)
    assert seq.meta.name == "second" and len(seq) == 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["seq"]


# ------------------------------------------------------------------------------------------ corrupt folders


def _rewrite_frames_csv(path: Path, edit) -> None:
    lines = (path / "frames.csv").read_text().splitlines()
    (path / "frames.csv").write_text("\n".join(edit(lines)) + "\n")


def test_missing_sequence_json(written: tuple[Path, list]) -> None:
    path, _ = written
    (path / "sequence.json").unlink()
    with pytest.raises(FormatError, match=r"sequence\.json missing") as exc_info:
        read_sequence(path)
    _one_line_error(exc_info)


def test_not_a_folder_and_bad_metadata(tmp_path: Path, written: tuple[Path, list]) -> None:
    with pytest.raises(InputError, match="no such sequence folder"):
        read_sequence(tmp_path / "nothing")
    path, _ = written
    meta = json.loads((path / "sequence.json").read_text())
    (path / "sequence.json").write_text(json.dumps({**meta, "version": 99}))
    with pytest.raises(FormatError, match="format version 99"):
        read_sequence(path)
    (path / "sequence.json").write_text('{"format": "bimfactor-seq')
    with pytest.raises(FormatError, match="corrupt JSON"):
        read_sequence(path)
    (path / "sequence.json").write_text(json.dumps({**meta, "frame_count": 9}))
    with pytest.raises(FormatError, match=r"5 frame rows, but sequence\.json says frame_count 9"):
        read_sequence(path)


def test_missing_frame_file(written: tuple[Path, list], caplog: pytest.LogCaptureFixture) -> None:
    path, frames = written
    (path / "depth" / "000003.png").unlink()
    with pytest.raises(FormatError, match=r"line 5: frame file missing: .*depth/000003.png") as exc_info:
        read_sequence(path)
    _one_line_error(exc_info)
    with caplog.at_level(logging.WARNING):
        seq = read_sequence(path, on_bad_frame="skip")
    assert len(seq) == len(frames) - 1
    assert [f.index for f in seq] == [f.index for k, f in enumerate(frames) if k != 3]
    assert "000003.png" in caplog.text


def test_truncated_png(written: tuple[Path, list]) -> None:
    path, frames = written
    png = path / "rgb" / "000002.png"
    png.write_bytes(png.read_bytes()[:-20])
    seq = read_sequence(path)  # lazy: opening does not decode
    with pytest.raises(FormatError, match=r"rgb/000002.png: truncated PNG") as exc_info:
        seq[2]
    _one_line_error(exc_info)
    np.testing.assert_array_equal(seq[3].rgb, frames[3].rgb)
    skipped = read_sequence(path, on_bad_frame="skip")
    assert len(skipped) == len(frames) - 1
    png.write_bytes(b"this is no png")
    with pytest.raises(FormatError, match="not a PNG file"):
        read_sequence(path)[2]


def test_image_of_the_wrong_kind(written: tuple[Path, list]) -> None:
    path, _ = written
    # an 8-bit colour PNG where a 16-bit depth PNG belongs
    (path / "depth" / "000000.png").write_bytes((path / "rgb" / "000000.png").read_bytes())
    with pytest.raises(FormatError, match=r"depth/000000.png: 3-channel uint8 image, expected 1-channel uint16"):
        read_sequence(path)[0]


@pytest.mark.parametrize("swap", ["out-of-order", "duplicate"])
def test_bad_timestamps_name_the_first_bad_row(written: tuple[Path, list], swap: str) -> None:
    path, _ = written

    def edit(lines: list[str]) -> list[str]:
        rows = [line.split(",") for line in lines]
        # row of frame 3 (line 5) gets frame 1's time (out of order) or frame 2's (duplicate)
        rows[4][1] = rows[2][1] if swap == "out-of-order" else rows[3][1]
        return [",".join(r) for r in rows]

    _rewrite_frames_csv(path, edit)
    with pytest.raises(FormatError, match=rf"frames.csv line 5: {swap} timestamp") as exc_info:
        read_sequence(path)
    _one_line_error(exc_info)


def test_wrong_column_count(written: tuple[Path, list]) -> None:
    path, _ = written
    n_columns = len(FRAME_COLUMNS) + 2  # two extra.* columns
    _rewrite_frames_csv(path, lambda lines: [*lines[:2], lines[2].rsplit(",", 1)[0], *lines[3:]])
    with pytest.raises(FormatError, match=rf"line 3: {n_columns - 1} columns, expected {n_columns}") as exc_info:
        read_sequence(path)
    _one_line_error(exc_info)


def test_bad_cells_and_header(written: tuple[Path, list]) -> None:
    path, _ = written
    original = (path / "frames.csv").read_text()
    (path / "frames.csv").write_text(original.replace(original.splitlines()[2].split(",")[5], "abc", 1))
    with pytest.raises(FormatError, match=r"line 3: odom_x 'abc' is not a number"):
        read_sequence(path)
    (path / "frames.csv").write_text(original.replace("timestamp_s", "time", 1))
    with pytest.raises(FormatError, match="header must start with index,timestamp_s"):
        read_sequence(path)
    (path / "frames.csv").unlink()
    with pytest.raises(FormatError, match=r"frames\.csv missing"):
        read_sequence(path)


def test_paths_outside_the_folder_are_rejected(written: tuple[Path, list]) -> None:
    path, _ = written
    _rewrite_frames_csv(path, lambda lines: [lines[0], lines[1].replace("rgb/000000.png", "../x.png"), *lines[2:]])
    with pytest.raises(FormatError, match="must be a relative path inside the sequence folder"):
        read_sequence(path)


def test_associate_nearest() -> None:
    t_rgb = np.array([0.0, 1.0, 2.0, 3.0])
    t_depth = np.array([0.01, 0.985, 1.005, 2.5, 3.0])
    iq, ir = associate_nearest(t_rgb, t_depth, 0.02)
    assert iq.tolist() == [0, 1, 3] and ir.tolist() == [0, 2, 4]  # 2.0 has nothing within 0.02 s
    iq, ir = associate_nearest(np.array([1.0, 1.01]), np.array([1.005]), 0.02)
    assert iq.tolist() == [0] and ir.tolist() == [0]  # one-to-one: the tie goes to the first query
    iq, ir = associate_nearest(np.array([1.0, 1.01, 5.0]), np.array([1.005]), 0.02, one_to_one=False)
    assert iq.tolist() == [0, 1] and ir.tolist() == [0, 0]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_full_disk_is_an_os_error_naming_the_file_and_libpng_says_nothing(capfd: pytest.CaptureFixture) -> None:
    """/dev/full fails every write with ENOSPC: the error names it, and no libpng line reaches stderr first."""
    import errno

    from bimfactor.io.sequence import _write_png

    with pytest.raises(OSError) as caught:
        _write_png(Path("/dev/full"), np.zeros((8, 8, 3), np.uint8), "frame 0")
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == "/dev/full"
    assert capfd.readouterr().err == ""


def test_a_storey_change_is_read_from_frames_csv_and_a_subset_keeps_it(tmp_path: Path) -> None:
    frames = make_frames(5)
    frames[1].extras = {STOREY_CHANGE: 1.0}  # the lift went up a floor before frame 1
    frames[3].extras = {STOREY_CHANGE: -2.0}
    write_sequence(tmp_path / "seq", make_meta(), frames)
    header = (tmp_path / "seq" / "frames.csv").read_text().splitlines()[0]
    assert header.endswith(f"extra.{STOREY_CHANGE}") or f"extra.{STOREY_CHANGE}," in header
    seq = read_sequence(tmp_path / "seq")
    assert [f.extras.get(STOREY_CHANGE) for f in seq] == [None, 1.0, None, -2.0, None]
    # keyframes 0, 2, 4: a change on a frame left out goes to the next one kept
    assert [f.extras.get(STOREY_CHANGE) for f in seq.subset(np.array([0, 2, 4]))] == [None, 1.0, -2.0]
    assert [f.extras.get(STOREY_CHANGE) for f in seq.subset(np.array([0, 1, 3]))] == [None, 1.0, -2.0]
