"""TUM trajectory files: planar trajectories as TUM text files.

One pose per line, `timestamp tx ty tz qx qy qz qw` (seconds, metres, unit quaternion), "#" comments. Planar poses
(x, y, yaw) are written with z = 0 and a rotation about z; reading projects any 3D pose onto the plane, warning when
roll or pitch exceed `MAX_TILT_DEG`.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from bimfactor.errors import FormatError, InputError
from bimfactor.io.atomic import write_text_atomic
from bimfactor.types import wrap_angle

log = logging.getLogger(__name__)

MAX_TILT_DEG = 3.0
_HEADER = "# timestamp tx ty tz qx qy qz qw"


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
