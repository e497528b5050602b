"""TUM RGB-D benchmark folders as a `Sequence`.

`read_tum_rgbd` pairs each colour image of a TUM folder (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)
with the depth image nearest in time (one-to-one, within `max_sync_dt_s`, as the benchmark's associate.py) and with
the nearest ground-truth pose, made a planar base pose: T_world_base = T_world_camera · T_base_camera⁻¹, projected.
TUM has no wheel odometry, and none is made up from the ground truth: `odometry()` is None. Intrinsics, unless
passed in: the benchmark's calibration of the camera the folder's name says (freiburg1/2/3; distortion ignored),
else the ROS default 525, 525, 319.5, 239.5.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from bimfactor.errors import FormatError, InputError
from bimfactor.io.sequence import (
    FrameImages,
    Sequence,
    associate_nearest,
    camera_problem,
    decode_png,
    depth_from_mm,
    level_camera_mount,
)
from bimfactor.io.tum import MAX_TILT_DEG, planar_from_matrices, read_tum_poses
from bimfactor.types import CameraIntrinsics, SequenceMeta

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE_PER_M = 5000
TUM_IMAGE_SIZE = (640, 480)
# fx, fy, cx, cy of the benchmark's colour cameras, and the ROS default it recommends for registered depth
TUM_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
TUM_ROS_DEFAULT = (525.0, 525.0, 319.5, 239.5)


def tum_default_intrinsics(dataset_name: str) -> CameraIntrinsics:
    """The intrinsics `read_tum_rgbd` assumes for a folder of this name (see the module docstring)."""
    fx, fy, cx, cy = next((v for k, v in TUM_CAMERAS.items() if k in dataset_name), TUM_ROS_DEFAULT)
    return CameraIntrinsics(*TUM_IMAGE_SIZE, fx, fy, cx, cy)


def tum_image_size(folder: str | Path) -> tuple[int, int] | None:
    """(width, height) of a TUM folder's first colour image, from its PNG header; None when it cannot be read."""
    folder = Path(folder)
    try:
        _, files = _read_file_list(folder, "rgb.txt")
        header = files[0].read_bytes()[:24] if len(files) else b""
    except (OSError, InputError, FormatError):
        return None
    if len(header) < 24 or header[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")


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
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"no such TUM RGB-D folder: {folder}")
    missing = [name for name in ("rgb.txt", "depth.txt") if not (folder / name).is_file()]
    if missing:
        raise FormatError(f"{folder}: not a TUM RGB-D folder ({', '.join(missing)} missing)")
    rgb_times, rgb_files = _read_file_list(folder, "rgb.txt")
    depth_times, depth_files = _read_file_list(folder, "depth.txt")
    intrinsics = intrinsics or tum_default_intrinsics(folder.name)
    T_base_camera = level_camera_mount() if T_base_camera is None else np.asarray(T_base_camera, dtype=float)
    problem = camera_problem(intrinsics, T_base_camera)
    if problem:
        raise InputError(f"{folder}: {problem}")

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


def tum_camera_poses(folder: str | Path, timestamps_s: np.ndarray, max_sync_dt_s: float) -> np.ndarray:
    """(N, 4, 4) T_world_camera of the frames stamped `timestamps_s`: the folder's groundtruth.txt pose nearest in
    time (within `max_sync_dt_s`; NaN where none is). The full 6-DoF pose, as the motion capture gave it.
    InputError when the folder has no groundtruth.txt."""
    gt_file = Path(folder) / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(f"{folder}: no groundtruth.txt (the camera poses a scene graph is built from)")
    gt_times, T_world_camera = read_tum_poses(gt_file)
    i_frame, i_gt = associate_nearest(np.asarray(timestamps_s, float), gt_times, max_sync_dt_s, one_to_one=False)
    poses = np.full((len(timestamps_s), 4, 4), np.nan)
    poses[i_frame] = T_world_camera[i_gt]
    return poses
