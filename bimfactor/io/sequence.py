"""The bimfactor sequence format: RGB-D frames with odometry and ground truth, one folder per sequence.

`write_sequence` writes it atomically, `read_sequence` opens it as a `Sequence` whose images load on access, and
`Sequence.from_frames` wraps frames already in memory. The format and its error contract: docs/sequences.md.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
import math
import os
import sys
import tempfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np

from bimfactor.errors import FormatError, InputError
from bimfactor.io.atomic import output_dir
from bimfactor.io.tum import format_tum_trajectory
from bimfactor.progress import progress
from bimfactor.types import STOREY_CHANGE, CameraIntrinsics, Frame, SequenceMeta

log = logging.getLogger(__name__)

SEQUENCE_FORMAT = "bimfactor-sequence"
SEQUENCE_VERSION = 1
DEPTH_UNIT = "millimetre"
DEPTH_SCALE_PER_M = 1000
MAX_DEPTH_MM = 65535
MAX_INSTANCE_ID = 65534  # stored as id + 1 in a uint16
FRAME_COLUMNS = (
    "index",
    "timestamp_s",
    "rgb",
    "depth",
    "instances",
    "odom_x",
    "odom_y",
    "odom_yaw",
    "gt_x",
    "gt_y",
    "gt_yaw",
    "gt_storey",
)
EXTRA_PREFIX = "extra."
META_FILE = "sequence.json"
FRAMES_FILE = "frames.csv"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk type and its CRC close every complete PNG


class FrameImages(NamedTuple):
    """The images of one frame: (H, W, 3) uint8 RGB, (H, W) float32 depth (NaN = no return), (H, W) int32 ids."""

    rgb: np.ndarray
    depth_m: np.ndarray
    instance_ids: np.ndarray | None


# ------------------------------------------------------------------------------------------ the interface


class Sequence:
    """Frames of one recording: the per-frame table held in memory, the images loaded on access.

    `load_images(i)` returns the images of row `i`. `odom_poses` (N, 3) T_odom_base or None when the source has
    no odometry (then `Frame.odom_pose` is NaN); `gt_poses` (N, 3) T_world_base with NaN rows where ground
    truth is unknown, or None when none is known.
    """

    def __init__(
        self,
        meta: SequenceMeta,
        timestamps_s: np.ndarray,
        load_images: Callable[[int], FrameImages],
        *,
        indices: np.ndarray | None = None,
        odom_poses: np.ndarray | None = None,
        gt_poses: np.ndarray | None = None,
        gt_storeys: list[int | None] | None = None,
        frame_extras: list[dict[str, float]] | None = None,
    ) -> None:
        n = len(timestamps_s)
        self.meta = meta
        self._timestamps = np.asarray(timestamps_s, dtype=np.float64).reshape(n)
        self._load_images = load_images
        self._indices = np.arange(n) if indices is None else np.asarray(indices, dtype=np.int64).reshape(n)
        self._odom = None if odom_poses is None else np.asarray(odom_poses, dtype=np.float64).reshape(n, 3)
        self._gt = None if gt_poses is None else np.asarray(gt_poses, dtype=np.float64).reshape(n, 3)
        if self._gt is not None and np.isnan(self._gt).all():
            self._gt = None
        self._gt_storeys = [None] * n if gt_storeys is None else list(gt_storeys)
        self._extras = [{} for _ in range(n)] if frame_extras is None else [dict(e) for e in frame_extras]
        if len(self._gt_storeys) != n or len(self._extras) != n:
            raise ValueError("per-frame lists must have one entry per timestamp")

    @classmethod
    def from_frames(cls, meta: SequenceMeta, frames: Iterable[Frame]) -> Sequence:
        """An in-memory sequence over already loaded frames (e.g. straight from the simulator)."""
        frames = list(frames)
        odom = np.array([np.asarray(f.odom_pose, dtype=np.float64) for f in frames]).reshape(len(frames), 3)
        gt = np.array([np.full(3, np.nan) if f.gt_pose is None else f.gt_pose for f in frames], dtype=np.float64)
        return cls(
            meta,
            np.array([f.timestamp_s for f in frames], dtype=np.float64),
            lambda i: FrameImages(frames[i].rgb, frames[i].depth_m, frames[i].instance_ids),
            indices=np.array([f.index for f in frames], dtype=np.int64),
            odom_poses=None if np.isnan(odom).all() else odom,
            gt_poses=gt.reshape(len(frames), 3),
            gt_storeys=[f.gt_storey for f in frames],
            frame_extras=[f.extras for f in frames],
        )

    def with_odometry(self, odom_poses: np.ndarray, extras: dict[str, Any] | None = None) -> Sequence:
        """This sequence with (N, 3) odometry T_odom_base (e.g. computed from its frames) and `meta.extras` updated
        by `extras`; ground truth and images as they were."""
        from dataclasses import replace

        odom_poses = np.asarray(odom_poses, dtype=np.float64)
        if odom_poses.shape != (len(self), 3) or not np.isfinite(odom_poses).all():
            raise ValueError(f"odometry must be {len(self)} finite x, y, yaw rows, got shape {odom_poses.shape}")

        meta = replace(self.meta, extras={**self.meta.extras, **(extras or {})})
        return Sequence(
            meta,
            self._timestamps,
            self._load_images,
            indices=self._indices,
            odom_poses=odom_poses,
            gt_poses=self._gt,
            gt_storeys=self._gt_storeys,
            frame_extras=self._extras,
        )

    def subset(self, rows: np.ndarray) -> Sequence:
        """The frames at increasing `rows` of this sequence (e.g. its keyframes), keeping their frame indices;
        images are still loaded on access. A storey change (`STOREY_CHANGE`) on a frame left out goes to the next
        frame kept."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        if len(rows) and (rows[0] < 0 or rows[-1] >= len(self) or np.any(np.diff(rows) <= 0)):
            raise ValueError(f"rows must increase within 0 … {len(self) - 1}")
        extras = [dict(self._extras[r]) for r in rows]
        changes = np.cumsum([0.0] + [e.get(STOREY_CHANGE, 0.0) for e in self._extras])
        for k, (before, row) in enumerate(zip([-1, *rows[:-1]], rows, strict=True)):
            change = changes[row + 1] - changes[before + 1]
            if change:
                extras[k][STOREY_CHANGE] = float(change)
        return Sequence(
            self.meta,
            self._timestamps[rows],
            lambda i: self._load_images(int(rows[i])),
            indices=self._indices[rows],
            odom_poses=None if self._odom is None else self._odom[rows],
            gt_poses=None if self._gt is None else self._gt[rows],
            gt_storeys=[self._gt_storeys[r] for r in rows],
            frame_extras=extras,
        )

    def __len__(self) -> int:
        return len(self._timestamps)

    def __getitem__(self, i: int) -> Frame:
        i = self._position(i)
        return self._frame(i, self._load_images(i))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.meta.name!r}, source={self.meta.source!r}, frames={len(self)})"

    def timestamps(self) -> np.ndarray:
        """(N,) frame times in seconds, strictly increasing."""
        return self._timestamps.copy()

    def odometry(self) -> np.ndarray | None:
        """(N, 3) T_odom_base as x, y, yaw; None when the source has no odometry."""
        return None if self._odom is None else self._odom.copy()

    def ground_truth(self) -> np.ndarray | None:
        """(N, 3) T_world_base as x, y, yaw with NaN rows where unknown; None when no frame has ground truth."""
        return None if self._gt is None else self._gt.copy()

    def indices(self) -> np.ndarray:
        """(N,) each frame's index (as in the source stream)."""
        return self._indices.copy()

    def ground_truth_storeys(self) -> list[int | None]:
        """Storey index of each frame's ground truth, None where unknown."""
        return list(self._gt_storeys)

    def _position(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for a sequence of {n} frames")
        return i % n

    def _frame(self, i: int, images: FrameImages) -> Frame:
        gt = None if self._gt is None or np.isnan(self._gt[i]).any() else self._gt[i].copy()
        return Frame(
            index=int(self._indices[i]),
            timestamp_s=float(self._timestamps[i]),
            rgb=images.rgb,
            depth_m=images.depth_m,
            odom_pose=np.full(3, np.nan) if self._odom is None else self._odom[i].copy(),
            gt_pose=gt,
            gt_storey=self._gt_storeys[i],
            instance_ids=images.instance_ids,
            extras=dict(self._extras[i]),
        )


# ------------------------------------------------------------------------------------------ helpers


def quantize_depth_m(depth_m: np.ndarray) -> np.ndarray:
    """Depth as it reads back after a write: millimetre steps, float32, NaN for no return (0 or > 65.535 m)."""
    return depth_from_mm(_depth_to_mm(np.asarray(depth_m))[0])


def depth_from_mm(depth_mm: np.ndarray, scale_per_m: int = DEPTH_SCALE_PER_M) -> np.ndarray:
    """uint16 depth in 1/scale_per_m metres → float32 metres with 0 → NaN."""
    depth_m = depth_mm.astype(np.float32) / np.float32(scale_per_m)
    depth_m[depth_mm == 0] = np.nan
    return depth_m


def _depth_to_mm(depth_m: np.ndarray) -> tuple[np.ndarray, int]:
    """float depth → uint16 millimetres and the count of pixels clamped to no return. Negative → ValueError."""
    depth = np.asarray(depth_m, dtype=np.float64)
    if (depth < 0).any():  # NaN compares False
        raise ValueError(f"negative depth ({np.nanmin(depth)!r} m)")
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.rint(depth * DEPTH_SCALE_PER_M)
    too_far = mm > MAX_DEPTH_MM
    mm[np.isnan(mm) | too_far] = 0
    return mm.astype(np.uint16), int(too_far.sum())


def associate_nearest(
    t_query: np.ndarray, t_ref: np.ndarray, max_dt_s: float, one_to_one: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Pair two sorted time series by nearest timestamp within `max_dt_s`.

    Returns (iq, ir): indices into `t_query` and `t_ref`, sorted by iq. With `one_to_one` each reference is
    used at most once, the closest pairs first (as the TUM benchmark's associate.py does); without it every
    query takes its nearest reference.
    """
    t_query, t_ref = np.asarray(t_query, float), np.asarray(t_ref, float)
    if len(t_query) == 0 or len(t_ref) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    if not one_to_one:
        right = np.clip(np.searchsorted(t_ref, t_query), 0, len(t_ref) - 1)
        left = np.clip(right - 1, 0, len(t_ref) - 1)
        nearest = np.where(np.abs(t_ref[left] - t_query) <= np.abs(t_ref[right] - t_query), left, right)
        keep = np.abs(t_ref[nearest] - t_query) <= max_dt_s
        return np.flatnonzero(keep), nearest[keep]
    # every candidate pair within max_dt, then greedily the closest pairs first
    lo = np.searchsorted(t_ref, t_query - max_dt_s, side="left")
    hi = np.searchsorted(t_ref, t_query + max_dt_s, side="right")
    pairs_q = np.repeat(np.arange(len(t_query)), hi - lo)
    pairs_r = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)]).astype(int)
    dt = np.abs(t_query[pairs_q] - t_ref[pairs_r])
    matched: dict[int, int] = {}
    used_r: set[int] = set()
    for k in np.argsort(dt, kind="stable"):
        q, r = int(pairs_q[k]), int(pairs_r[k])
        if q not in matched and r not in used_r:
            matched[q] = r
            used_r.add(r)
    iq = np.array(sorted(matched), dtype=int)
    return iq, np.array([matched[q] for q in iq], dtype=int)


def level_camera_mount(height_m: float = 0.0) -> np.ndarray:
    """(4, 4) T_base_camera of a camera looking straight ahead: camera z → base x, x → −y, y → −z."""
    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    T[2, 3] = height_m
    return T


MOUNT_TOLERANCE = 1e-3
"""How far a camera mount may be from rigid: each entry of RᵀR − I, det R − 1 and the last row's difference from
0 0 0 1. A rotation written with four decimals passes; a scaled, sheared or mirrored one does not."""


MIN_FOV_DEG, MAX_FOV_DEG = 10.0, 170.0
"""The field of view a pinhole RGB-D camera's intrinsics may give along each image axis (a Kinect's is 62° × 49°, a
RealSense D435's depth 87° × 58°, an Azure Kinect's wide mode 120°): anything else is a focal length in the wrong
unit (3.6 mm read as 3.6 px gives 178°) or a typo (1e12 px gives 0°)."""


def intrinsics_problem(values: dict[str, Any]) -> str | None:
    """What is wrong with pinhole intrinsics given as {"width", "height", "fx", "fy", "cx", "cy"} (as read from JSON,
    or `dataclasses.asdict` of a `CameraIntrinsics`), e.g. "intrinsics.fx must be a positive finite number, got 0";
    None when they describe a camera: width and height positive integers, fx and fy positive and finite, cx and cy
    finite and in the image, and a field of view along each axis within `MIN_FOV_DEG`–`MAX_FOV_DEG`."""
    if not isinstance(values, dict):
        return f"intrinsics must be an object with width, height, fx, fy, cx, cy, got {values!r}"
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        if key not in values:
            return f"intrinsics.{key} is missing"
        value = values[key]
        value = value.item() if isinstance(value, np.generic) else value
        number = isinstance(value, int | float) and not isinstance(value, bool)
        finite = number and math.isfinite(value)
        if key in ("width", "height"):
            if not finite or value != int(value) or value < 1:
                return f"intrinsics.{key} must be a positive integer, got {value!r}"
        elif key in ("fx", "fy"):
            if not finite or value <= 0:
                return f"intrinsics.{key} must be a positive finite number, got {value!r}"
        elif not finite:
            return f"intrinsics.{key} must be a finite number, got {value!r}"
    w, h, cx, cy = (values[k] for k in ("width", "height", "cx", "cy"))
    if not (0 <= cx <= w and 0 <= cy <= h):
        return f"intrinsics: the principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} image"
    for key, side in (("fx", w), ("fy", h)):
        fov = math.degrees(2 * math.atan(side / (2 * values[key])))
        if not MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
            return (
                f"intrinsics.{key} = {values[key]:g} px gives a {side} px image a field of view of {fov:.3g}°, not a "
                f"camera's ({MIN_FOV_DEG:g}–{MAX_FOV_DEG:g}°; focal lengths are in pixels)"
            )
    return None


def mount_problem(T_base_camera: Any) -> str | None:
    """What is wrong with a camera mount T_base_camera, e.g. "T_base_camera's rotation part is not a rotation"; None
    for a finite 4×4 rigid transform (rotation part orthonormal with determinant +1 and last row 0 0 0 1, both
    within `MOUNT_TOLERANCE`)."""
    try:
        T = np.asarray(T_base_camera, dtype=np.float64)
    except (TypeError, ValueError):
        return "T_base_camera must be a 4x4 matrix of numbers"
    if T.shape != (4, 4):
        return f"T_base_camera must be a 4x4 matrix, got shape {T.shape}"
    if not np.isfinite(T).all():
        row, col = np.argwhere(~np.isfinite(T))[0]
        return f"T_base_camera must be finite, got {float(T[row, col])!r} in row {row}, column {col}"
    R = T[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if off > MOUNT_TOLERANCE or abs(det - 1.0) > MOUNT_TOLERANCE:
        return (
            "T_base_camera's rotation part is not a rotation (it must be orthonormal with determinant +1; "
            f"max |RᵀR − I| = {off:.3g}, det = {det:.3g})"
        )
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > MOUNT_TOLERANCE:
        return f"T_base_camera's last row must be 0 0 0 1, got {' '.join(f'{v:g}' for v in T[3])}"
    return None


def camera_problem(intrinsics: CameraIntrinsics, T_base_camera: Any) -> str | None:
    """`intrinsics_problem` or `mount_problem` of a camera model, the first found; None when it is a camera."""
    return intrinsics_problem(dataclasses.asdict(intrinsics)) or mount_problem(T_base_camera)


def decode_png(path: Path, *, channels: int, dtype: type, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a PNG with `channels` channels of `dtype`; colour comes back as RGB. (W, H) `size` is checked.

    Any failure is a one-line FormatError naming the file. The chunks and their CRCs are checked here first
    (`png_chunk_problem`), so that a damaged file never reaches libpng; what libpng would still print about a file
    that passes (its C code writes to file descriptor 2 itself) is caught and goes into the error, or the debug log.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not data.startswith(_PNG_SIGNATURE):
        raise FormatError(f"{path}: not a PNG file")
    if not data.endswith(_PNG_END):
        raise FormatError(f"{path}: truncated PNG (no closing IEND chunk)")
    problem = png_chunk_problem(data)
    if problem:
        raise FormatError(f"{path}: corrupt PNG ({problem})")
    image, native = _decode_quietly(data)
    if image is None:
        said = next((line.strip() for line in native.splitlines() if line.strip()), "")
        said = said.removeprefix("libpng error:").strip()
        raise FormatError(f"{path}: corrupt PNG ({said or 'cannot be decoded'})")
    if native.strip():
        log.debug("%s: the PNG decoder said: %s", path, " | ".join(native.split("\n")).strip())
    got_channels = 1 if image.ndim == 2 else image.shape[2]
    if got_channels != channels or image.dtype != dtype:
        raise FormatError(
            f"{path}: {got_channels}-channel {image.dtype} image, expected {channels}-channel {np.dtype(dtype)}"
        )
    if size is not None and (image.shape[1], image.shape[0]) != size:
        raise FormatError(f"{path}: image is {image.shape[1]}x{image.shape[0]}, expected {size[0]}x{size[1]}")
    if channels == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


def png_chunk_problem(data: bytes) -> str | None:
    """The first structural fault of a PNG file's bytes after the signature: a chunk that runs past the end, a CRC
    that does not match its chunk, IHDR not first, no IDAT before IEND, no IEND; None when every chunk is sound."""
    view = memoryview(data)
    pos, has_data = len(_PNG_SIGNATURE), False
    while pos + 12 <= len(data):
        length = int.from_bytes(view[pos : pos + 4], "big")
        kind = bytes(view[pos + 4 : pos + 8])
        name = kind.decode("ascii", "replace")
        end = pos + 12 + length
        if end > len(data):
            return f"the {name} chunk at byte {pos} runs past the end of the file"
        if zlib.crc32(view[pos + 4 : end - 4]) != int.from_bytes(view[end - 4 : end], "big"):
            return f"CRC mismatch in the {name} chunk at byte {pos}"
        if pos == len(_PNG_SIGNATURE) and kind != b"IHDR":
            return f"the first chunk is {name}, not IHDR"
        has_data = has_data or kind == b"IDAT"
        if kind == b"IEND":
            return None if has_data else "no IDAT chunk"
        pos = end
    return "no IEND chunk"


def _decode_quietly(data: bytes) -> tuple[np.ndarray | None, str]:
    """`cv2.imdecode` of PNG bytes, with what native code writes to file descriptor 2 meanwhile (libpng's "libpng
    error: ..." lines) caught instead of printed: (image or None, the text caught). While it runs, anything another
    thread writes to stderr is caught too (bimfactor decodes on the thread that reports)."""
    buffer = np.frombuffer(data, np.uint8)
    try:
        if sys.stderr is not None:
            sys.stderr.flush()
        saved = os.dup(2)
    except OSError:  # no file descriptor 2 (a windowed process): nothing can be printed
        return cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED), ""
    with tempfile.TemporaryFile() as sink:
        try:
            os.dup2(sink.fileno(), 2)
            image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        sink.seek(0)
        said = sink.read(4096).decode("utf-8", "replace")
    return image, said


def png_looks_complete(path: Path) -> bool:
    """Cheap structural check: the file exists, starts with the PNG signature and ends with the IEND chunk."""
    try:
        with path.open("rb") as f:
            head = f.read(len(_PNG_SIGNATURE))
            f.seek(0, io.SEEK_END)
            if f.tell() < len(_PNG_SIGNATURE) + len(_PNG_END):
                return False
            f.seek(-len(_PNG_END), io.SEEK_END)
            tail = f.read()
    except OSError:
        return False
    return head == _PNG_SIGNATURE and tail == _PNG_END


def _num(value: float) -> str:
    """Shortest text that reads back to the same float64."""
    return repr(float(value))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


# ------------------------------------------------------------------------------------------ writer


def write_sequence(
    path: str | Path,
    meta: SequenceMeta,
    frames: Iterable[Frame],
    *,
    overwrite: bool = False,
    inputs: Iterable[str | Path] = (),
) -> None:
    """Write `frames` as a sequence folder at `path` (format above); the folder appears only when complete.

    An existing sequence folder is replaced only with `overwrite`; any other non-empty folder, or one that holds an
    input path, is refused (`io.atomic.output_dir`). Raises InputError for frames that cannot be written exactly.
    """
    with output_dir(path, "sequence", inputs=inputs, replace=overwrite) as tmp:
        write_sequence_files(tmp, meta, frames, label=str(path))


def write_sequence_files(folder: Path, meta: SequenceMeta, frames: Iterable[Frame], label: str = "") -> None:
    """Write the sequence's files into the new, empty `folder` (for a command that adds files of its own to the
    same output folder before it appears; `write_sequence` otherwise).

    Frames are consumed one at a time (a generator is fine); their images are written as they come.
    """
    label = label or folder.name
    header = _meta_json(meta)  # fails early on metadata that JSON cannot hold
    K = meta.intrinsics
    size = (K.width, K.height)
    total = len(frames) if hasattr(frames, "__len__") else None
    rows: list[dict[str, str]] = []
    extra_keys: list[str] = []
    odom_rows: list[np.ndarray] = []
    gt_times: list[float] = []
    gt_rows: list[np.ndarray] = []
    has_odometry: bool | None = None
    clamped_pixels = clamped_frames = 0
    for sub in ("rgb", "depth"):
        (folder / sub).mkdir()
    for k, frame in enumerate(progress(frames, desc=f"write {Path(label).name}", total=total, unit="frame")):
        where = f"frame {k} (index {frame.index})"
        t = float(frame.timestamp_s)
        if not math.isfinite(t):
            raise InputError(f"{where}: timestamp {t!r} is not finite")
        if rows and t <= float(rows[-1]["timestamp_s"]):
            raise InputError(f"{where}: timestamp {t!r} is not after the previous one ({rows[-1]['timestamp_s']})")
        odom = _pose_or_none(frame.odom_pose, f"{where}: odom_pose")
        if has_odometry is None:
            has_odometry = odom is not None
        elif has_odometry != (odom is not None):
            raise InputError(f"{where}: odometry must be known for every frame or for none")
        gt = _pose_or_none(frame.gt_pose, f"{where}: gt_pose")

        name = f"{k:06d}.png"
        row = {c: "" for c in FRAME_COLUMNS}
        row.update(index=str(int(frame.index)), timestamp_s=_num(t), rgb=f"rgb/{name}", depth=f"depth/{name}")
        _write_png(folder / "rgb" / name, _rgb_to_disk(frame.rgb, size, where), where)
        try:
            depth_mm, clamped = _depth_to_mm(_depth_image(frame.depth_m, size, where))
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from None
        if clamped:
            clamped_pixels += clamped
            clamped_frames += 1
        _write_png(folder / "depth" / name, depth_mm, where)
        if frame.instance_ids is not None:
            (folder / "instances").mkdir(exist_ok=True)
            _write_png(folder / "instances" / name, _instances_to_disk(frame.instance_ids, size, where), where)
            row["instances"] = f"instances/{name}"
        if odom is not None:
            row.update(odom_x=_num(odom[0]), odom_y=_num(odom[1]), odom_yaw=_num(odom[2]))
            odom_rows.append(odom)
        if gt is not None:
            row.update(gt_x=_num(gt[0]), gt_y=_num(gt[1]), gt_yaw=_num(gt[2]))
            gt_times.append(t)
            gt_rows.append(gt)
        if frame.gt_storey is not None:
            row["gt_storey"] = str(int(frame.gt_storey))
        for key, value in frame.extras.items():
            column = EXTRA_PREFIX + str(key)
            if column not in extra_keys:
                extra_keys.append(column)
            row[column] = _num(value)
        rows.append(row)
    if not rows:
        raise InputError(f"{label}: no frames to write")

    with (folder / FRAMES_FILE).open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*FRAME_COLUMNS, *extra_keys], restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    timestamps = np.array([float(r["timestamp_s"]) for r in rows])
    if has_odometry:
        (folder / "odometry.txt").write_text(format_tum_trajectory(timestamps, np.array(odom_rows), "T_odom_base"))
    if gt_rows:
        (folder / "groundtruth.txt").write_text(
            format_tum_trajectory(np.array(gt_times), np.array(gt_rows), "T_world_base")
        )
    header["frame_count"] = len(rows)
    (folder / META_FILE).write_text(json.dumps(header, indent=2, default=_json_default) + "\n")
    if clamped_pixels:
        log.warning(
            "%s: %d depth pixels in %d frames beyond %.3f m written as no return",
            label,
            clamped_pixels,
            clamped_frames,
            MAX_DEPTH_MM / DEPTH_SCALE_PER_M,
        )
    log.info("wrote sequence %s: %d frames", label, len(rows))


def _meta_json(meta: SequenceMeta) -> dict[str, Any]:
    K = meta.intrinsics
    problem = camera_problem(K, meta.T_base_camera)
    if problem:
        raise InputError(f"sequence {meta.name!r}: {problem}")
    T = np.asarray(meta.T_base_camera, dtype=float)
    header = {
        "format": SEQUENCE_FORMAT,
        "version": SEQUENCE_VERSION,
        "name": str(meta.name),
        "source": str(meta.source),
        "intrinsics": {
            "width": int(K.width),
            "height": int(K.height),
            "fx": float(K.fx),
            "fy": float(K.fy),
            "cx": float(K.cx),
            "cy": float(K.cy),
        },
        "T_base_camera": T.tolist(),
        "depth_unit": DEPTH_UNIT,
        "prior_sha256": str(meta.prior_sha256),
        "instances": meta.instances,
        "extras": meta.extras,
        "frame_count": 0,
    }
    try:
        json.dumps(header, default=_json_default, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"sequence metadata is not JSON serialisable: {exc}") from None
    return header


def _pose_or_none(pose: np.ndarray | None, what: str) -> np.ndarray | None:
    """A finite (3,) pose, or None for an unknown one (None or all NaN)."""
    if pose is None:
        return None
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3,):
        raise InputError(f"{what} has shape {pose.shape}, expected (3,)")
    if np.isnan(pose).all():
        return None
    if not np.isfinite(pose).all():
        raise InputError(f"{what} {pose.tolist()} is partly unknown or infinite")
    return pose


def _checked_image(image: np.ndarray, size: tuple[int, int], where: str, what: str, kind: type) -> np.ndarray:
    image = np.asarray(image)
    if image.shape[:2] != (size[1], size[0]) or image.ndim not in (2, 3):
        raise InputError(f"{where}: {what} has shape {image.shape}, the intrinsics say {size[0]}x{size[1]}")
    if not np.issubdtype(image.dtype, kind):
        raise InputError(f"{where}: {what} has dtype {image.dtype}, expected {np.dtype(kind).name}")
    return image


def _rgb_to_disk(rgb: np.ndarray, size: tuple[int, int], where: str) -> np.ndarray:
    rgb = _checked_image(rgb, size, where, "rgb", np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"{where}: rgb has shape {rgb.shape}, expected (H, W, 3)")
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)


def _depth_image(depth_m: np.ndarray, size: tuple[int, int], where: str) -> np.ndarray:
    depth_m = _checked_image(depth_m, size, where, "depth_m", np.floating)
    if depth_m.ndim != 2:
        raise InputError(f"{where}: depth_m has shape {depth_m.shape}, expected (H, W)")
    return depth_m


def _instances_to_disk(ids: np.ndarray, size: tuple[int, int], where: str) -> np.ndarray:
    ids = _checked_image(ids, size, where, "instance_ids", np.integer)
    if ids.ndim != 2:
        raise InputError(f"{where}: instance_ids has shape {ids.shape}, expected (H, W)")
    if ids.size and (ids.min() < -1 or ids.max() > MAX_INSTANCE_ID):
        raise InputError(f"{where}: instance ids must lie in -1..{MAX_INSTANCE_ID}, got {ids.min()}..{ids.max()}")
    return (ids.astype(np.int64) + 1).astype(np.uint16)


def _write_png(path: Path, image: np.ndarray, where: str) -> None:
    """Encode in memory, then write the bytes: a full disk is Python's OSError naming the file (cv2.imwrite would
    print libpng's own line first and return False)."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{where}: could not encode {path.name} as PNG")
    try:
        path.write_bytes(data.tobytes())
    except OSError as exc:  # a full disk fails at the flush, with no file name: give it one
        raise OSError(exc.errno, exc.strerror, str(path)) from None


# ------------------------------------------------------------------------------------------ reader


def read_sequence(path: str | Path, *, on_bad_frame: Literal["raise", "skip"] = "raise") -> Sequence:
    """Open a sequence folder; the table is read now, the images when a frame is accessed.

    `on_bad_frame="skip"` drops frames with missing or truncated files (logged) instead of raising.
    """
    if on_bad_frame not in ("raise", "skip"):
        raise ValueError(f"on_bad_frame must be 'raise' or 'skip', not {on_bad_frame!r}")
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"no such sequence folder: {folder}")
    meta, frame_count = _read_meta(folder)
    table = _read_frames_table(folder, frame_count)

    keep = []
    for row, files in enumerate(table.files):
        bad = next((f for f in files if f is not None and not f.is_file()), None)
        if bad is None and on_bad_frame == "skip":
            bad = next((f for f in files if f is not None and not png_looks_complete(f)), None)
        if bad is None:
            keep.append(row)
        elif on_bad_frame == "raise":
            raise FormatError(f"{folder / FRAMES_FILE} line {row + 2}: frame file missing: {bad}")
        else:
            log.warning("%s: skipping frame at line %d: missing or truncated %s", folder, row + 2, bad)
    if not keep:
        raise FormatError(f"{folder}: no readable frames")
    if len(keep) < frame_count:
        log.warning("%s: %d of %d frames skipped", folder, frame_count - len(keep), frame_count)
    files = [table.files[r] for r in keep]
    size = (meta.intrinsics.width, meta.intrinsics.height)

    def load_images(i: int) -> FrameImages:
        rgb_file, depth_file, instance_file = files[i]
        rgb = decode_png(rgb_file, channels=3, dtype=np.uint8, size=size)
        depth = depth_from_mm(decode_png(depth_file, channels=1, dtype=np.uint16, size=size))
        ids = None
        if instance_file is not None:
            ids = decode_png(instance_file, channels=1, dtype=np.uint16, size=size).astype(np.int32) - 1
        return FrameImages(rgb, depth, ids)

    return Sequence(
        meta,
        table.timestamps[keep],
        load_images,
        indices=table.indices[keep],
        odom_poses=None if table.odom is None else table.odom[keep],
        gt_poses=None if table.gt is None else table.gt[keep],
        gt_storeys=[table.gt_storeys[r] for r in keep],
        frame_extras=[table.extras[r] for r in keep],
    )


def _read_meta(folder: Path) -> tuple[SequenceMeta, int]:
    meta_file = folder / META_FILE
    if not meta_file.is_file():
        raise FormatError(f"{folder}: not a bimfactor sequence ({META_FILE} missing)")
    try:
        data = json.loads(meta_file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"{meta_file}: corrupt JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != SEQUENCE_FORMAT:
        raise FormatError(f"{meta_file}: not a {SEQUENCE_FORMAT} file")
    version = data.get("version")
    if not isinstance(version, int) or version > SEQUENCE_VERSION or version < 1:
        raise FormatError(f"{meta_file}: format version {version!r}; this bimfactor reads up to {SEQUENCE_VERSION}")
    required = ("name", "source", "intrinsics", "T_base_camera", "depth_unit", "frame_count")
    missing = [key for key in required if key not in data]
    if missing:
        raise FormatError(f"{meta_file}: missing key(s) {', '.join(missing)}")
    if data["depth_unit"] != DEPTH_UNIT:
        raise FormatError(f"{meta_file}: depth_unit {data['depth_unit']!r}, expected {DEPTH_UNIT!r}")
    problem = intrinsics_problem(data["intrinsics"]) or mount_problem(data["T_base_camera"])
    if problem:
        raise FormatError(f"{meta_file}: {problem}")
    K = data["intrinsics"]
    intrinsics = CameraIntrinsics(
        int(K["width"]), int(K["height"]), float(K["fx"]), float(K["fy"]), float(K["cx"]), float(K["cy"])
    )
    T = np.array(data["T_base_camera"], dtype=np.float64)
    try:
        frame_count = int(data["frame_count"])
    except (TypeError, ValueError):
        raise FormatError(f"{meta_file}: frame_count {data['frame_count']!r} is not an integer") from None
    if not isinstance(data.get("instances", []), list) or not isinstance(data.get("extras", {}), dict):
        raise FormatError(f"{meta_file}: instances must be a list and extras an object")
    meta = SequenceMeta(
        name=str(data["name"]),
        source=str(data["source"]),
        intrinsics=intrinsics,
        T_base_camera=T,
        prior_sha256=str(data.get("prior_sha256", "")),
        instances=list(data.get("instances", [])),
        extras=dict(data.get("extras", {})),
    )
    return meta, frame_count


class _FramesTable(NamedTuple):
    indices: np.ndarray
    timestamps: np.ndarray
    files: list[tuple[Path, Path, Path | None]]
    odom: np.ndarray | None
    gt: np.ndarray | None
    gt_storeys: list[int | None]
    extras: list[dict[str, float]]


def _read_frames_table(folder: Path, frame_count: int) -> _FramesTable:
    frames_file = folder / FRAMES_FILE
    if not frames_file.is_file():
        raise FormatError(f"{folder}: {FRAMES_FILE} missing")
    try:
        with frames_file.open(newline="", encoding="utf-8-sig") as f:  # a byte-order mark is not part of the header
            lines = list(csv.reader(f))
    except (UnicodeDecodeError, csv.Error) as exc:
        raise FormatError(f"{frames_file}: unreadable CSV ({exc})") from None
    if not lines:
        raise FormatError(f"{frames_file}: empty (no header line)")
    header, body = lines[0], lines[1:]
    if tuple(header[: len(FRAME_COLUMNS)]) != FRAME_COLUMNS:
        raise FormatError(f"{frames_file}: header must start with {','.join(FRAME_COLUMNS)}")
    extra_columns = header[len(FRAME_COLUMNS) :]
    if any(not c.startswith(EXTRA_PREFIX) for c in extra_columns):
        raise FormatError(f"{frames_file}: columns after gt_storey must be named {EXTRA_PREFIX}<key>")
    if len(body) != frame_count:
        raise FormatError(f"{frames_file}: {len(body)} frame rows, but {META_FILE} says frame_count {frame_count}")

    indices, timestamps, files, storeys, extras = [], [], [], [], []
    odom = np.full((len(body), 3), np.nan)
    gt = np.full((len(body), 3), np.nan)
    has_odom: list[bool] = []
    for row, cells in enumerate(body):
        where = f"{frames_file} line {row + 2}"
        if len(cells) != len(header):
            raise FormatError(f"{where}: {len(cells)} columns, expected {len(header)}")
        cell = dict(zip(header, cells, strict=True))
        indices.append(_parse_int(cell["index"], where, "index"))
        timestamps.append(_parse_float(cell["timestamp_s"], where, "timestamp_s"))
        files.append(
            (
                _frame_path(folder, cell["rgb"], where, "rgb"),
                _frame_path(folder, cell["depth"], where, "depth"),
                _frame_path(folder, cell["instances"], where, "instances") if cell["instances"] else None,
            )
        )
        odom_known = _parse_pose(cell, ("odom_x", "odom_y", "odom_yaw"), odom[row], where)
        has_odom.append(odom_known)
        _parse_pose(cell, ("gt_x", "gt_y", "gt_yaw"), gt[row], where)
        storeys.append(_parse_int(cell["gt_storey"], where, "gt_storey") if cell["gt_storey"] else None)
        extras.append({c[len(EXTRA_PREFIX) :]: _parse_float(cell[c], where, c) for c in extra_columns if cell[c] != ""})
        if has_odom[row] != has_odom[0]:
            raise FormatError(f"{where}: odometry must be given on every row or on none")
        if row and timestamps[row] <= timestamps[row - 1]:
            order = "duplicate" if timestamps[row] == timestamps[row - 1] else "out-of-order"
            raise FormatError(
                f"{where}: {order} timestamp {cell['timestamp_s']} (previous row has {timestamps[row - 1]!r})"
            )
    return _FramesTable(
        indices=np.array(indices, dtype=np.int64),
        timestamps=np.array(timestamps, dtype=np.float64),
        files=files,
        odom=odom if has_odom and has_odom[0] else None,
        gt=None if np.isnan(gt).all() else gt,
        gt_storeys=storeys,
        extras=extras,
    )


def _parse_float(text: str, where: str, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FormatError(f"{where}: {column} {text!r} is not a number") from None
    return value


def _parse_int(text: str, where: str, column: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise FormatError(f"{where}: {column} {text!r} is not an integer") from None


def _parse_pose(cell: dict[str, str], columns: tuple[str, str, str], out: np.ndarray, where: str) -> bool:
    """Fill `out` from three columns; False when all three are empty, FormatError when only some are."""
    texts = [cell[c] for c in columns]
    if all(t == "" for t in texts):
        return False
    if any(t == "" for t in texts):
        raise FormatError(f"{where}: {', '.join(columns)} must be all given or all empty")
    out[:] = [_parse_float(t, where, c) for t, c in zip(texts, columns, strict=True)]
    if not np.isfinite(out).all():
        raise FormatError(f"{where}: {', '.join(columns)} are not finite")
    return True


def _frame_path(folder: Path, name: str, where: str, column: str) -> Path:
    relative = PurePosixPath(name)
    if not name or relative.is_absolute() or ".." in relative.parts:
        raise FormatError(f"{where}: {column} path {name!r} must be a relative path inside the sequence folder")
    return folder.joinpath(*relative.parts)
