"""ROS 2 bags (sqlite3 or mcap) as a `Sequence`, read with the pure-Python `rosbags` library.

Topics come from `RosbagConfig`:

- `rgb_topic`: sensor_msgs/msg/Image, encoding rgb8, bgr8, rgba8 or bgra8 (alpha dropped);
- `depth_topic`: sensor_msgs/msg/Image, 16UC1 / mono16 in millimetres (0 = no return) or 32FC1 in metres
  (NaN, ±inf and values ≤ 0 = no return); it must have the colour image's size (use an aligned depth topic);
- `camera_info_topic`: sensor_msgs/msg/CameraInfo; the first message's K gives the intrinsics (distortion is
  ignored, with a warning when not zero). Optional when intrinsics are passed in;
- `odom_topic`: nav_msgs/msg/Odometry; pose.pose projected onto the plane is T_odom_base.

Times are the messages' header stamps; a frame's `timestamp_s` is its colour stamp in ns / 1e9. Each colour
image is paired one-to-one with the depth image nearest in time and with the odometry message nearest in time,
both within `max_sync_dt_s`; colour images without both are dropped (logged), and of images with the same stamp
only the first is kept. The bag is scanned once when opened (headers and odometry only); images are decoded when
a frame is accessed, and iterating streams the bag in one pass. `meta.source` is "rosbag"; there is no ground
truth. Missing topics, wrong message types or unsupported encodings are InputErrors that name them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bimfactor.config import RosbagConfig
from bimfactor.errors import DependencyError, FormatError, InputError
from bimfactor.io.sequence import (
    DEPTH_SCALE_PER_M,
    FrameImages,
    Sequence,
    associate_nearest,
    camera_problem,
    depth_from_mm,
    level_camera_mount,
)
from bimfactor.io.tum import MAX_TILT_DEG, planar_from_matrices, quaternion_to_matrix
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta

log = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
RGB_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


def _rosbags() -> tuple[Any, Any, Any]:
    """The rosbags Reader, its error type and a ROS 2 typestore (imported on first use: optional dependency)."""
    try:
        from rosbags.rosbag2 import Reader, ReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DependencyError("reading ROS 2 bags needs the 'rosbags' package: pip install rosbags") from None
    # Image, CameraInfo and Odometry are the same in every ROS 2 distribution
    return Reader, ReaderError, get_typestore(Stores.ROS2_HUMBLE)


@dataclass(frozen=True)
class _MessageRef:
    """Where an image message is in the bag: topic, log time (ns), header stamp (ns)."""

    topic: str
    log_ns: int
    stamp_ns: int


def read_rosbag(
    path: str | Path,
    config: RosbagConfig,
    *,
    intrinsics: CameraIntrinsics | None = None,
    T_base_camera: np.ndarray | None = None,
    max_tilt_deg: float = MAX_TILT_DEG,
) -> RosbagSequence:
    """Open a ROS 2 bag folder (or a single .db3 / .mcap file) as a `Sequence` of synchronised RGB-D frames.

    `T_base_camera` (4, 4) defaults to a level camera at the base origin (`level_camera_mount()`).
    """
    Reader, ReaderError, typestore = _rosbags()
    path = Path(path)
    if not path.exists():
        raise InputError(f"no such ROS 2 bag: {path}")
    not_a_bag = _not_a_bag(path)
    if not_a_bag:
        raise InputError(f"{path}: not a readable ROS 2 bag: {not_a_bag}")
    wanted = {
        config.rgb_topic: IMAGE_TYPE,
        config.depth_topic: IMAGE_TYPE,
        config.odom_topic: ODOMETRY_TYPE,
    }
    if intrinsics is None:
        wanted[config.camera_info_topic] = CAMERA_INFO_TYPE

    refs: dict[str, list[_MessageRef]] = {config.rgb_topic: [], config.depth_topic: []}
    odom_stamps: list[int] = []
    odom_xyz: list[tuple[float, float, float]] = []
    odom_quat: list[tuple[float, float, float, float]] = []
    camera_info = None
    try:
        with Reader(path) as reader:
            present = {topic: info.msgtype for topic, info in reader.topics.items()}
            _check_topics(path, wanted, present)
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, log_ns, raw in reader.messages(connections=connections):
                msg = typestore.deserialize_cdr(raw, connection.msgtype)
                stamp_ns = _stamp_ns(msg)
                if connection.topic in refs:
                    refs[connection.topic].append(_MessageRef(connection.topic, log_ns, stamp_ns))
                elif connection.topic == config.odom_topic:
                    p, q = msg.pose.pose.position, msg.pose.pose.orientation
                    odom_stamps.append(stamp_ns)
                    odom_xyz.append((p.x, p.y, p.z))
                    odom_quat.append((q.x, q.y, q.z, q.w))
                elif camera_info is None:
                    camera_info = msg
    except (FileNotFoundError, ReaderError) as exc:
        said = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise InputError(f"{path}: not a readable ROS 2 bag ({said})") from None

    if intrinsics is None:
        if camera_info is None:
            raise InputError(f"{path}: no message on {config.camera_info_topic}; pass the intrinsics instead")
        intrinsics = _intrinsics_from_camera_info(camera_info, path)
    mount = level_camera_mount() if T_base_camera is None else T_base_camera
    problem = camera_problem(intrinsics, mount)
    if problem:
        raise InputError(f"{path}: {problem}")

    # pair colour ↔ depth one-to-one, colour → odometry nearest, all by header stamp
    rgb_refs = _sorted_unique(refs[config.rgb_topic], path)
    depth_refs = _sorted_unique(refs[config.depth_topic], path)
    if not rgb_refs or not depth_refs or not odom_stamps:
        empty = [
            t
            for t, n in (
                (config.rgb_topic, rgb_refs),
                (config.depth_topic, depth_refs),
                (config.odom_topic, odom_stamps),
            )
            if not n
        ]
        raise InputError(f"{path}: no messages on {', '.join(empty)}")
    # seconds from the first colour stamp: float64 keeps nanoseconds there, unlike seconds since 1970
    t0 = rgb_refs[0].stamp_ns
    rgb_t = np.array([(r.stamp_ns - t0) / 1e9 for r in rgb_refs])
    depth_t = np.array([(r.stamp_ns - t0) / 1e9 for r in depth_refs])
    order = np.argsort(np.array(odom_stamps, dtype=np.int64), kind="stable")
    odom_t = (np.array(odom_stamps, dtype=np.int64)[order] - t0) / 1e9
    i_rgb, i_depth = associate_nearest(rgb_t, depth_t, config.max_sync_dt_s, one_to_one=True)
    i_frame, i_odom = associate_nearest(rgb_t[i_rgb], odom_t, config.max_sync_dt_s, one_to_one=False)
    i_rgb, i_depth = i_rgb[i_frame], i_depth[i_frame]
    if len(i_rgb) == 0:
        raise InputError(
            f"{path}: no colour image has both depth and odometry within max_sync_dt_s={config.max_sync_dt_s} s"
        )
    if len(i_rgb) < len(rgb_refs):
        log.info(
            "%s: %d of %d colour images dropped (no depth or odometry within %s s)",
            path,
            len(rgb_refs) - len(i_rgb),
            len(rgb_refs),
            config.max_sync_dt_s,
        )

    T_odom = np.tile(np.eye(4), (len(order), 1, 1))
    T_odom[:, :3, :3] = quaternion_to_matrix(np.array(odom_quat)[order])
    T_odom[:, :3, 3] = np.array(odom_xyz)[order]
    odom_planar = planar_from_matrices(T_odom, what=f"{path} {config.odom_topic}", max_tilt_deg=max_tilt_deg)

    meta = SequenceMeta(
        name=path.stem if path.is_file() else path.name,
        source="rosbag",
        intrinsics=intrinsics,
        T_base_camera=np.asarray(mount, dtype=float),
        extras={
            "bag": str(path),
            "rgb_topic": config.rgb_topic,
            "depth_topic": config.depth_topic,
            "odom_topic": config.odom_topic,
        },
    )
    return RosbagSequence(
        path,
        meta,
        rgb_refs=[rgb_refs[i] for i in i_rgb],
        depth_refs=[depth_refs[i] for i in i_depth],
        odom_poses=odom_planar[i_odom],
    )


class RosbagSequence(Sequence):
    """A `Sequence` over a ROS 2 bag; `__getitem__` reads one frame's messages, `__iter__` streams the bag."""

    def __init__(
        self,
        path: Path,
        meta: SequenceMeta,
        *,
        rgb_refs: list[_MessageRef],
        depth_refs: list[_MessageRef],
        odom_poses: np.ndarray,
    ) -> None:
        timestamps = np.array([r.stamp_ns / 1e9 for r in rgb_refs])  # Python int / float: correctly rounded
        super().__init__(meta, timestamps, self._load_frame_images, odom_poses=odom_poses)
        self._path = path
        self._rgb_refs = rgb_refs
        self._depth_refs = depth_refs

    def _load_frame_images(self, i: int) -> FrameImages:
        Reader, _, typestore = _rosbags()
        decoded = {}
        with Reader(self._path) as reader:
            for role, ref in (("rgb", self._rgb_refs[i]), ("depth", self._depth_refs[i])):
                connections = [c for c in reader.connections if c.topic == ref.topic]
                for connection, _log_ns, raw in reader.messages(connections, start=ref.log_ns, stop=ref.log_ns + 1):
                    msg = typestore.deserialize_cdr(raw, connection.msgtype)
                    if _stamp_ns(msg) == ref.stamp_ns:
                        decoded[role] = msg
                        break
                else:
                    raise FormatError(f"{self._path}: message on {ref.topic} at {ref.log_ns} ns vanished")
        return self._images(decoded["rgb"], decoded["depth"])

    def __iter__(self) -> Iterator[Frame]:
        Reader, _, typestore = _rosbags()
        wanted: dict[_MessageRef, list[tuple[int, str]]] = {}
        for i, (rgb, depth) in enumerate(zip(self._rgb_refs, self._depth_refs, strict=True)):
            wanted.setdefault(rgb, []).append((i, "rgb"))
            wanted.setdefault(depth, []).append((i, "depth"))
        topics = {self._rgb_refs[0].topic, self._depth_refs[0].topic}
        pending: dict[int, dict[str, Any]] = {}
        next_frame = 0
        with Reader(self._path) as reader:
            connections = [c for c in reader.connections if c.topic in topics]
            for connection, log_ns, raw in reader.messages(connections):
                msg = typestore.deserialize_cdr(raw, connection.msgtype)
                for i, role in wanted.pop(_MessageRef(connection.topic, log_ns, _stamp_ns(msg)), ()):
                    pending.setdefault(i, {})[role] = msg
                while len(pending.get(next_frame, ())) == 2:
                    msgs = pending.pop(next_frame)
                    yield self._frame(next_frame, self._images(msgs["rgb"], msgs["depth"]))
                    next_frame += 1
        if next_frame < len(self):
            raise FormatError(f"{self._path}: messages of frame {next_frame} not found on a second pass")

    def _images(self, rgb_msg: Any, depth_msg: Any) -> FrameImages:
        rgb = rgb_image(rgb_msg, str(self._path))
        depth = depth_image(depth_msg, str(self._path))
        K = self.meta.intrinsics
        for what, image in (("colour", rgb), ("depth", depth)):
            if image.shape[:2] != (K.height, K.width):
                raise InputError(
                    f"{self._path}: {what} image is {image.shape[1]}x{image.shape[0]}, the camera info says "
                    f"{K.width}x{K.height} (use a depth topic aligned to the colour image)"
                )
        return FrameImages(rgb, depth, None)


