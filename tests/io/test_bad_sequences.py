"""Sequences that are not what they claim: a camera model that is no camera (read and write), a PNG whose damage
libpng would print about, a byte-order mark before frames.csv's header, TUM / ROS inputs with a bad camera, and a
folder that is not a ROS 2 bag. Each is one InputError / FormatError line naming what is wrong."""

from __future__ import annotations

import dataclasses
import json
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bimfactor.cli import app
from bimfactor.errors import FormatError, InputError
from bimfactor.io.sequence import (
    camera_problem,
    decode_png,
    level_camera_mount,
    read_sequence,
    write_sequence,
)
from bimfactor.types import CameraIntrinsics
from tests.io.synthetic import make_frames, make_meta

# sequence.json edits that leave no camera: (id, edit of the parsed JSON, the message's field text)
MIRRORED = np.diag([1.0, 1.0, -1.0, 1.0]) @ level_camera_mount(0.5)
SCALED = level_camera_mount(0.5) * np.array([[2.0], [2.0], [2.0], [1.0]])


def _set(path: tuple[str, ...], value: object) -> Callable[[dict], None]:
    def edit(data: dict) -> None:
        target = data
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return edit


def _both(edit_a: Callable[[dict], None], edit_b: Callable[[dict], None]) -> Callable[[dict], None]:
    def edit(data: dict) -> None:
        edit_a(data)
        edit_b(data)

    return edit


BAD_CAMERAS = {
    "mount NaN": (
        _set(("T_base_camera",), np.full((4, 4), np.nan).tolist()),
        "T_base_camera must be finite, got nan in row 0, column 0",
    ),
    "mount all zeros": (_set(("T_base_camera",), np.zeros((4, 4)).tolist()), "rotation part is not a rotation"),
    "mount scaled": (_set(("T_base_camera",), SCALED.tolist()), "rotation part is not a rotation"),
    "mount mirrored": (_set(("T_base_camera",), MIRRORED.tolist()), "det = -1"),
    "mount last row": (
        _set(("T_base_camera",), np.vstack([level_camera_mount()[:3], [0.0, 0.0, 1.0, 1.0]]).tolist()),
        "last row must be 0 0 0 1, got 0 0 1 1",
    ),
    "mount 3x3": (_set(("T_base_camera",), np.eye(3).tolist()), "T_base_camera must be a 4x4 matrix, got shape (3, 3)"),
    "cx NaN": (_set(("intrinsics", "cx"), float("nan")), "intrinsics.cx must be a finite number, got nan"),
    "fx = fy = 0": (
        _both(_set(("intrinsics", "fx"), 0), _set(("intrinsics", "fy"), 0)),
        "intrinsics.fx must be a positive finite number, got 0",
    ),
    "negative fx": (_set(("intrinsics", "fx"), -16.0), "intrinsics.fx must be a positive finite number, got -16.0"),
    "infinite fy": (
        _set(("intrinsics", "fy"), float("inf")),
        "intrinsics.fy must be a positive finite number, got inf",
    ),
    "width NaN": (_set(("intrinsics", "width"), float("nan")), "intrinsics.width must be a positive integer, got nan"),
    "height 0": (_set(("intrinsics", "height"), 0), "intrinsics.height must be a positive integer, got 0"),
    "height negative": (_set(("intrinsics", "height"), -24), "intrinsics.height must be a positive integer, got -24"),
    "width fractional": (_set(("intrinsics", "width"), 32.5), "intrinsics.width must be a positive integer, got 32.5"),
    "fx a string": (_set(("intrinsics", "fx"), "16"), "intrinsics.fx must be a positive finite number, got '16'"),
    "cy missing": (lambda data: data["intrinsics"].pop("cy"), "intrinsics.cy is missing"),
}

runner = CliRunner()


def _one_line(exc_info: pytest.ExceptionInfo) -> str:
    message = str(exc_info.value)
    assert "\n" not in message
    return message


def _assert_one_line_cli_error(result, contains: str) -> str:
    """Exit code 2, exactly one `error:` line on stderr, no traceback (as tests/test_cli.py's helper)."""
    assert isinstance(result.exception, SystemExit), f"uncaught {result.exception!r}"
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and contains in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def sequence(tmp_path: Path) -> Path:
    path = tmp_path / "seq"
    write_sequence(path, make_meta(), make_frames(3))
    return path


def _edit_meta(folder: Path, edit: Callable[[dict], None]) -> None:
    meta_file = folder / "sequence.json"
    data = json.loads(meta_file.read_text())
    edit(data)
    meta_file.write_text(json.dumps(data, allow_nan=True))


