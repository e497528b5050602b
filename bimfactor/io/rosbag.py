"""Robot recordings as a `Sequence`: ROS 1 bags (.bag), ROS 2 bags (a folder with metadata.yaml, sqlite3 or mcap
storage, or a lone .db3 / .mcap file), read with the `rosbags` library's AnyReader.

Topics are named in `io.rosbag` or found by message type; what is read, how it is synchronised, registered and
undistorted, and every error: docs/sequences.md, "Bags".
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bimfactor.config import RosbagConfig
from bimfactor.errors import DependencyError, FormatError, InputError
from bimfactor.io.rectify import distortion_problem, register_depth, remap_colour, remap_depth, undistort_maps
from bimfactor.io.sequence import (
    DEPTH_SCALE_PER_M,
    FrameImages,
    Sequence,
    associate_nearest,
    camera_problem,
    depth_from_mm,
    level_camera_mount,
)
from bimfactor.io.tf import TfChain, TfTree, describe_chain, frame_name, stamp_ns, transform_matrix
from bimfactor.io.tum import MAX_TILT_DEG, planar_from_matrices
from bimfactor.progress import progress
from bimfactor.types import STOREY_CHANGE, CameraIntrinsics, Frame, SequenceMeta, wrap_angle

log = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
STOREY_TYPE = "std_msgs/msg/Int32"
# vision_msgs 4 (ROS 2 Humble and later), for ROS 2 bags that carry no message definitions (ROS 1 bags and MCAP files
# carry their own, so vision_msgs 1-3 read from them too).
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\nvision_msgs/BoundingBox2D bbox\n"
        "string id\n"
    ),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}
RGB_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
FOUND_DEPTH_ENCODINGS = ("16UC1", "32FC1")  # mono16 is also an infrared format: read only from a named topic
R_LINK_OPTICAL = level_camera_mount()[:3, :3]
"""A camera body frame (ROS camera_link: x forward, y left, z up) → its optical frame (x right, y down, z forward)."""


def _rosbags() -> tuple[Any, tuple[type[BaseException], ...], Any]:
    """AnyReader, the errors it raises on a bad file, and a ROS 2 typestore for bags without message definitions
    (imported on first use: optional dependency)."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag1 import ReaderError as Ros1ReaderError
        from rosbags.rosbag2 import ReaderError as Ros2ReaderError
        from rosbags.serde import SerdeError
    except ImportError:
        raise DependencyError("reading ROS bags needs the 'rosbags' package: pip install rosbags") from None
    # a damaged file fails inside the reader as any of these, or asks for more memory than a record can hold
    errors = (AnyReaderError, Ros1ReaderError, Ros2ReaderError, SerdeError, FileNotFoundError, MemoryError)
    return AnyReader, errors, ros2_typestore()


def ros2_typestore() -> Any:
    """The ROS 2 Humble typestore with vision_msgs' detection messages added."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@dataclass(frozen=True)
class _MessageRef:
    """Where an image message is in the bag: topic, log time (ns), header stamp (ns)."""

    topic: str
    log_ns: int
    stamp_ns: int


@dataclass(frozen=True)
class CameraInfo:
    """What bimfactor reads of a sensor_msgs/CameraInfo (ROS 1's K, D, P are ROS 2's k, d, p)."""

    topic: str
    frame_id: str
    width: int
    height: int
    K: np.ndarray  # (3, 3)
    D: np.ndarray  # (n,)
    P: np.ndarray  # (3, 4)
    model: str
    binning: tuple[int, int]
    roi_wh: tuple[int, int]

    @classmethod
    def from_msg(cls, topic: str, msg: Any) -> CameraInfo:
        def field(name: str) -> np.ndarray:
            value = getattr(msg, name, None)
            return np.asarray(getattr(msg, name.upper()) if value is None else value, dtype=np.float64)

        return cls(
            topic,
            frame_name(msg.header.frame_id),
            int(msg.width),
            int(msg.height),
            field("k").reshape(-1),
            field("d").reshape(-1),
            field("p").reshape(-1),
            str(msg.distortion_model),
            (int(msg.binning_x), int(msg.binning_y)),
            (int(msg.roi.width), int(msg.roi.height)),
        )

    def problem(self, image_wh: tuple[int, int], what: str) -> str | None:
        """Why these intrinsics cannot describe the `what` images of size `image_wh`, or None."""
        w, h = image_wh
        if (self.width, self.height) != (w, h):
            return f"{what} images are {w}x{h} but CameraInfo on {self.topic} says {self.width}x{self.height}"
        if max(self.binning) > 1 or (0 < self.roi_wh[0] < w) or (0 < self.roi_wh[1] < h):
            return f"CameraInfo on {self.topic} uses binning {self.binning} or a region of interest {self.roi_wh}"
        if self.K.size != 9 or not np.isfinite(self.K).all() or not (self.K[0] > 0 and self.K[4] > 0):
            return f"CameraInfo on {self.topic} has no valid K ({self.K.tolist()})"
        cx, cy = self.K[2], self.K[5]
        if not (0 <= cx < w and 0 <= cy < h):
            return f"CameraInfo on {self.topic}: principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} image"
        return None

    def matrix(self, rectified: bool) -> np.ndarray:
        """(3, 3) camera matrix: K, or for an already rectified image P's left 3x3 (K when P is not set)."""
        if rectified and self.P.size == 12 and self.P[0] > 0 and self.P[5] > 0:
            return self.P.reshape(3, 4)[:, :3].copy()
        return self.K.reshape(3, 3).copy()


@dataclass
class _Rectifier:
    """What turns a frame's raw messages into pinhole images: colour remap tables, the depth's remap tables (in its
    own camera), and the depth → colour registration (K_depth, T_colour_depth, K_colour, size) or None."""

    colour_maps: tuple[np.ndarray, np.ndarray] | None = None
    depth_maps: tuple[np.ndarray, np.ndarray] | None = None
    registration: tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None = None
    depth_size_wh: tuple[int, int] | None = None  # the raw depth image's size when it is registered


def read_rosbag(
    path: str | Path,
    config: RosbagConfig,
    *,
    intrinsics: CameraIntrinsics | None = None,
    T_base_camera: np.ndarray | None = None,
    mount_source: str = "given by the caller",
    max_tilt_deg: float = MAX_TILT_DEG,
    needs_odometry: bool = True,
) -> RosbagSequence:
    """Open a ROS 1 or ROS 2 bag as a `Sequence` of synchronised RGB-D frames with interpolated odometry.

    `intrinsics` replaces the CameraInfo (no undistortion then); `T_base_camera` (4, 4) replaces the tf mount
    (`mount_source` says where it came from, for the report). Without `needs_odometry` a bag with no odometry is
    read without it (`odometry()` is None: a camera-only recording, for RGB-D odometry).
    """
    AnyReader, reader_errors, default_typestore = _rosbags()
    path = Path(path)
    if not path.exists():
        raise InputError(f"no such bag: {path}")
    kind = "ROS 1" if path.suffix == ".bag" and not path.is_dir() else "ROS 2"
    not_a_bag = _not_a_bag(path)
    if not_a_bag:
        raise InputError(f"{path}: not a readable {kind} bag: {not_a_bag}")
    try:
        with AnyReader([path], default_typestore=default_typestore) as reader:
            return _read(reader, path, config, intrinsics, T_base_camera, mount_source, max_tilt_deg, needs_odometry)
    except reader_errors as exc:
        said = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise InputError(f"{path}: not a readable {kind} bag ({said})") from None


