"""The ROS 2 bag reader on bags the test writes itself with rosbags' Writer: both depth encodings."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bimfactor.config import Config, RosbagConfig
from bimfactor.errors import FormatError, InputError
from bimfactor.io.rosbag import depth_image, read_rosbag, rgb_image
from bimfactor.io.sequence import read_sequence, write_sequence
from bimfactor.types import wrap_angle

rosbags = pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")
from rosbags.rosbag2 import Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

W, H = 32, 24
K = (25.0, 26.0, 15.5, 11.25)  # fx, fy, cx, cy
T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 Hz colour
N_FRAMES = 5


@pytest.fixture(scope="module")
def config(test_config: Config) -> RosbagConfig:
    """The default topics of bimfactor/configs/default.yaml."""
    return test_config.io.rosbag


def _stamp(ts, t_ns: int):
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000), frame_id="camera")


def _image(ts, t_ns: int, pixels: np.ndarray, encoding: str, pad: int = 0):
    """An Image message; `pad` extra bytes at the end of every row (step > width · pixel size)."""
    rows = pixels.reshape(H, -1).view(np.uint8)
    rows = np.concatenate([rows, np.zeros((H, pad), np.uint8)], axis=1)
    Image = ts.types["sensor_msgs/msg/Image"]
    return Image(
        header=_stamp(ts, t_ns),
        height=H,
        width=W,
        encoding=encoding,
        is_bigendian=0,
        step=rows.shape[1],
        data=rows.ravel().copy(),
    )


def _write_bag(path: Path, config: RosbagConfig, depth_encoding: str, topics: tuple[str, ...] = ()) -> dict:
    """Colour at 10 Hz (frame 3 has no depth), depth 3 ms later, odometry at 100 Hz, one CameraInfo."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(3)
    truth = {"stamps": [], "rgb": [], "depth": [], "odom": []}
    Odometry = ts.types["nav_msgs/msg/Odometry"]
    geo = {
        name: ts.types[f"geometry_msgs/msg/{name}"]
        for name in ("Point", "Quaternion", "Pose", "PoseWithCovariance", "Vector3", "Twist", "TwistWithCovariance")
    }
    CameraInfo = ts.types["sensor_msgs/msg/CameraInfo"]
    RegionOfInterest = ts.types["sensor_msgs/msg/RegionOfInterest"]
    topics = topics or (config.rgb_topic, config.depth_topic, config.camera_info_topic, config.odom_topic)
    with Writer(path, version=9) as writer:
        conns = {}
        types = {
            config.rgb_topic: "sensor_msgs/msg/Image",
            config.depth_topic: "sensor_msgs/msg/Image",
            config.camera_info_topic: "sensor_msgs/msg/CameraInfo",
            config.odom_topic: "nav_msgs/msg/Odometry",
        }
        for topic in topics:
            conns[topic] = writer.add_connection(topic, types[topic], typestore=ts)

        def write(topic: str, t_ns: int, msg) -> None:
            if topic in conns:
                writer.write(conns[topic], t_ns + 1_000_000, ts.serialize_cdr(msg, types[topic]))  # 1 ms transport

        info = CameraInfo(
            header=_stamp(ts, T0_NS),
            height=H,
            width=W,
            distortion_model="plumb_bob",
            d=np.zeros(5),
            k=np.array([K[0], 0, K[2], 0, K[1], K[3], 0, 0, 1.0]),
            r=np.eye(3).ravel(),
            p=np.zeros(12),
            binning_x=0,
            binning_y=0,
            roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        write(config.camera_info_topic, T0_NS, info)
        for k in range(50):  # odometry 100 Hz
            t_ns = T0_NS - 20_000_000 + k * 10_000_000
            x, y, yaw = 0.01 * k, -0.02 * k, wrap_angle(0.1 * k)
            pose = geo["Pose"](
                position=geo["Point"](x=x, y=y, z=0.0),
                orientation=geo["Quaternion"](x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)),
            )
            zero = geo["Vector3"](x=0.0, y=0.0, z=0.0)
            msg = Odometry(
                header=_stamp(ts, t_ns),
                child_frame_id="base_link",
                pose=geo["PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=geo["TwistWithCovariance"](
                    twist=geo["Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
                ),
            )
            write(config.odom_topic, t_ns, msg)
            truth["odom"].append((t_ns, np.array([x, y, yaw])))
        for k in range(N_FRAMES):
            t_ns = T0_NS + k * FRAME_NS + 123
            rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
            if k % 2:
                write(config.rgb_topic, t_ns, _image(ts, t_ns, np.ascontiguousarray(rgb[..., ::-1]), "bgr8", pad=4))
            else:
                write(config.rgb_topic, t_ns, _image(ts, t_ns, rgb, "rgb8"))
            if depth_encoding == "16UC1":
                depth = rng.integers(0, 9000, size=(H, W), dtype=np.uint16)
                depth[0] = 0
            else:
                depth = rng.uniform(0.3, 9.0, size=(H, W)).astype(np.float32)
                depth[0, :4] = [np.nan, 0.0, np.inf, -1.0]
            if k != 3:
                write(config.depth_topic, t_ns + 3_000_000, _image(ts, t_ns + 3_000_000, depth, depth_encoding))
                truth["stamps"].append(t_ns)
                truth["rgb"].append(rgb)
                truth["depth"].append(depth)
    return truth


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_reader_returns_what_was_written(tmp_path: Path, config: RosbagConfig, encoding: str) -> None:
    truth = _write_bag(tmp_path / "bag", config, encoding)
    seq = read_rosbag(tmp_path / "bag", config)

    assert seq.meta.source == "rosbag"
    K_got = seq.meta.intrinsics
    assert (K_got.width, K_got.height, K_got.fx, K_got.fy, K_got.cx, K_got.cy) == (W, H, *K)
    assert len(seq) == N_FRAMES - 1  # colour image 3 has no depth
    np.testing.assert_array_equal(seq.timestamps(), [t / 1e9 for t in truth["stamps"]])
    assert seq.ground_truth() is None

    odom_t = np.array([t for t, _ in truth["odom"]])
    want_odom = np.array([truth["odom"][int(np.argmin(np.abs(odom_t - t)))][1] for t in truth["stamps"]])
    got_odom = seq.odometry()
    np.testing.assert_array_equal(got_odom[:, :2], want_odom[:, :2])
    np.testing.assert_allclose(wrap_angle(got_odom[:, 2] - want_odom[:, 2]), 0.0, atol=1e-12)

    frames = list(seq)  # one streaming pass
    for k, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.rgb, truth["rgb"][k])
        if encoding == "16UC1":
            want = truth["depth"][k].astype(np.float32) / np.float32(1000)
            want[truth["depth"][k] == 0] = np.nan
        else:
            want = truth["depth"][k].copy()
            want[0, :4] = np.nan  # NaN, 0, inf and negative are no return
        assert frame.depth_m.dtype == np.float32
        np.testing.assert_array_equal(frame.depth_m, want)
        np.testing.assert_array_equal(frame.odom_pose, got_odom[k])

    # random access reads the same frame as the stream
    np.testing.assert_array_equal(seq[2].rgb, frames[2].rgb)
    np.testing.assert_array_equal(seq[-1].depth_m, frames[-1].depth_m)

    # and the bag converts to the bimfactor format
    write_sequence(tmp_path / "converted", seq.meta, seq)
    back = read_sequence(tmp_path / "converted")
    np.testing.assert_array_equal(back.odometry(), got_odom)
    np.testing.assert_array_equal(back[1].rgb, frames[1].rgb)