# ------------------------------------------------------------------------------------------ camera model


@pytest.mark.parametrize("case", BAD_CAMERAS)
def test_reading_a_camera_that_is_no_camera_is_a_format_error(sequence: Path, case: str) -> None:
    edit, field = BAD_CAMERAS[case]
    _edit_meta(sequence, edit)
    with pytest.raises(FormatError) as exc_info:
        read_sequence(sequence)
    assert _one_line(exc_info).startswith(f"{sequence / 'sequence.json'}: ")
    assert field in str(exc_info.value)


WRITE_CASES = {
    "mount NaN": (lambda m: dataclasses.replace(m, T_base_camera=np.full((4, 4), np.nan)), "must be finite"),
    "mount all zeros": (lambda m: dataclasses.replace(m, T_base_camera=np.zeros((4, 4))), "is not a rotation"),
    "cx NaN": (
        lambda m: dataclasses.replace(m, intrinsics=dataclasses.replace(m.intrinsics, cx=float("nan"))),
        "intrinsics.cx must be a finite number, got nan",
    ),
    "fx = fy = 0": (
        lambda m: dataclasses.replace(m, intrinsics=dataclasses.replace(m.intrinsics, fx=0.0, fy=0.0)),
        "intrinsics.fx must be a positive finite number, got 0.0",
    ),
    "negative fx": (
        lambda m: dataclasses.replace(m, intrinsics=dataclasses.replace(m.intrinsics, fx=-3.0)),
        "intrinsics.fx must be a positive finite number, got -3.0",
    ),
}


@pytest.mark.parametrize("case", WRITE_CASES)
def test_writing_a_camera_that_is_no_camera_is_refused(tmp_path: Path, case: str) -> None:
    change, field = WRITE_CASES[case]
    with pytest.raises(InputError, match="sequence 'synthetic': ") as exc_info:
        write_sequence(tmp_path / "seq", change(make_meta()), make_frames(2))
    assert field in _one_line(exc_info)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_a_rigid_mount_within_the_tolerance_passes() -> None:
    K = CameraIntrinsics(32, 24, 16.0, 16.0, 15.5, 11.5)
    typed = np.round(level_camera_mount(0.5) @ _rotation_z(0.3), 4)  # a rotation typed with four decimals
    assert camera_problem(K, typed) is None
    assert camera_problem(K, level_camera_mount()) is None
    assert "intrinsics.fx" in camera_problem(dataclasses.replace(K, fx=0.0), typed)


def _rotation_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return T


def test_localize_refuses_a_bad_camera_in_one_line(sequence: Path, tmp_path: Path, cli_config_args: list[str]) -> None:
    from tests.localization.handmade import make_prior

    make_prior().save(tmp_path / "prior")
    _edit_meta(sequence, _both(_set(("intrinsics", "fx"), 0), _set(("intrinsics", "fy"), 0)))
    result = runner.invoke(
        app, ["localize", str(tmp_path / "prior"), str(sequence), "-o", str(tmp_path / "run"), *cli_config_args]
    )
    _assert_one_line_cli_error(result, "sequence.json: intrinsics.fx must be a positive finite number, got 0")
    assert not (tmp_path / "run").exists()


def test_the_tum_and_rosbag_readers_check_a_camera_passed_in(tmp_path: Path, test_config) -> None:
    from bimfactor.io.tum_rgbd import read_tum_rgbd
    from tests.io.test_tum import H, W, _write_tum_folder

    _write_tum_folder(tmp_path / "tum")
    bad = CameraIntrinsics(W, H, 25.0, 25.0, float("nan"), 11.5)
    with pytest.raises(InputError, match=r"tum: intrinsics\.cx must be a finite number, got nan"):
        read_tum_rgbd(tmp_path / "tum", max_sync_dt_s=0.02, intrinsics=bad)
    with pytest.raises(InputError, match="T_base_camera's rotation part is not a rotation"):
        read_tum_rgbd(tmp_path / "tum", max_sync_dt_s=0.02, T_base_camera=np.zeros((4, 4)))

    pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")
    from bimfactor.io.rosbag import read_rosbag
    from tests.io.test_rosbag import _write_bag

    config = test_config.io.rosbag
    _write_bag(tmp_path / "bag", "16UC1")
    with pytest.raises(InputError, match=r"bag: intrinsics\.fx must be a positive finite number, got -25\.0"):
        read_rosbag(tmp_path / "bag", config, intrinsics=CameraIntrinsics(W, H, -25.0, 25.0, 15.5, 11.5))
    with pytest.raises(InputError, match="T_base_camera must be finite"):
        read_rosbag(tmp_path / "bag", config, T_base_camera=np.full((4, 4), np.nan))