def _read(
    reader: Any,
    path: Path,
    config: RosbagConfig,
    intrinsics: CameraIntrinsics | None,
    T_base_camera: np.ndarray | None,
    mount_source: str,
    max_tilt_deg: float,
    needs_odometry: bool,
) -> RosbagSequence:
    """`read_rosbag` on an open AnyReader: the streams, the camera, tf and odometry, then the image headers."""
    topics = {topic: info.msgtype for topic, info in reader.topics.items()}
    connections: dict[str, list[Any]] = {}
    for c in reader.connections:
        connections.setdefault(c.topic, []).append(c)
    first = _FirstMessages(reader, connections)
    found: dict[str, str] = {}

    # 1. the streams: colour and depth images, their camera infos, odometry
    rgb_topic = _image_topic(path, "colour", "rgb_topic", config.rgb_topic, topics, first, found)
    depth_topic = _image_topic(path, "depth", "depth_topic", config.depth_topic, topics, first, found)
    rgb_first, depth_first = first(rgb_topic), first(depth_topic)
    colour_frame, depth_frame = frame_name(rgb_first.header.frame_id), frame_name(depth_first.header.frame_id)
    colour_wh = (int(rgb_first.width), int(rgb_first.height))
    depth_wh = (int(depth_first.width), int(depth_first.height))
    depth_registered = depth_frame == colour_frame and depth_wh == colour_wh
    extras: dict[str, Any] = {"bag": str(path), "bag_format": _bag_format(path)}

    colour_info = None
    if intrinsics is None:
        colour_info = _camera_info(
            path, "colour", "camera_info_topic", config.camera_info_topic, rgb_topic, colour_frame, topics, first, found
        )
        problem = colour_info.problem(colour_wh, "colour")
        if problem:
            raise InputError(f"{path}: {problem}")
    depth_info = None
    if not depth_registered:
        depth_info = _camera_info(
            path,
            "depth",
            "depth_camera_info_topic",
            config.depth_camera_info_topic,
            depth_topic,
            depth_frame,
            topics,
            first,
            found,
        )
        problem = depth_info.problem(depth_wh, "depth")
        if problem:
            raise InputError(f"{path}: {problem}")

    # 2. intrinsics and distortion, checked before anything else is read
    rectifier = _Rectifier()
    if colour_info is not None:
        intrinsics, rectifier.colour_maps, extras["intrinsics"], extras["distortion"] = _colour_camera(
            path, colour_info, colour_wh, rectified="rect" in rgb_topic.lower()
        )
        if depth_registered:
            rectifier.depth_maps = rectifier.colour_maps  # depth shares the colour image's pixels and lens
    else:
        extras["intrinsics"] = {"from": "given by the caller"}
        extras["distortion"] = {"model": "none (given intrinsics)", "coefficients": [], "undistorted": False}
    extras["intrinsics"].update({k: getattr(intrinsics, k) for k in ("width", "height", "fx", "fy", "cx", "cy")})
    problem = camera_problem(intrinsics, level_camera_mount() if T_base_camera is None else T_base_camera)
    if problem:
        raise InputError(f"{path}: {problem}")
    odom_topic = _odometry_topic(path, config.odom_topic, topics, found)
    detections_topic = _detections_topic(path, config.detections_topic, topics, found)
    storey_topic = config.storey_topic or None
    if storey_topic is not None and topics.get(storey_topic) != STOREY_TYPE:
        carries = "is not in the bag" if storey_topic not in topics else f"carries {topics[storey_topic]}"
        raise InputError(f"{path}: topic {storey_topic} (io.rosbag.storey_topic) {carries}, expected {STOREY_TYPE}")
    tf_topics = sorted(t for t, m in topics.items() if m in TF_TYPES)

    # 3. tf, odometry and a detector's detections: one pass over their messages
    tree = TfTree()
    odom_msgs: list[tuple[int, Any]] = []
    detection_msgs: list[tuple[int, Any]] = []
    storey_msgs: list[tuple[int, int]] = []
    streams = [*tf_topics, *(t for t in (odom_topic, detections_topic, storey_topic) if t)]
    wanted = [c for t in streams for c in connections[t]]
    for connection, log_ns, raw in reader.messages(connections=wanted) if wanted else ():
        msg = reader.deserialize(raw, connection.msgtype)
        if connection.topic == odom_topic:
            odom_msgs.append((log_ns, msg))
        elif connection.topic == detections_topic:
            detection_msgs.append((_stamp_or_log(msg, log_ns), msg))
        elif connection.topic == storey_topic:
            storey_msgs.append((log_ns, int(msg.data)))
        else:
            tree.add(msg, static=connection.topic.rstrip("/").endswith("tf_static"))
    t_first_ns = _stamp_or_log(rgb_first, 0)

    # 4. the camera mount: the tf chain base → colour optical frame, unless given
    base = frame_name(config.base_frame)
    if T_base_camera is None:
        T_base_camera, mount_source = _mount_from_tf(path, tree, base, colour_frame, rgb_topic, t_first_ns)
        problem = camera_problem(intrinsics, T_base_camera)
        if problem:
            raise InputError(f"{path}: the tf chain {base} → {colour_frame}: {problem}")
    extras["camera_mount"] = {
        "frames": f"{base} → {colour_frame or '(none)'}",
        "xyz_m": [float(v) for v in T_base_camera[:3, 3]],
        "rpy_deg": [float(v) for v in mount_rpy_deg(T_base_camera)],
        "from": mount_source,
    }

    # 5. depth → colour registration
    if depth_registered:
        extras["depth"] = {"registration": f"as recorded: already in the colour frame {colour_frame or '(none)'}"}
    else:
        assert depth_info is not None
        rectifier.depth_maps, rectifier.registration, extras["depth"] = _depth_registration(
            path, tree, depth_info, depth_topic, colour_frame, intrinsics, t_first_ns
        )
        rectifier.depth_size_wh = depth_wh

    # 6. odometry samples: (M,) stamps and (M, 3) planar T_odom_base
    odometry = _odometry_samples(path, config, odom_topic, odom_msgs, tree, max_tilt_deg, needs_odometry)
    odom_stamps, odom_planar, odom_from = odometry if odometry is not None else (None, None, None)

    # 7. the image headers, then colour ↔ depth ↔ odometry by time
    refs: dict[str, list[_MessageRef]] = {rgb_topic: [], depth_topic: []}
    images = [c for t in refs for c in connections[t]]
    total = sum(topics_info.msgcount for t, topics_info in reader.topics.items() if t in refs)
    for connection, log_ns, raw in progress(
        reader.messages(connections=images), desc="reading image headers", total=total, unit="msg"
    ):
        msg = reader.deserialize(raw, connection.msgtype)
        refs[connection.topic].append(_MessageRef(connection.topic, log_ns, _stamp_or_log(msg, log_ns)))
    rgb_refs, depth_refs = (_with_stamps(path, refs[t], t) for t in (rgb_topic, depth_topic))
    kept, odom_poses, sync, dropped = _associate(path, config, rgb_refs, depth_refs, odom_stamps, odom_planar)

    frame_rgb = [rgb_refs[i] for i in kept[0]]
    detections = None
    if detections_topic is not None:
        lens = None if colour_info is None or rectifier.colour_maps is None else (colour_info.K, colour_info.D)
        detections, extras["detections"] = _detections_at_frames(
            detection_msgs, frame_rgb, config.max_sync_dt_s, intrinsics, lens
        )
    frame_extras = _storey_changes_at_frames(storey_msgs, frame_rgb)
    if storey_topic is not None:
        extras["storey_changes"] = {"messages": len(storey_msgs), "frames": sum(bool(e) for e in frame_extras)}
    extras["topics"] = {
        "rgb": rgb_topic,
        "detections": detections_topic,
        "storey": storey_topic,
        "depth": depth_topic,
        "camera_info": None if colour_info is None else colour_info.topic,
        "depth_camera_info": None if depth_info is None else depth_info.topic,
        "odometry": odom_from,
        "tf": tf_topics,
        "found_by_type": sorted(found),
    }
    extras["base_frame"] = base
    extras["sync"] = sync
    extras["frames"] = {"colour_images": len(refs[rgb_topic]), "kept": len(kept[0]), "dropped": dropped}
    meta = SequenceMeta(
        name=path.stem if path.is_file() else path.name,
        source="rosbag",
        intrinsics=intrinsics,
        T_base_camera=np.asarray(T_base_camera, dtype=float),
        extras=extras,
    )
    return RosbagSequence(
        path,
        meta,
        rgb_refs=frame_rgb,
        depth_refs=[depth_refs[i] for i in kept[1]],
        odom_poses=odom_poses,
        rectifier=rectifier,
        detections=detections,
        frame_extras=frame_extras,
    )


