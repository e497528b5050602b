"""Bags the rosbag tests write themselves with the `rosbags` writers: ROS 2 (sqlite3 or mcap) and ROS 1.

`TestBag` collects messages by log time and writes them sorted when closed; every message is built from the writer's
own typestore (ROS 2 Humble, or ROS 1 Noetic with tf2_msgs/TFMessage registered), so the reader sees what a real
recorder would have written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bimfactor.io.rosbag import ros2_typestore

FORMATS = ("sqlite3", "mcap", "ros1")
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera_link → optical frame
TRANSPORT_NS = 1_000_000  # log time = stamp + 1 ms


def rigid(xyz: tuple[float, float, float] = (0.0, 0.0, 0.0), R: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = xyz
    return T


def rpy_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ROS RPY (fixed axes x, y, z) in degrees → (3, 3)."""
    return Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()


class TestBag:
    """A bag being written: `path` is a folder (ROS 2) or a .bag file (ROS 1)."""

    __test__ = False  # not a pytest class

    def __init__(self, path: Path, fmt: str = "sqlite3") -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        assert fmt in FORMATS
        self.path, self.fmt = Path(path), fmt
        self.ros1 = fmt == "ros1"
        # ROS 2: Humble's types and vision_msgs 4 (the reader's typestore)
        self.ts = get_typestore(Stores.ROS1_NOETIC) if self.ros1 else ros2_typestore()
        if self.ros1:
            self.ts.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
            )
        self.T = self.ts.types
        self._messages: list[tuple[int, str, str, Any]] = []

    # ---------------------------------------------------------------- messages

    def header(self, t_ns: int, frame_id: str) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        Header = self.T["std_msgs/msg/Header"]
        return Header(seq=0, stamp=stamp, frame_id=frame_id) if self.ros1 else Header(stamp=stamp, frame_id=frame_id)

    def add(self, topic: str, msgtype: str, msg: Any, t_ns: int) -> None:
        self._messages.append((t_ns + TRANSPORT_NS, topic, msgtype, msg))

    def image(self, topic: str, t_ns: int, pixels: np.ndarray, encoding: str, frame_id: str, pad: int = 0) -> None:
        """An Image message; `pad` extra bytes at the end of every row (step > width · pixel size)."""
        h, w = pixels.shape[:2]
        rows = np.ascontiguousarray(pixels).reshape(h, -1).view(np.uint8)
        rows = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1)
        msg = self.T["sensor_msgs/msg/Image"](
            header=self.header(t_ns, frame_id),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=rows.shape[1],
            data=rows.ravel().copy(),
        )
        self.add(topic, "sensor_msgs/msg/Image", msg, t_ns)

    def compressed(self, topic: str, t_ns: int, pixels: np.ndarray, fmt: str, frame_id: str) -> None:
        """A CompressedImage as image_transport writes it: `fmt` "rgb8; jpeg compressed bgr8" encodes an RGB image as
        JPEG, "16UC1; compressedDepth png" a millimetre image as compressedDepth (its 12-byte header, then PNG)."""
        import cv2

        if "compressedDepth" in fmt:
            ok, body = cv2.imencode(".png", pixels)
            header = np.array([(0, 0.0, 0.0)], dtype=[("f", "<i4"), ("a", "<f4"), ("b", "<f4")]).view(np.uint8)
            data = np.concatenate([header, body.ravel()])
        else:
            ok, body = cv2.imencode(".jpg", cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            data = body.ravel()
        assert ok
        msg = self.T["sensor_msgs/msg/CompressedImage"](header=self.header(t_ns, frame_id), format=fmt, data=data)
        self.add(topic, "sensor_msgs/msg/CompressedImage", msg, t_ns)

    def depth_mm(self, topic: str, t_ns: int, depth_m: np.ndarray, frame_id: str) -> None:
        """A 16UC1 depth image in millimetres (NaN → 0, no return)."""
        mm = np.nan_to_num(np.rint(np.asarray(depth_m, np.float64) * 1000.0), nan=0.0)
        self.image(topic, t_ns, np.clip(mm, 0, 65535).astype(np.uint16), "16UC1", frame_id)

    def camera_info(
        self,
        topic: str,
        t_ns: int,
        frame_id: str,
        size_wh: tuple[int, int],
        K: tuple[float, float, float, float],
        D: np.ndarray | None = None,
        model: str = "plumb_bob",
    ) -> None:
        fx, fy, cx, cy = K
        k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0])
        p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0])
        d = np.zeros(5) if D is None else np.asarray(D, float)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        matrices = dict(zip(names, (d, k, np.eye(3).ravel(), p), strict=True))
        msg = self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t_ns, frame_id),
            height=size_wh[1],
            width=size_wh[0],
            distortion_model=model,
            binning_x=0,
            binning_y=0,
            roi=roi,
            **matrices,
        )
        self.add(topic, "sensor_msgs/msg/CameraInfo", msg, t_ns)

    def tf(self, topic: str, t_ns: int, transforms: list[tuple[str, str, np.ndarray]]) -> None:
        """A TFMessage of (parent, child, T_parent_child) entries."""
        V, Q = self.T["geometry_msgs/msg/Vector3"], self.T["geometry_msgs/msg/Quaternion"]
        entries = []
        for parent, child, T in transforms:
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            entries.append(
                self.T["geometry_msgs/msg/TransformStamped"](
                    header=self.header(t_ns, parent),
                    child_frame_id=child,
                    transform=self.T["geometry_msgs/msg/Transform"](
                        translation=V(x=T[0, 3], y=T[1, 3], z=T[2, 3]), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])
                    ),
                )
            )
        self.add(topic, "tf2_msgs/msg/TFMessage", self.T["tf2_msgs/msg/TFMessage"](transforms=entries), t_ns)

    def odometry(self, topic: str, t_ns: int, pose: np.ndarray, child: str = "base_link") -> None:
        """A nav_msgs/Odometry at planar pose (x, y, yaw)."""
        g = {n: self.T[f"geometry_msgs/msg/{n}"] for n in ("Point", "Quaternion", "Pose", "Vector3", "Twist")}
        x, y, yaw = (float(v) for v in pose)
        zero = g["Vector3"](x=0.0, y=0.0, z=0.0)
        msg = self.T["nav_msgs/msg/Odometry"](
            header=self.header(t_ns, "odom"),
            child_frame_id=child,
            pose=self.T["geometry_msgs/msg/PoseWithCovariance"](
                pose=g["Pose"](
                    position=g["Point"](x=x, y=y, z=0.0),
                    orientation=g["Quaternion"](x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)),
                ),
                covariance=np.zeros(36),
            ),
            twist=self.T["geometry_msgs/msg/TwistWithCovariance"](
                twist=g["Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
            ),
        )
        self.add(topic, "nav_msgs/msg/Odometry", msg, t_ns)

    def detections(self, topic: str, t_ns: int, frame_id: str, entries: list[dict[str, Any]]) -> None:
        """A vision_msgs/Detection2DArray (version 4) of detections-file entries (label, score, box x0 y0 x1 y1)."""
        T, header = self.T, self.header(t_ns, frame_id)
        covariance = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=np.zeros(36),
        )
        detections = []
        for e in entries:
            x0, y0, x1, y1 = e["box"]
            centre = T["vision_msgs/msg/Pose2D"](
                position=T["vision_msgs/msg/Point2D"](x=(x0 + x1) / 2, y=(y0 + y1) / 2), theta=0.0
            )
            hypothesis = T["vision_msgs/msg/ObjectHypothesis"](class_id=e["label"], score=e["score"])
            detections.append(
                T["vision_msgs/msg/Detection2D"](
                    header=header,
                    results=[T["vision_msgs/msg/ObjectHypothesisWithPose"](hypothesis=hypothesis, pose=covariance)],
                    bbox=T["vision_msgs/msg/BoundingBox2D"](center=centre, size_x=x1 - x0, size_y=y1 - y0),
                    id="",
                )
            )
        msg = T["vision_msgs/msg/Detection2DArray"](header=header, detections=detections)
        self.add(topic, "vision_msgs/msg/Detection2DArray", msg, t_ns)

    # ---------------------------------------------------------------- writing

    def write(self) -> Path:
        """Write every message, in log-time order, with the format's writer."""
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        if self.ros1:
            writer = Writer1(self.path)
        else:
            plugin = StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(self.path, version=9, storage_plugin=plugin)
        serialize = self.ts.serialize_ros1 if self.ros1 else self.ts.serialize_cdr
        with writer:
            connections: dict[str, Any] = {}
            for log_ns, topic, msgtype, msg in sorted(self._messages, key=lambda m: m[0]):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=self.ts)
                writer.write(connections[topic], log_ns, serialize(msg, msgtype))
        return self.path