def rgb_image(msg: Any, where: str) -> np.ndarray:
    """sensor_msgs/Image in rgb8 / bgr8 / rgba8 / bgra8 → (H, W, 3) uint8 RGB."""
    encoding = msg.encoding.lower()
    if encoding not in RGB_ENCODINGS:
        raise InputError(f"{where}: colour encoding {msg.encoding!r} not supported ({', '.join(RGB_ENCODINGS)})")
    channels = 4 if encoding.endswith("a8") else 3
    image = _pixels(msg, np.dtype(np.uint8), channels, where)
    image = image[..., :3]
    if encoding.startswith("bgr"):
        image = image[..., ::-1]
    return np.ascontiguousarray(image)


def depth_image(msg: Any, where: str) -> np.ndarray:
    """sensor_msgs/Image in 16UC1 / mono16 (mm) or 32FC1 (m) → (H, W) float32 metres, NaN = no return."""
    encoding = msg.encoding
    if encoding in ("16UC1", "mono16"):
        return depth_from_mm(_pixels(msg, np.dtype(np.uint16), 1, where), DEPTH_SCALE_PER_M)
    if encoding == "32FC1":
        depth = _pixels(msg, np.dtype(np.float32), 1, where).astype(np.float32)
        depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
        return depth
    raise InputError(f"{where}: depth encoding {encoding!r} not supported ({', '.join(DEPTH_ENCODINGS)})")