def _storey_changes_at_frames(messages: list[tuple[int, int]], frames: list[_MessageRef]) -> list[dict[str, float]]:
    """Each frame's extras: the storey changes stamped after the frame before and at or before it, summed (none
    after the last frame is kept)."""
    extras: list[dict[str, float]] = [{} for _ in frames]
    stamps = np.array([r.stamp_ns for r in frames], np.int64)
    for stamp, floors in messages:
        k = int(np.searchsorted(stamps, stamp, side="left"))
        if k < len(frames) and floors:
            extras[k][STOREY_CHANGE] = extras[k].get(STOREY_CHANGE, 0.0) + floors
    return extras


class RosbagSequence(Sequence):
    """A `Sequence` over a bag; `__getitem__` reads one frame's messages, `__iter__` streams the bag."""

    def __init__(
        self,
        path: Path,
        meta: SequenceMeta,
        *,
        rgb_refs: list[_MessageRef],
        depth_refs: list[_MessageRef],
        odom_poses: np.ndarray | None,
        rectifier: _Rectifier | None = None,
        detections: list[dict[str, Any]] | None = None,
        frame_extras: list[dict[str, float]] | None = None,
    ) -> None:
        timestamps = np.array([r.stamp_ns / 1e9 for r in rgb_refs])  # Python int / float: correctly rounded
        super().__init__(meta, timestamps, self._load_frame_images, odom_poses=odom_poses, frame_extras=frame_extras)
        self.detections = detections
        """A detector's detections on the bag (vision_msgs/Detection2DArray): one line of the detections file
        (docs/perception.md: timestamp, detections of label, score, box) per frame that has a message within
        max_sync_dt_s, named by the frame's stamp; None: the bag has no such topic."""
        self._path = path
        self._rgb_refs = rgb_refs
        self._depth_refs = depth_refs
        self._rectifier = rectifier or _Rectifier()

    def _open(self) -> Any:
        AnyReader, _, default_typestore = _rosbags()
        return AnyReader([self._path], default_typestore=default_typestore)

    def _load_frame_images(self, i: int) -> FrameImages:
        decoded = {}
        with self._open() as reader:
            for role, ref in (("rgb", self._rgb_refs[i]), ("depth", self._depth_refs[i])):
                connections = [c for c in reader.connections if c.topic == ref.topic]
                for connection, log_ns, raw in reader.messages(connections, start=ref.log_ns, stop=ref.log_ns + 1):
                    msg = reader.deserialize(raw, connection.msgtype)
                    if _MessageRef(ref.topic, log_ns, _stamp_or_log(msg, log_ns)) == ref:
                        decoded[role] = msg
                        break
                else:
                    raise FormatError(f"{self._path}: message on {ref.topic} at {ref.log_ns} ns vanished")
        return self._images(decoded["rgb"], decoded["depth"])

    def __iter__(self) -> Iterator[Frame]:
        if not len(self):
            return
        wanted: dict[_MessageRef, list[tuple[int, str]]] = {}
        for i, (rgb, depth) in enumerate(zip(self._rgb_refs, self._depth_refs, strict=True)):
            wanted.setdefault(rgb, []).append((i, "rgb"))
            wanted.setdefault(depth, []).append((i, "depth"))
        topics = {self._rgb_refs[0].topic, self._depth_refs[0].topic}
        pending: dict[int, dict[str, Any]] = {}
        next_frame = 0
        with self._open() as reader:
            connections = [c for c in reader.connections if c.topic in topics]
            for connection, log_ns, raw in reader.messages(connections):
                msg = reader.deserialize(raw, connection.msgtype)
                for i, role in wanted.pop(_MessageRef(connection.topic, log_ns, _stamp_or_log(msg, log_ns)), ()):
                    pending.setdefault(i, {})[role] = msg
                while len(pending.get(next_frame, ())) == 2:
                    msgs = pending.pop(next_frame)
                    yield self._frame(next_frame, self._images(msgs["rgb"], msgs["depth"]))
                    next_frame += 1
        if next_frame < len(self):
            raise FormatError(f"{self._path}: messages of frame {next_frame} not found on a second pass")

    def _images(self, rgb_msg: Any, depth_msg: Any) -> FrameImages:
        where, fix = str(self._path), self._rectifier
        rgb = rgb_image(rgb_msg, where)
        depth = depth_image(depth_msg, where)
        K = self.meta.intrinsics
        raw_depth_wh = fix.depth_size_wh or (K.width, K.height)
        for what, image, (w, h) in (("colour", rgb, (K.width, K.height)), ("depth", depth, raw_depth_wh)):
            if image.shape[:2] != (h, w):
                raise InputError(
                    f"{where}: a {what} image is {image.shape[1]}x{image.shape[0]}, the first one was {w}x{h}"
                )
        if fix.colour_maps is not None:
            rgb = remap_colour(rgb, fix.colour_maps)
        if fix.depth_maps is not None:
            depth = remap_depth(depth, fix.depth_maps)
        if fix.registration is not None:
            depth = register_depth(depth, *fix.registration)
        return FrameImages(rgb, depth, None)