def test_convert_keeps_the_keyframes_of_the_odometry(tmp_path: Path, config: RosbagConfig) -> None:
    from tests.test_cli import invoke

    truth = _write_bag(tmp_path / "bag", config, "16UC1")
    # Colour frames k = 0, 1, 2, 4 meet odometry message j = 10 k + 2: (0.01 j, −0.02 j, 0.1 j). From frame 0,
    # frame 1 moved 0.22 m and turned 57°, frame 2 0.45 m; from frame 2, frame 4 moved 0.45 m.
    spacing = ("--set", "localization.keyframe_distance_m=0.4", "--set", "localization.keyframe_angle_deg=90")
    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "kf", *spacing)
    assert result.exit_code == 0, result.output
    assert "3 keyframes of 4 frames (every 0.4 m or 90° of odometry)" in result.output
    kept = read_sequence(tmp_path / "kf")
    stamps = [t / 1e9 for t in truth["stamps"]]
    np.testing.assert_array_equal(kept.timestamps(), [stamps[0], stamps[2], stamps[3]])
    np.testing.assert_array_equal(kept[1].rgb, truth["rgb"][2])

    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "all", "--all-frames", *spacing)
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(read_sequence(tmp_path / "all").timestamps(), stamps)


def test_missing_topics_are_listed(tmp_path: Path, config: RosbagConfig) -> None:
    _write_bag(tmp_path / "bag", config, "16UC1", topics=(config.rgb_topic, config.odom_topic))
    with pytest.raises(InputError) as exc_info:
        read_rosbag(tmp_path / "bag", config)
    message = str(exc_info.value)
    assert "\n" not in message
    missing = ", ".join(sorted([config.depth_topic, config.camera_info_topic]))
    assert f"topic(s) {missing} not in the bag" in message
    present = sorted([f"{config.odom_topic} (nav_msgs/msg/Odometry)", f"{config.rgb_topic} (sensor_msgs/msg/Image)"])
    assert f"it has: {', '.join(present)}" in message