def _pixels(msg: Any, dtype: np.dtype, channels: int, where: str) -> np.ndarray:
    """The message's pixel rows (honouring `step` padding and byte order) as (H, W[, C]) native-endian values."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row_bytes or data.size < step * h:
        raise FormatError(f"{where}: image message of {data.size} bytes is too short for {w}x{h} {msg.encoding}")
    rows = data[: step * h].reshape(h, step)[:, :row_bytes]
    values = np.ascontiguousarray(rows).view(dtype.newbyteorder(">" if msg.is_bigendian else "<"))
    values = values.astype(dtype.newbyteorder("="))
    return values.reshape(h, w, channels) if channels > 1 else values.reshape(h, w)


def _stamp_ns(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _sorted_unique(refs: list[_MessageRef], path: Path) -> list[_MessageRef]:
    """Image references by header stamp, dropping repeated stamps (logged)."""
    out: list[_MessageRef] = []
    for ref in sorted(refs, key=lambda r: (r.stamp_ns, r.log_ns)):
        if out and ref.stamp_ns == out[-1].stamp_ns:
            log.warning("%s: %s has two images stamped %d ns; keeping the first", path, ref.topic, ref.stamp_ns)
            continue
        out.append(ref)
    return out


def _not_a_bag(path: Path) -> str | None:
    """Why an existing path cannot be a ROS 2 bag the reader opens (None: it may be one): a folder needs the
    metadata.yaml that `ros2 bag record` writes, a single file must be a .db3 or .mcap storage file."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return None
        storage = sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
        if storage:
            return f"no metadata.yaml in the folder (open the storage file {path / storage[0]} instead)"
        ros1 = [p.name for p in path.iterdir() if p.suffix == ".bag"]
        if ros1:
            return f"it holds a ROS 1 bag ({ros1[0]}); convert it to ROS 2 first (rosbags-convert)"
        return "the folder has no metadata.yaml (a ROS 2 bag is a folder with metadata.yaml, or a .db3 or .mcap file)"
    if path.suffix == ".bag":
        return "a ROS 1 bag; convert it to ROS 2 first (rosbags-convert)"
    if path.suffix not in (".db3", ".mcap"):
        return (
            f"a {path.suffix or 'suffix-less'} file; expected a bag folder with metadata.yaml, or a .db3 or .mcap file"
        )
    return None


def _check_topics(path: Path, wanted: dict[str, str], present: dict[str, str | None]) -> None:
    missing = sorted(t for t in wanted if t not in present)
    if missing:
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(present.items())) or "none"
        raise InputError(f"{path}: topic(s) {', '.join(missing)} not in the bag; it has: {listing}")
    for topic, msgtype in wanted.items():
        if topic in present and present[topic] != msgtype:
            raise InputError(f"{path}: topic {topic} carries {present[topic]}, expected {msgtype}")


def _intrinsics_from_camera_info(info: Any, path: Path) -> CameraIntrinsics:
    K = np.asarray(info.k, dtype=float)
    if K.size != 9 or not K[0] > 0 or not K[4] > 0 or info.width <= 0 or info.height <= 0:
        raise InputError(f"{path}: camera info has no valid K / image size (K = {K.tolist()})")
    if np.any(np.asarray(info.d, dtype=float) != 0):
        log.warning("%s: camera info distortion %s ignored (pinhole model)", path, list(info.d))
    return CameraIntrinsics(int(info.width), int(info.height), float(K[0]), float(K[4]), float(K[2]), float(K[5]))