# ------------------------------------------------------------------------------------------ the camera mount


def mount_from_xyz_rpy(values: list[float] | tuple[float, ...] | np.ndarray) -> np.ndarray:
    """(4, 4) T_base_camera from x, y, z (metres) and roll, pitch, yaw (degrees) of the camera body frame.

    The body frame is a ROS camera_link (x forward, y left, z up); roll, pitch, yaw turn it about the base's fixed x,
    y, z axes in that order (ROS RPY), so 0, 0, 0 looks straight ahead and a positive pitch looks down. The optical
    frame (x right, y down, z forward), which T_base_camera maps, follows by the fixed camera_link → optical rotation.
    """
    x, y, z, roll, pitch, yaw = (float(v) for v in values)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix() @ R_LINK_OPTICAL
    T[:3, 3] = [x, y, z]
    return T


def mount_rpy_deg(T_base_camera: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw in degrees of a mount, in the convention of `mount_from_xyz_rpy`."""
    R_base_link = np.asarray(T_base_camera, dtype=np.float64)[:3, :3] @ R_LINK_OPTICAL.T
    return Rotation.from_matrix(R_base_link).as_euler("xyz", degrees=True)


def _chain_source(tree: TfTree, chain: TfChain) -> str:
    if tree.is_static(chain):
        return f"tf static: {describe_chain(chain)}"
    return f"tf (moving links at the sample nearest the first colour image): {describe_chain(chain)}"


def _frames_seen(tree: TfTree) -> str:
    return ", ".join(sorted(tree.frames_seen)) or "none"


def _mount_from_tf(
    path: Path, tree: TfTree, base: str, colour_frame: str, rgb_topic: str, t_ns: int
) -> tuple[np.ndarray, str]:
    """T_base_camera (4, 4) from the tf chain base → the colour images' frame, and where it came from."""
    if not colour_frame:
        raise InputError(
            f"{path}: the colour images on {rgb_topic} have no header.frame_id, so their mount cannot be looked up in "
            "tf; give --camera-mount x,y,z,roll,pitch,yaw"
        )
    chain = tree.chain(base, colour_frame)
    if chain is None:
        raise InputError(
            f"{path}: no transform from {base} to {colour_frame} in /tf_static or /tf (frames seen: "
            f"{_frames_seen(tree)}); give --camera-mount x,y,z,roll,pitch,yaw or --base-frame"
        )
    return tree.transforms(chain, np.array([t_ns]), nearest=True)[0], _chain_source(tree, chain)


# ------------------------------------------------------------------------------------------ camera models


def _colour_camera(
    path: Path, info: CameraInfo, size_wh: tuple[int, int], *, rectified: bool
) -> tuple[CameraIntrinsics, tuple[np.ndarray, np.ndarray] | None, dict[str, Any], dict[str, Any]]:
    """The colour camera's pinhole intrinsics, the remap tables that undistort its images (None: nothing to undo),
    and the report's intrinsics and distortion entries."""
    K = info.matrix(rectified)
    intrinsics = CameraIntrinsics(
        size_wh[0], size_wh[1], float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    )
    distortion = _distortion_extras(path, info, rectified)
    maps = undistort_maps(K, info.D, size_wh) if distortion["undistorted"] else None
    note = " (P: the topic is rectified)" if rectified else ""
    return intrinsics, maps, {"from": f"CameraInfo {info.topic}{note}"}, distortion


def _depth_registration(
    path: Path,
    tree: TfTree,
    info: CameraInfo,
    depth_topic: str,
    colour_frame: str,
    intrinsics: CameraIntrinsics,
    t_ns: int,
) -> tuple[
    tuple[np.ndarray, np.ndarray] | None,
    tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]],
    dict[str, Any],
]:
    """For depth not registered to colour: the remap tables that undistort it in its own camera (or None), the
    registration's arguments (K_depth, T_colour_depth, K_colour, colour size) and the report's depth entry."""
    rectified = "rect" in depth_topic.lower()
    K_depth = info.matrix(rectified)
    distortion = _distortion_extras(path, info, rectified)
    maps = undistort_maps(K_depth, info.D, (info.width, info.height)) if distortion["undistorted"] else None
    chain = tree.chain(colour_frame, info.frame_id)
    if chain is None:
        raise InputError(
            f"{path}: depth ({info.frame_id or 'no frame_id'}) is not registered to colour ({colour_frame}) and there "
            f"is no transform between them in /tf_static or /tf (frames seen: {_frames_seen(tree)}); record an "
            "aligned depth topic or name it in io.rosbag.depth_topic"
        )
    T_colour_depth = tree.transforms(chain, np.array([t_ns]), nearest=True)[0]
    report = {
        "registration": f"registered to colour from {info.frame_id} ({_chain_source(tree, chain)})",
        "baseline_m": float(np.linalg.norm(T_colour_depth[:3, 3])),
        "depth_camera_info": info.topic,
        "depth_distortion": distortion,
    }
    return maps, (K_depth, T_colour_depth, intrinsics.K, (intrinsics.width, intrinsics.height)), report


# ------------------------------------------------------------------------------------------ topics


class _FirstMessages:
    """The first message of a topic, deserialised, read once (to learn a topic's encoding, frame_id and size)."""

    def __init__(self, reader: Any, connections: dict[str, list[Any]]) -> None:
        self._reader = reader
        self._connections = connections
        self._first: dict[str, Any] = {}

    def __call__(self, topic: str) -> Any:
        if topic not in self._first:
            message = next(iter(self._reader.messages(connections=self._connections[topic])), None)
            msg = None if message is None else self._reader.deserialize(message[2], message[0].msgtype)
            if msg is not None and message[0].msgtype == COMPRESSED_IMAGE_TYPE:
                msg = decoded_image(msg, f"{topic}, its first message")
            self._first[topic] = msg
        return self._first[topic]


