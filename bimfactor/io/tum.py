"""TUM formats: planar trajectories as TUM text files, and TUM RGB-D benchmark folders as a `Sequence`.

A TUM trajectory file has one pose per line, `timestamp tx ty tz qx qy qz qw` (seconds, metres, unit
quaternion), and comment lines starting with "#". Planar poses (x, y, yaw) are written with z = 0 and a
rotation about z; reading accepts any 3D pose and projects it onto the plane (x, y and the heading of the
pose's x-axis), with a logged warning when roll or pitch exceed `MAX_TILT_DEG`.

A TUM RGB-D folder (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats) holds `rgb.txt` and
`depth.txt` (`timestamp filename` per line), 640×480 8-bit colour PNGs, 16-bit depth PNGs at 5000 units per
metre (0 = no data), and usually `groundtruth.txt`: the pose of the colour camera's optical centre in the
motion-capture frame. `accelerometer.txt` is ignored. `read_tum_rgbd` pairs each colour image with the depth
image nearest in time (one-to-one, within `max_sync_dt_s`, as the benchmark's associate.py) and with the
ground-truth pose nearest in time (within the same limit; frames without one have unknown ground truth).
Ground truth becomes a planar base pose: T_world_base = T_world_camera · T_base_camera⁻¹, projected.

TUM has no wheel odometry: the returned sequence's `odometry()` is None and `Frame.odom_pose` is NaN.
Deriving odometry from ground truth would hide the drift a localizer must cope with, so it is never done.

Intrinsics, unless passed in: the folder name's camera ("freiburg1", "freiburg2", "freiburg3") selects the
benchmark's published colour-camera calibration for that sensor (fx, fy, cx, cy; distortion terms are ignored,
which is exact for freiburg3, whose published distortion is zero, and an approximation for freiburg1/2); any other
name gets the "ROS default" set 525, 525, 319.5, 239.5 that TUM recommends for the pre-registered depth. Pass
`intrinsics` to choose otherwise (e.g. the ROS default for freiburg1/2 too).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bimfactor.errors import FormatError, InputError
from bimfactor.io.atomic import write_text_atomic
from bimfactor.types import CameraIntrinsics, wrap_angle

if TYPE_CHECKING:
    from bimfactor.io.sequence import Sequence

log = logging.getLogger(__name__)

MAX_TILT_DEG = 3.0
TUM_DEPTH_SCALE_PER_M = 5000
TUM_IMAGE_SIZE = (640, 480)
# fx, fy, cx, cy of the benchmark's colour cameras, and the ROS default it recommends for registered depth
TUM_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
TUM_ROS_DEFAULT = (525.0, 525.0, 319.5, 239.5)
_HEADER = "# timestamp tx ty tz qx qy qz qw"


# ------------------------------------------------------------------------------------------ trajectories


def format_tum_trajectory(timestamps_s: np.ndarray, poses: np.ndarray, comment: str = "") -> str:
    """TUM text for (N,) timestamps and (N, 3) planar poses; numbers as Python's shortest exact repr."""
    timestamps_s, poses = _checked_trajectory(timestamps_s, poses)
    lines = [_HEADER] + ([f"# {comment}"] if comment else [])
    for t, (x, y, yaw) in zip(timestamps_s.tolist(), poses.tolist(), strict=True):  # Python floats: exact repr
        qz, qw = math.sin(yaw / 2), math.cos(yaw / 2)
        lines.append(f"{t!r} {x!r} {y!r} 0.0 0.0 0.0 {qz!r} {qw!r}")
    return "\n".join(lines) + "\n"


def write_tum_trajectory(path: str | Path, timestamps_s: np.ndarray, poses: np.ndarray, comment: str = "") -> None:
    """Write (N,) timestamps and (N, 3) x, y, yaw poses as a TUM trajectory file, atomically."""
    write_text_atomic(path, format_tum_trajectory(timestamps_s, poses, comment))