def test_intrinsics_passed_in_make_camera_info_optional(tmp_path: Path, config: RosbagConfig) -> None:
    from bimfactor.types import CameraIntrinsics

    _write_bag(tmp_path / "bag", config, "16UC1", topics=(config.rgb_topic, config.depth_topic, config.odom_topic))
    K_given = CameraIntrinsics(W, H, 30.0, 30.0, 16.0, 12.0)
    seq = read_rosbag(tmp_path / "bag", config, intrinsics=K_given)
    assert seq.meta.intrinsics == K_given and len(seq) == N_FRAMES - 1


def test_not_a_bag(tmp_path: Path, config: RosbagConfig) -> None:
    with pytest.raises(InputError, match="no such ROS 2 bag"):
        read_rosbag(tmp_path / "missing", config)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a readable ROS 2 bag"):
        read_rosbag(tmp_path / "empty", config)


def _message(encoding: str, data: np.ndarray, *, bigendian: bool, h: int, w: int) -> SimpleNamespace:
    raw = np.ascontiguousarray(data).view(np.uint8).ravel()
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=raw.size // h, is_bigendian=int(bigendian), data=raw
    )


def test_image_decoding_byte_order_and_errors() -> None:
    mm = np.array([[0, 1000, 65535], [1, 2, 3]], dtype=np.uint16)
    msg = _message("16UC1", mm.astype(">u2"), bigendian=True, h=2, w=3)
    want = mm.astype(np.float32) / np.float32(1000)
    want[0, 0] = np.nan
    np.testing.assert_array_equal(depth_image(msg, "bag"), want)
    with pytest.raises(InputError, match="depth encoding '8UC1' not supported"):
        depth_image(_message("8UC1", mm.astype(np.uint8), bigendian=False, h=2, w=3), "bag")
    rgba = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
    np.testing.assert_array_equal(
        rgb_image(_message("bgra8", rgba, bigendian=False, h=2, w=3), "bag"), rgba[..., 2::-1]
    )
    with pytest.raises(FormatError, match="too short"):
        rgb_image(_message("rgb8", rgba[:1], bigendian=False, h=2, w=3), "bag")