def _image_topic(
    path: Path,
    role: str,
    key: str,
    named: str,
    topics: dict[str, str | None],
    first: _FirstMessages,
    found: dict[str, str],
) -> str:
    """The colour or depth topic: the one named in io.rosbag.`key`, checked, or the one found by encoding."""
    encodings = RGB_ENCODINGS if role == "colour" else DEPTH_ENCODINGS
    if named:
        if named not in topics:
            raise InputError(f"{path}: topic {named} (io.rosbag.{key}) is not in the bag; it has: {_listing(topics)}")
        if topics[named] not in IMAGE_TYPES:
            raise InputError(f"{path}: topic {named} carries {topics[named]}, expected {' or '.join(IMAGE_TYPES)}")
        msg = first(named)
        if msg is None:
            raise InputError(f"{path}: no messages on {named}")
        if (msg.encoding.lower() if role == "colour" else msg.encoding) not in encodings:
            raise InputError(
                f"{path}: {role} encoding {msg.encoding!r} on {named} not supported ({', '.join(encodings)})"
            )
        return named
    images = sorted(t for t, m in topics.items() if m in IMAGE_TYPES)
    if role == "colour":
        candidates = [t for t in images if first(t) is not None and first(t).encoding.lower() in RGB_ENCODINGS]
        preferences: tuple[tuple[str, ...], ...] = (("color", "colour", "rgb"),)
    else:
        encodings = FOUND_DEPTH_ENCODINGS
        candidates = [t for t in images if first(t) is not None and first(t).encoding in encodings]
        preferences = (("depth",), ("aligned",))
    # a stream recorded both raw and through image_transport (…/image_raw and …/image_raw/compressed): the raw one
    candidates = [
        t for t in candidates if not (topics[t] == COMPRESSED_IMAGE_TYPE and t.rsplit("/", 1)[0] in candidates)
    ]
    if not candidates:
        seen = ", ".join(f"{t} ({first(t).encoding if first(t) is not None else 'empty'})" for t in images) or "none"
        raise InputError(
            f"{path}: no {role} image topic (sensor_msgs/Image or CompressedImage in {', '.join(encodings)}); image "
            f"topics: {seen}"
        )
    return _one_of(path, role, key, candidates, preferences, found)


def _one_of(
    path: Path,
    role: str,
    key: str,
    candidates: list[str],
    preferences: tuple[tuple[str, ...], ...],
    found: dict[str, str],
) -> str:
    """The single candidate left after narrowing to names with each preference's words in turn; else InputError."""
    for words in preferences:
        narrowed = [t for t in candidates if any(w in t.lower() for w in words)]
        candidates = narrowed or candidates
    if len(candidates) > 1:
        raise InputError(
            f"{path}: several {role} topics ({', '.join(candidates)}); name one with --set io.rosbag.{key}=TOPIC"
        )
    found[key] = candidates[0]
    return candidates[0]


def _camera_info(
    path: Path,
    role: str,
    key: str,
    named: str,
    image_topic: str,
    frame_id: str,
    topics: dict[str, str | None],
    first: _FirstMessages,
    found: dict[str, str],
) -> CameraInfo:
    """The CameraInfo of the colour or depth camera: named, else the image topic's sibling camera_info, else the
    one whose frame_id is the images'."""
    if named:
        if topics.get(named) != CAMERA_INFO_TYPE:
            carries = "is not in the bag" if named not in topics else f"carries {topics[named]}"
            raise InputError(f"{path}: topic {named} (io.rosbag.{key}) {carries}, expected {CAMERA_INFO_TYPE}")
        topic = named
    else:
        infos = sorted(t for t, m in topics.items() if m == CAMERA_INFO_TYPE)
        if not infos:
            raise InputError(
                f"{path}: no {CAMERA_INFO_TYPE} topic in the bag: the {role} camera's intrinsics are unknown"
            )
        sibling = image_topic.rsplit("/", 1)[0] + "/camera_info"
        if sibling in infos:
            topic = sibling
        else:
            same_frame = [t for t in infos if first(t) is not None and frame_name(first(t).header.frame_id) == frame_id]
            if not same_frame:
                listing = ", ".join(
                    f"{t} ({frame_name(first(t).header.frame_id) if first(t) is not None else 'empty'})" for t in infos
                )
                raise InputError(
                    f"{path}: no CameraInfo for the {role} images on {image_topic} (frame {frame_id or 'none'}); "
                    f"CameraInfo topics: {listing}; name one with --set io.rosbag.{key}=TOPIC"
                )
            topic = _one_of(path, f"{role} CameraInfo", key, same_frame, (), found)
        found[key] = topic
    msg = first(topic)
    if msg is None:
        raise InputError(f"{path}: no message on {topic}: the {role} camera's intrinsics are unknown")
    return CameraInfo.from_msg(topic, msg)


def _distortion_extras(path: Path, info: CameraInfo, rectified: bool) -> dict[str, Any]:
    """The distortion as the report gives it; a model that cannot be undistorted is an InputError."""
    out = {"model": info.model or "(none)", "coefficients": info.D.tolist(), "undistorted": False}
    if rectified:
        out["note"] = "topic already rectified: not undistorted"
        return out
    problem = distortion_problem(info.model, info.D)
    if problem:
        raise InputError(f"{path}: CameraInfo on {info.topic}: {problem}")
    out["undistorted"] = bool(np.any(info.D))
    return out


def _odometry_topic(path: Path, named: str, topics: dict[str, str | None], found: dict[str, str]) -> str | None:
    """The Odometry topic named or found by type; None when the bag has none (odometry then comes from tf)."""
    if named:
        if topics.get(named) != ODOMETRY_TYPE:
            carries = "is not in the bag" if named not in topics else f"carries {topics[named]}"
            raise InputError(f"{path}: topic {named} (io.rosbag.odom_topic) {carries}, expected {ODOMETRY_TYPE}")
        return named
    candidates = sorted(t for t, m in topics.items() if m == ODOMETRY_TYPE)
    if not candidates:
        return None
    return _one_of(path, "odometry", "odom_topic", candidates, (), found)


def _detections_topic(path: Path, named: str, topics: dict[str, str | None], found: dict[str, str]) -> str | None:
    """The Detection2DArray topic named or found by type; None when the bag has none."""
    if named:
        if topics.get(named) != DETECTIONS_TYPE:
            carries = "is not in the bag" if named not in topics else f"carries {topics[named]}"
            raise InputError(
                f"{path}: topic {named} (io.rosbag.detections_topic) {carries}, expected {DETECTIONS_TYPE}"
            )
        return named
    candidates = sorted(t for t, m in topics.items() if m == DETECTIONS_TYPE)
    return _one_of(path, "detections", "detections_topic", candidates, (), found) if candidates else None