# ------------------------------------------------------------------------------------------ corrupt PNG


def _damage_idat(png: Path, *, fix_crc: bool) -> None:
    """Flip bytes inside the first IDAT chunk's compressed data; with `fix_crc` its CRC is recomputed so that only
    the decoder itself can tell (libpng: "IDAT: incorrect data check" and the like)."""
    data = bytearray(png.read_bytes())
    at = data.find(b"IDAT")
    length = struct.unpack(">I", data[at - 4 : at])[0]
    for k in range(4, min(length, 40), 3):
        data[at + 4 + k] ^= 0x5A
    if fix_crc:
        data[at + 4 + length : at + 8 + length] = struct.pack(">I", zlib.crc32(bytes(data[at : at + 4 + length])))
    png.write_bytes(bytes(data))


@pytest.mark.parametrize("fix_crc", [False, True], ids=["bad CRC", "valid CRC"])
def test_a_corrupt_png_is_one_error_and_nothing_on_stderr(
    sequence: Path, fix_crc: bool, capfd: pytest.CaptureFixture
) -> None:
    png = sequence / "rgb" / "000001.png"
    _damage_idat(png, fix_crc=fix_crc)
    seq = read_sequence(sequence)
    capfd.readouterr()
    with pytest.raises(FormatError, match=r"rgb/000001\.png: corrupt PNG \(") as exc_info:
        seq[1]
    message = _one_line(exc_info)
    assert ("CRC mismatch in the IDAT chunk" in message) != fix_crc
    out, err = capfd.readouterr()
    assert err == "" and out == ""  # libpng's own line was caught, not printed
    np.testing.assert_array_equal(decode_png(sequence / "rgb" / "000000.png", channels=3, dtype=np.uint8).shape,
                                  (24, 32, 3))  # fmt: skip


def test_a_corrupt_png_in_a_real_process_is_one_stderr_line(sequence: Path, tmp_path: Path) -> None:
    _damage_idat(sequence / "depth" / "000000.png", fix_crc=True)  # passes the CRC check: libpng itself fails
    proc = subprocess.run(
        [sys.executable, "-m", "bimfactor", "convert", "sequence", str(sequence), "-o", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"error: {sequence / 'depth' / '000000.png'}: corrupt PNG (")
    assert "libpng" not in proc.stderr


# ------------------------------------------------------------------------------------------ frames.csv


def test_a_byte_order_mark_before_the_header_is_accepted(sequence: Path) -> None:
    frames_file = sequence / "frames.csv"
    plain = read_sequence(sequence)
    frames_file.write_bytes(b"\xef\xbb\xbf" + frames_file.read_bytes())
    with_bom = read_sequence(sequence)
    assert len(with_bom) == len(plain) == 3
    np.testing.assert_array_equal(with_bom.indices(), plain.indices())
    np.testing.assert_array_equal(with_bom.timestamps(), plain.timestamps())
    np.testing.assert_array_equal(with_bom.odometry(), plain.odometry())
    np.testing.assert_array_equal(with_bom[2].rgb, plain[2].rgb)


# ------------------------------------------------------------------------------------------ ROS 2 bags


def test_a_folder_that_is_not_a_bag_says_what_a_bag_is(tmp_path: Path, test_config) -> None:
    pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")
    from bimfactor.io.rosbag import read_rosbag

    config = test_config.io.rosbag
    folder = tmp_path / "recording"
    folder.mkdir()
    (folder / "notes.txt").write_text("not a bag\n")
    with pytest.raises(InputError) as exc_info:
        read_rosbag(folder, config)
    assert _one_line(exc_info) == (
        f"{folder}: not a readable ROS 2 bag: the folder has no metadata.yaml (a ROS 2 bag is a folder with "
        "metadata.yaml, or a .db3 or .mcap file)"
    )
    (folder / "run.bag").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(InputError, match=r"holds a ROS 1 bag \(run\.bag\); open that file instead"):
        read_rosbag(folder, config)
    with pytest.raises(InputError, match=r"notes\.txt: not a readable ROS 2 bag: a \.txt file; expected a bag folder"):
        read_rosbag(folder / "notes.txt", config)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")  # YAML errors span several lines
    with pytest.raises(InputError, match="not a readable ROS 2 bag") as exc_info:
        read_rosbag(broken, config)
    _one_line(exc_info)