def read_tum_trajectory(path: str | Path, *, max_tilt_deg: float = MAX_TILT_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory as (N,) timestamps and (N, 3) planar poses x, y, yaw (yaw in [-π, π))."""
    timestamps, T = read_tum_poses(path)
    return timestamps, planar_from_matrices(T, what=str(path), max_tilt_deg=max_tilt_deg)


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory as (N,) timestamps and (N, 4, 4) homogeneous poses.

    Timestamps must be strictly increasing; any malformed line is a FormatError naming the line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: unreadable ({exc})") from None
    rows: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise FormatError(f"{path} line {number}: {len(fields)} fields, expected 8 ({_HEADER[2:]})")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise FormatError(f"{path} line {number}: not a number in {line!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise FormatError(f"{path} line {number}: non-finite value")
        if math.sqrt(sum(v * v for v in values[4:])) < 1e-9:
            raise FormatError(f"{path} line {number}: zero quaternion")
        if rows and values[0] <= rows[-1][0]:
            raise FormatError(f"{path} line {number}: timestamp {fields[0]} is not after the previous pose's")
        rows.append(values)
    if not rows:
        raise FormatError(f"{path}: no poses")
    data = np.array(rows)
    T = np.tile(np.eye(4), (len(data), 1, 1))
    T[:, :3, :3] = quaternion_to_matrix(data[:, 4:8])
    T[:, :3, 3] = data[:, 1:4]
    return data[:, 0], T


def quaternion_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions x, y, z, w (normalised here) → (N, 3, 3) rotation matrices."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def planar_from_matrices(T: np.ndarray, *, what: str, max_tilt_deg: float = MAX_TILT_DEG) -> np.ndarray:
    """(N, 4, 4) poses → (N, 3) x, y, yaw; logs a warning naming `what` when any tilt exceeds `max_tilt_deg`."""
    T = np.asarray(T, dtype=np.float64)
    tilt_deg = np.rad2deg(np.arccos(np.clip(T[:, 2, 2], -1.0, 1.0)))
    if len(T) and tilt_deg.max() > max_tilt_deg:
        log.warning(
            "%s: roll/pitch up to %.1f° (%d of %d poses above %.1f°) dropped by the planar projection",
            what,
            tilt_deg.max(),
            int((tilt_deg > max_tilt_deg).sum()),
            len(T),
            max_tilt_deg,
        )
    yaw = wrap_angle(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    return np.stack([T[:, 0, 3], T[:, 1, 3], yaw], axis=-1)


def _checked_trajectory(timestamps_s: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if timestamps_s.ndim != 1 or poses.shape != (len(timestamps_s), 3):
        raise InputError(f"trajectory: timestamps {timestamps_s.shape} and poses {poses.shape} must be (N,), (N, 3)")
    if not (np.isfinite(timestamps_s).all() and np.isfinite(poses).all()):
        raise InputError("trajectory: timestamps and poses must be finite")
    return timestamps_s, poses


# ------------------------------------------------------------------------------------------ RGB-D folders


def tum_default_intrinsics(dataset_name: str) -> CameraIntrinsics:
    """The intrinsics `read_tum_rgbd` assumes for a folder of this name (see the module docstring)."""
    fx, fy, cx, cy = next((v for k, v in TUM_CAMERAS.items() if k in dataset_name), TUM_ROS_DEFAULT)
    return CameraIntrinsics(*TUM_IMAGE_SIZE, fx, fy, cx, cy)


def read_tum_rgbd(
    folder: str | Path,
    *,
    max_sync_dt_s: float,
    intrinsics: CameraIntrinsics | None = None,
    T_base_camera: np.ndarray | None = None,
    max_tilt_deg: float = MAX_TILT_DEG,
) -> Sequence:
    """Open a TUM RGB-D benchmark folder as a `Sequence` (images load on access; `odometry()` is None).

    `T_base_camera` (4, 4) defaults to a level camera at the base origin (`level_camera_mount()`);
    `max_sync_dt_s` is the config's `io.tum_max_sync_dt_s`.
    """
    # imported here: the sequence format itself writes TUM trajectories with this module
    from bimfactor.io.sequence import (
        FrameImages,
        Sequence,
        associate_nearest,
        camera_problem,
        decode_png,
        depth_from_mm,
        level_camera_mount,
    )
    from bimfactor.types import SequenceMeta

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"no such TUM RGB-D folder: {folder}")
    missing = [name for name in ("rgb.txt", "depth.txt") if not (folder / name).is_file()]
    if missing:
        raise FormatError(f"{folder}: not a TUM RGB-D folder ({', '.join(missing)} missing)")
    rgb_times, rgb_files = _read_file_list(folder, "rgb.txt")
    depth_times, depth_files = _read_file_list(folder, "depth.txt")
    intrinsics = intrinsics or tum_default_intrinsics(folder.name)
    problem = camera_problem(intrinsics, level_camera_mount() if T_base_camera is None else T_base_camera)
    if problem:
        raise InputError(f"{folder}: {problem}")
    T_base_camera = level_camera_mount() if T_base_camera is None else np.asarray(T_base_camera, dtype=float)

    i_rgb, i_depth = associate_nearest(rgb_times, depth_times, max_sync_dt_s, one_to_one=True)
    if len(i_rgb) == 0:
        raise InputError(f"{folder}: no colour image has a depth image within {max_sync_dt_s} s")
    if len(i_rgb) < len(rgb_times):
        log.info(
            "%s: %d of %d colour images have no depth within %s s",
            folder,
            len(rgb_times) - len(i_rgb),
            len(rgb_times),
            max_sync_dt_s,
        )
    timestamps = rgb_times[i_rgb]

    gt = None
    gt_file = folder / "groundtruth.txt"
    if gt_file.is_file():
        gt_times, T_world_camera = read_tum_poses(gt_file)
        T_world_base = T_world_camera @ np.linalg.inv(T_base_camera)
        gt_planar = planar_from_matrices(T_world_base, what=str(gt_file), max_tilt_deg=max_tilt_deg)
        i_frame, i_gt = associate_nearest(timestamps, gt_times, max_sync_dt_s, one_to_one=False)
        gt = np.full((len(timestamps), 3), np.nan)
        gt[i_frame] = gt_planar[i_gt]
        if len(i_frame) < len(timestamps):
            log.info(
                "%s: %d of %d frames have no ground truth within %s s",
                folder,
                len(timestamps) - len(i_frame),
                len(timestamps),
                max_sync_dt_s,
            )
    else:
        log.info("%s: no groundtruth.txt; ground truth unknown", folder)

    files = [(rgb_files[a], depth_files[b]) for a, b in zip(i_rgb, i_depth, strict=True)]
    for pair in files:
        for path in pair:
            if not path.is_file():
                raise FormatError(f"{folder}: frame file missing: {path}")
    size = (intrinsics.width, intrinsics.height)

    def load_images(i: int) -> FrameImages:
        rgb = decode_png(files[i][0], channels=3, dtype=np.uint8, size=size)
        depth = decode_png(files[i][1], channels=1, dtype=np.uint16, size=size)
        return FrameImages(rgb, depth_from_mm(depth, TUM_DEPTH_SCALE_PER_M), None)

    meta = SequenceMeta(
        name=folder.name,
        source="tum",
        intrinsics=intrinsics,
        T_base_camera=T_base_camera,
        extras={"tum_folder": str(folder), "ground_truth_frame": "TUM motion-capture frame"},
    )
    return Sequence(meta, timestamps, load_images, gt_poses=gt)


def _read_file_list(folder: Path, name: str) -> tuple[np.ndarray, list[Path]]:
    """`timestamp filename` lines of rgb.txt / depth.txt → (N,) times and paths; strictly increasing times."""
    path = folder / name
    times: list[float] = []
    files: list[Path] = []
    for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 2:
            raise FormatError(f"{path} line {number}: {len(fields)} fields, expected 2 (timestamp filename)")
        try:
            t = float(fields[0])
        except ValueError:
            raise FormatError(f"{path} line {number}: timestamp {fields[0]!r} is not a number") from None
        if not math.isfinite(t) or (times and t <= times[-1]):
            raise FormatError(f"{path} line {number}: timestamp {fields[0]} is not after the previous line's")
        relative = Path(fields[1])
        if relative.is_absolute() or ".." in relative.parts:
            raise FormatError(f"{path} line {number}: {fields[1]!r} is not a path inside {folder}")
        times.append(t)
        files.append(folder / relative)
    if not times:
        raise FormatError(f"{path}: no images listed")
    return np.array(times), files