def _detections_at_frames(
    messages: list[tuple[int, Any]],
    frames: list[_MessageRef],
    max_dt_s: float,
    intrinsics: CameraIntrinsics,
    lens: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Each frame's Detection2DArray (the nearest in time, within `max_dt_s`, one message per frame) as a line of the
    detections file at the frame's stamp, boxes moved into the undistorted image when `lens` (K, D) undistorts the
    colour images; and the report's entry."""
    lines: list[dict[str, Any]] = []
    if messages and frames:
        stamps = np.array([s for s, _ in messages], dtype=np.int64)
        frame_t = np.array([(r.stamp_ns - frames[0].stamp_ns) / 1e9 for r in frames])
        msg_t = (stamps - frames[0].stamp_ns) / 1e9
        i_frame, i_msg = associate_nearest(frame_t, msg_t, max_dt_s, one_to_one=True)
        for i, j in zip(i_frame, i_msg, strict=True):
            found = (_detection_entry(d, intrinsics, lens) for d in messages[j][1].detections)
            lines.append({"timestamp": frames[i].stamp_ns / 1e9, "detections": [d for d in found if d is not None]})
    entry = {
        "messages": len(messages),
        "frames_with_detections": len(lines),
        "detections": sum(len(line["detections"]) for line in lines),
    }
    return lines, entry


def _detection_entry(
    detection: Any, intrinsics: CameraIntrinsics, lens: tuple[np.ndarray, np.ndarray] | None
) -> dict[str, Any] | None:
    """One vision_msgs/Detection2D (version 4: hypothesis.class_id, bbox.center.position; versions 1-3: id,
    bbox.center.x) as a detections-file entry of its best hypothesis; None when it has no hypothesis."""
    if not len(detection.results):
        return None
    scored = []
    for result in detection.results:
        hypothesis = getattr(result, "hypothesis", result)
        label = getattr(hypothesis, "class_id", None)
        scored.append((float(hypothesis.score), str(label if label is not None else hypothesis.id)))
    score, label = max(scored)
    centre = getattr(detection.bbox.center, "position", detection.bbox.center)
    cx, cy = float(centre.x), float(centre.y)
    half = np.array([float(detection.bbox.size_x), float(detection.bbox.size_y)]) / 2
    corners = np.array([[cx, cy]]) + half * np.array([[-1, -1], [1, -1], [-1, 1], [1, 1]])
    if lens is not None:
        K = np.asarray(lens[0], dtype=np.float64).reshape(3, 3)
        corners = cv2.undistortPoints(corners.reshape(-1, 1, 2), K, lens[1], P=K).reshape(-1, 2)
    size = [intrinsics.width, intrinsics.height]
    x0, y0 = np.clip(corners.min(axis=0), 0, size)
    x1, y1 = np.clip(corners.max(axis=0), 0, size)
    return {"label": label, "score": min(max(score, 0.0), 1.0), "box": [float(x0), float(y0), float(x1), float(y1)]}


def _listing(topics: dict[str, str | None]) -> str:
    return ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"


def _bag_format(path: Path) -> str:
    if path.suffix == ".bag":
        return "ROS 1"
    files = [path] if path.is_file() else sorted(path.iterdir())
    storage = next((p.suffix for p in files if p.suffix in (".db3", ".mcap")), "")
    return {".db3": "ROS 2 (sqlite3)", ".mcap": "ROS 2 (mcap)"}.get(storage, "ROS 2")


# ------------------------------------------------------------------------------------------ odometry


def _odometry_samples(
    path: Path,
    config: RosbagConfig,
    odom_topic: str | None,
    odom_msgs: list[tuple[int, Any]],
    tree: TfTree,
    max_tilt_deg: float,
    needed: bool = True,
) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(M,) stamps in ns, sorted and unique, (M, 3) planar T_odom_base, and where they came from; None for a bag
    with no odometry when it is not `needed`."""
    base = frame_name(config.base_frame)
    if odom_topic is not None:
        if not odom_msgs:
            raise InputError(f"{path}: no messages on {odom_topic}")
        stamps = np.array([_stamp_or_log(msg, log_ns) for log_ns, msg in odom_msgs], dtype=np.int64)
        poses = [m.pose.pose for _, m in odom_msgs]
        T = transform_matrix(
            np.array([(p.position.x, p.position.y, p.position.z) for p in poses]),
            np.array([(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w) for p in poses]),
        )
        child = frame_name(odom_msgs[0][1].child_frame_id)
        source = odom_topic
        if child and child != base:
            chain = tree.chain(child, base)
            if chain is None or not tree.is_static(chain):
                raise InputError(
                    f"{path}: odometry on {odom_topic} is of frame {child}, not of the base frame {base}, and "
                    f"/tf_static has no fixed transform between them; give --base-frame {child}"
                )
            T = T @ tree.transforms(chain, stamps[:1])[0]
            source += f" (moved from {child} to {base} through tf)"
        what = f"{path} {odom_topic}"
    else:
        odom = frame_name(config.odom_frame)
        chain = tree.chain(odom, base)
        stamps = np.zeros(0, np.int64) if chain is None else tree.dynamic_stamps(chain)
        if not len(stamps) and not needed:
            return None
        if not len(stamps):
            raise InputError(
                f"{path}: no {ODOMETRY_TYPE} topic and no moving {odom} → {base} transform on /tf (frames seen: "
                f"{_frames_seen(tree)}); name the odometry with --set io.rosbag.odom_topic=TOPIC or "
                "io.rosbag.odom_frame=FRAME"
            )
        assert chain is not None
        T = tree.transforms(chain, stamps)
        source = f"tf {describe_chain(chain)}"
        what = f"{path} tf {odom} → {base}"
    order = np.argsort(stamps, kind="stable")
    stamps, T = stamps[order], T[order]
    keep = np.r_[True, stamps[1:] != stamps[:-1]]
    planar = planar_from_matrices(T[keep], what=what, max_tilt_deg=max_tilt_deg)
    return stamps[keep], planar, source


def interpolate_planar(t_samples: np.ndarray, poses: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """(N, 3) planar poses at (N,) query times from (M,) sorted sample times and (M, 3) x, y, yaw: x and y linear,
    yaw along the shorter arc; NaN rows outside the samples' span."""
    t_samples, poses, t_query = np.asarray(t_samples, float), np.asarray(poses, float), np.asarray(t_query, float)
    out = np.full((len(t_query), 3), np.nan)
    inside = (t_query >= t_samples[0]) & (t_query <= t_samples[-1])
    if len(t_samples) == 1:
        out[inside] = poses[0]
        return out
    i = np.clip(np.searchsorted(t_samples, t_query[inside], side="right") - 1, 0, len(t_samples) - 2)
    a = (t_query[inside] - t_samples[i]) / (t_samples[i + 1] - t_samples[i])
    step = poses[i + 1] - poses[i]
    step[:, 2] = wrap_angle(step[:, 2])
    out[inside] = poses[i] + a[:, None] * step
    out[inside, 2] = wrap_angle(out[inside, 2])
    return out


# ------------------------------------------------------------------------------------------ association


def _associate(
    path: Path,
    config: RosbagConfig,
    rgb_refs: list[_MessageRef],
    depth_refs: list[_MessageRef],
    odom_stamps_ns: np.ndarray | None,
    odom_planar: np.ndarray | None,
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray | None, dict[str, float], dict[str, int]]:
    """Colour ↔ depth (nearest, one-to-one, within max_sync_dt_s) and the odometry interpolated at each colour stamp
    (None without odometry).

    Returns the kept (colour, depth) indices, (K, 3) odometry, the time offsets and the drops by reason."""
    # seconds from the first colour stamp: float64 keeps nanoseconds there, unlike seconds since 1970
    t0 = rgb_refs[0].stamp_ns
    rgb_t = np.array([(r.stamp_ns - t0) / 1e9 for r in rgb_refs])
    depth_t = np.array([(r.stamp_ns - t0) / 1e9 for r in depth_refs])
    dropped: Counter[str] = Counter()

    i_rgb, i_depth = associate_nearest(rgb_t, depth_t, config.max_sync_dt_s, one_to_one=True)
    if len(i_rgb) == 0:
        nearest = np.abs(depth_t[np.clip(np.searchsorted(depth_t, rgb_t), 0, len(depth_t) - 1)] - rgb_t)
        nearest = np.minimum(nearest, np.abs(depth_t[np.clip(np.searchsorted(depth_t, rgb_t) - 1, 0, None)] - rgb_t))
        raise InputError(
            f"{path}: colour ({rgb_refs[0].topic}) and depth ({depth_refs[0].topic}) are never within "
            f"io.rosbag.max_sync_dt_s = {config.max_sync_dt_s:g} s of each other: the nearest depth image is "
            f"{np.min(nearest):.3f} s to {np.max(nearest):.3f} s (median {np.median(nearest):.3f} s) from each colour "
            "image; the streams are not synchronised"
        )
    dropped[f"no depth image within {config.max_sync_dt_s:g} s"] += len(rgb_t) - len(i_rgb)
    if odom_stamps_ns is None or odom_planar is None:
        depth_dt = np.abs(depth_t[i_depth] - rgb_t[i_rgb])
        sync = {"depth_dt_median_s": float(np.median(depth_dt)), "depth_dt_max_s": float(np.max(depth_dt))}
        return (i_rgb, i_depth), None, sync, {reason: n for reason, n in dropped.items() if n}
    odom_t = (odom_stamps_ns - t0) / 1e9

    odom = interpolate_planar(odom_t, odom_planar, rgb_t[i_rgb])
    outside = np.isnan(odom[:, 0])
    dropped["outside the odometry's time span"] += int(outside.sum())
    if outside.all():
        raise InputError(
            f"{path}: no colour image lies within the odometry's time span (colour {rgb_t[0]:.3f} s to "
            f"{rgb_t[-1]:.3f} s, odometry {odom_t[0]:.3f} s to {odom_t[-1]:.3f} s from the first colour image)"
        )
    # the odometry samples around each colour stamp: a long gap between them is a stream that stopped
    right = np.clip(np.searchsorted(odom_t, rgb_t[i_rgb]), 0, len(odom_t) - 1)
    left = np.clip(right - 1, 0, len(odom_t) - 1)
    gap = np.where(odom_t[right] == rgb_t[i_rgb], 0.0, odom_t[right] - odom_t[left])
    across_gap = ~outside & (gap > config.max_odom_gap_s)
    dropped[f"odometry gap over {config.max_odom_gap_s:g} s"] += int(across_gap.sum())
    keep = ~outside & ~across_gap
    if not keep.any():
        raise InputError(f"{path}: every colour image falls in an odometry gap over {config.max_odom_gap_s:g} s")
    i_rgb, i_depth, odom = i_rgb[keep], i_depth[keep], odom[keep]

    depth_dt = np.abs(depth_t[i_depth] - rgb_t[i_rgb])
    odom_dt = np.minimum(np.abs(odom_t[left[keep]] - rgb_t[i_rgb]), np.abs(odom_t[right[keep]] - rgb_t[i_rgb]))
    sync = {
        "depth_dt_median_s": float(np.median(depth_dt)),
        "depth_dt_max_s": float(np.max(depth_dt)),
        "odom_dt_median_s": float(np.median(odom_dt)),
        "odom_dt_max_s": float(np.max(odom_dt)),
        "odom_interpolated": True,
    }
    drops = {reason: n for reason, n in dropped.items() if n}
    if drops:
        log.info("%s: %d of %d colour images dropped (%s)", path, sum(drops.values()), len(rgb_t), drops)
    return (i_rgb, i_depth), odom, sync, drops


def _with_stamps(path: Path, refs: list[_MessageRef], topic: str) -> list[_MessageRef]:
    """Image references sorted by stamp, of repeated stamps the first (logged)."""
    out: list[_MessageRef] = []
    for ref in sorted(refs, key=lambda r: (r.stamp_ns, r.log_ns)):
        if out and ref.stamp_ns == out[-1].stamp_ns:
            log.warning("%s: %s has two images stamped %d ns; keeping the first", path, topic, ref.stamp_ns)
            continue
        out.append(ref)
    if not out:
        raise InputError(f"{path}: no messages on {topic}")
    return out


def _stamp_or_log(msg: Any, log_ns: int) -> int:
    """A message's header stamp in ns; its log time when the header is stamped zero (some drivers never set it)."""
    stamp = stamp_ns(msg.header.stamp)
    return stamp if stamp else log_ns


# ------------------------------------------------------------------------------------------ images


@dataclass(frozen=True)
class DecodedImage:
    """A sensor_msgs/CompressedImage decoded: the fields of the sensor_msgs/Image it was."""

    header: Any
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray


# compressedDepth's header (image_transport's ConfigHeader): int32 format, float32 depthQuantA, depthQuantB
_COMPRESSED_DEPTH_HEADER = np.dtype([("format", "<i4"), ("quant_a", "<f4"), ("quant_b", "<f4")])


def decoded_image(msg: Any, where: str) -> Any:
    """A sensor_msgs/CompressedImage as the Image it was (`DecodedImage`); an Image as it is.

    `compressed` (format e.g. "rgb8; jpeg compressed bgr8", or just "jpeg"): OpenCV decodes it unchanged, 8-bit
    colour as bgr8 / bgra8, 16-bit single channel as 16UC1. `compressedDepth` ("16UC1; compressedDepth png" or
    "32FC1; compressedDepth png"): a 12-byte header before a 16-bit PNG; 16UC1 is millimetres as they were, 32FC1
    was quantised as inverse depth, depth = quant_a / (value − quant_b) with 0 no return.
    """
    if not hasattr(msg, "format"):
        return msg
    fmt = str(msg.format)
    data = np.asarray(msg.data, dtype=np.uint8)
    if "compresseddepth" in fmt.lower():
        if "rvl" in fmt.lower():
            raise InputError(f"{where}: depth compressed with RVL ({fmt!r}) is not read: record it raw or as png")
        if data.size <= _COMPRESSED_DEPTH_HEADER.itemsize:
            raise FormatError(f"{where}: compressedDepth message of {data.size} bytes has no image")
        header = data[: _COMPRESSED_DEPTH_HEADER.itemsize].view(_COMPRESSED_DEPTH_HEADER)[0]
        pixels = _imdecode(data[_COMPRESSED_DEPTH_HEADER.itemsize :], fmt, where)
        if pixels.dtype != np.uint16 or pixels.ndim != 2:
            raise FormatError(f"{where}: compressedDepth {fmt!r} did not decode to a 16-bit single-channel image")
        if fmt.split(";")[0].strip() == "32FC1":
            value = pixels.astype(np.float32)
            with np.errstate(divide="ignore"):
                depth = np.float32(header["quant_a"]) / (value - np.float32(header["quant_b"]))
            depth[pixels == 0] = np.nan
            return _as_image(msg.header, depth.astype(np.float32), "32FC1")
        return _as_image(msg.header, pixels, "16UC1")
    pixels = _imdecode(data, fmt, where)
    if pixels.dtype == np.uint16 and pixels.ndim == 2:
        return _as_image(msg.header, pixels, "16UC1")
    if pixels.dtype == np.uint8 and pixels.ndim == 3:
        return _as_image(msg.header, pixels, "bgr8" if pixels.shape[2] == 3 else "bgra8")
    shape = "x".join(str(n) for n in pixels.shape)
    return _as_image(msg.header, pixels, f"{pixels.dtype}, shape {shape}")


def _imdecode(data: np.ndarray, fmt: str, where: str) -> np.ndarray:
    pixels = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise FormatError(f"{where}: a CompressedImage ({fmt!r}) that OpenCV cannot decode")
    return pixels


def _as_image(header: Any, pixels: np.ndarray, encoding: str) -> DecodedImage:
    h, w = pixels.shape[:2]
    rows = np.ascontiguousarray(pixels).reshape(h, -1).view(np.uint8)
    return DecodedImage(header, h, w, encoding, 0 if np.little_endian else 1, rows.shape[1], rows.reshape(-1))


def rgb_image(msg: Any, where: str) -> np.ndarray:
    """sensor_msgs/Image (or a CompressedImage, `decoded_image`) in rgb8, bgr8, rgba8, bgra8 → (H, W, 3) uint8 RGB."""
    msg = decoded_image(msg, where)
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
    """sensor_msgs/Image (or a CompressedImage, `decoded_image`) in 16UC1 / mono16 (mm) or 32FC1 (m) → (H, W)
    float32 metres, NaN = no return."""
    msg = decoded_image(msg, where)
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


ROS1_MAGIC = b"#ROSBAG V2.0\n"
"""The first line of a ROS 1 bag (format 2.0, the only one rosbags reads)."""


def _not_a_bag(path: Path) -> str | None:
    """Why an existing path cannot be a bag the reader opens (None: it may be one): a folder needs the metadata.yaml
    that `ros2 bag record` writes; a single file must be a ROS 1 .bag or a ROS 2 .db3 or .mcap storage file."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return None
        storage = sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
        if storage:
            return f"no metadata.yaml in the folder (open the storage file {path / storage[0]} instead)"
        ros1 = sorted(p.name for p in path.iterdir() if p.suffix == ".bag")
        if ros1:
            return f"it holds a ROS 1 bag ({ros1[0]}); open that file instead"
        return "the folder has no metadata.yaml (a ROS 2 bag is a folder with metadata.yaml, or a .db3 or .mcap file)"
    if path.suffix not in (".bag", ".db3", ".mcap"):
        return (
            f"a {path.suffix or 'suffix-less'} file; expected a bag folder with metadata.yaml, a .db3 or .mcap file, "
            "or a ROS 1 .bag file"
        )
    if path.suffix == ".bag":
        try:
            with path.open("rb") as f:
                head = f.read(len(ROS1_MAGIC))
        except OSError as exc:
            return f"cannot be read ({exc.strerror or exc})"
        if head != ROS1_MAGIC:
            return "it does not begin with '#ROSBAG V2.0' (the first line of every ROS 1 bag of format 2.0)"
    return None


# ------------------------------------------------------------------------------------------ the report


def conversion_report(extras: dict[str, Any]) -> list[str]:
    """What a bag conversion assumed (a rosbag sequence's `meta.extras`), as lines for a person to check."""
    topics, mount, K = extras["topics"], extras["camera_mount"], extras["intrinsics"]
    found = set(topics.get("found_by_type", []))

    def named(role: str, key: str) -> str:
        return f"{topics[role]}" + (" (found by type)" if key in found else "")

    lines = [
        f"{extras['bag_format']} bag; colour {named('rgb', 'rgb_topic')}, depth {named('depth', 'depth_topic')}, "
        "odometry " + (named("odometry", "odom_topic") if topics["odometry"] else "none in the bag"),
    ]
    x, y, z = mount["xyz_m"]
    roll, pitch, yaw = mount["rpy_deg"]
    lines.append(
        f"camera mount {mount['frames']}: x {x:.3f} y {y:.3f} z {z:.3f} m, roll {roll:.2f}° pitch {pitch:.2f}° "
        f"yaw {yaw:.2f}° (from {mount['from']})"
    )
    distortion = extras["distortion"]
    state = "undistorted" if distortion["undistorted"] else distortion.get("note", "nothing to undistort")
    lines.append(
        f"intrinsics {K['width']}x{K['height']} fx {K['fx']:.2f} fy {K['fy']:.2f} cx {K['cx']:.2f} cy {K['cy']:.2f} "
        f"(from {K['from']}); distortion {distortion['model']}: {state}"
    )
    lines.append(f"depth: {extras['depth']['registration']}")
    sync = extras["sync"]
    odometry = (
        f"; odometry interpolated, nearest sample median {sync['odom_dt_median_s'] * 1e3:.1f} ms, max "
        f"{sync['odom_dt_max_s'] * 1e3:.1f} ms"
        if "odom_dt_median_s" in sync
        else ""
    )
    lines.append(
        f"time offsets: depth |Δt| median {sync['depth_dt_median_s'] * 1e3:.1f} ms, max "
        f"{sync['depth_dt_max_s'] * 1e3:.1f} ms{odometry}"
    )
    frames = extras["frames"]
    dropped = "; ".join(f"{n} {reason}" for reason, n in frames["dropped"].items())
    lines.append(
        f"{frames['kept']} of {frames['colour_images']} colour images synchronised"
        + (f"; dropped: {dropped}" if dropped else "")
    )
    return lines
