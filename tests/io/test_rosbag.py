"""The bag reader on small bags the tests write with rosbags' writers: decoding, topics found or named, odometry
interpolation and drops, undistortion, depth registration, and the errors of each."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from bimfactor.config import Config, RosbagConfig
from bimfactor.errors import FormatError, InputError
from bimfactor.io.rectify import register_depth
from bimfactor.io.rosbag import (
    depth_image,
    interpolate_planar,
    mount_from_xyz_rpy,
    mount_rpy_deg,
    read_rosbag,
    rgb_image,
)
from bimfactor.io.sequence import read_sequence, write_sequence
from bimfactor.types import STOREY_CHANGE, CameraIntrinsics, wrap_angle
from tests.io.bags import R_LINK_OPTICAL, TestBag, rigid

pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")

W, H = 32, 24
K = (25.0, 26.0, 15.5, 11.25)  # fx, fy, cx, cy
T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 Hz colour
N_FRAMES = 5
CAMERA = "cam_optical"
RGB, DEPTH, INFO, ODOM = "/cam/color/image_raw", "/cam/aligned_depth/image_raw", "/cam/color/camera_info", "/odom"
ALL = (RGB, DEPTH, INFO, ODOM, "/tf_static")


@pytest.fixture(scope="module")
def config(test_config: Config) -> RosbagConfig:
    """io.rosbag by default: every topic found by type."""
    return test_config.io.rosbag


def _odom_pose(k: int) -> np.ndarray:
    return np.array([0.01 * k, -0.02 * k, wrap_angle(0.1 * k)])


def _odom_ns(k: int) -> int:
    return T0_NS - 20_000_000 + k * 10_000_000  # 100 Hz from 20 ms before the first colour image


def _write_bag(
    path: Path,
    depth_encoding: str = "16UC1",
    topics: tuple[str, ...] = ALL,
    fmt: str = "sqlite3",
    storey_changes: dict[int, int] | None = None,
) -> dict:
    """Colour at 10 Hz (frame 3 has no depth), depth 3 ms later, odometry at 100 Hz, one CameraInfo; tf_static
    puts the camera 0.2 m up, looking ahead. `storey_changes`: colour frame → a std_msgs/Int32 on /storey_change
    50 ms before it."""
    bag = TestBag(path, fmt)
    for k, floors in (storey_changes or {}).items():
        bag.add("/storey_change", "std_msgs/msg/Int32", bag.T["std_msgs/msg/Int32"](data=floors), T0_NS + k * FRAME_NS)
    rng = np.random.default_rng(3)
    truth: dict[str, list] = {"stamps": [], "rgb": [], "depth": []}
    if INFO in topics:
        bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    if "/tf_static" in topics:
        bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid((0.0, 0.0, 0.2), R_LINK_OPTICAL))])
    if ODOM in topics:
        for k in range(50):
            bag.odometry(ODOM, _odom_ns(k), _odom_pose(k))
    for k in range(N_FRAMES):
        t_ns = T0_NS + k * FRAME_NS + 123
        rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        if RGB in topics:
            if k % 2:
                bag.image(RGB, t_ns, np.ascontiguousarray(rgb[..., ::-1]), "bgr8", CAMERA, pad=4)
            else:
                bag.image(RGB, t_ns, rgb, "rgb8", CAMERA)
        if depth_encoding == "16UC1":
            depth = rng.integers(0, 9000, size=(H, W), dtype=np.uint16)
            depth[0] = 0
        else:
            depth = rng.uniform(0.3, 9.0, size=(H, W)).astype(np.float32)
            depth[0, :4] = [np.nan, 0.0, np.inf, -1.0]
        if k != 3:
            if DEPTH in topics:
                bag.image(DEPTH, t_ns + 3_000_000, depth, depth_encoding, CAMERA)
            truth["stamps"].append(t_ns)
            truth["rgb"].append(rgb)
            truth["depth"].append(depth)
    bag.write()
    return truth


def _odometry_at(stamps_ns: list[int]) -> np.ndarray:
    """The 100 Hz odometry interpolated by hand: x, y linear, yaw on the unwrapped angle."""
    t = np.array([_odom_ns(k) - T0_NS for k in range(50)], dtype=np.float64)  # ns from T0: exact in float64
    poses = np.array([_odom_pose(k) for k in range(50)])
    q = np.array(stamps_ns, dtype=np.int64) - T0_NS
    out = np.stack(
        [np.interp(q, t, poses[:, 0]), np.interp(q, t, poses[:, 1]), np.interp(q, t, np.unwrap(poses[:, 2]))]
    )
    out = out.T
    out[:, 2] = wrap_angle(out[:, 2])
    return out


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_reader_returns_what_was_written(tmp_path: Path, config: RosbagConfig, encoding: str) -> None:
    truth = _write_bag(tmp_path / "bag", encoding)
    seq = read_rosbag(tmp_path / "bag", config)

    assert seq.meta.source == "rosbag"
    K_got = seq.meta.intrinsics
    assert (K_got.width, K_got.height, K_got.fx, K_got.fy, K_got.cx, K_got.cy) == (W, H, *K)
    np.testing.assert_allclose(seq.meta.T_base_camera, rigid((0.0, 0.0, 0.2), R_LINK_OPTICAL), atol=1e-12)
    assert len(seq) == N_FRAMES - 1  # colour image 3 has no depth
    assert seq.meta.extras["frames"]["dropped"] == {"no depth image within 0.05 s": 1}
    np.testing.assert_array_equal(seq.timestamps(), [t / 1e9 for t in truth["stamps"]])
    assert seq.ground_truth() is None

    want_odom = _odometry_at(truth["stamps"])
    got_odom = seq.odometry()
    np.testing.assert_allclose(got_odom[:, :2], want_odom[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(got_odom[:, 2] - want_odom[:, 2]), 0.0, atol=1e-9)

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

    # and the bag converts to the bimfactor format, with what was assumed in its extras
    write_sequence(tmp_path / "converted", seq.meta, seq)
    back = read_sequence(tmp_path / "converted")
    np.testing.assert_array_equal(back.odometry(), got_odom)
    np.testing.assert_array_equal(back[1].rgb, frames[1].rgb)
    assert back.meta.extras["topics"]["rgb"] == RGB and back.meta.extras["camera_mount"]["xyz_m"] == [0.0, 0.0, 0.2]


def test_convert_keeps_the_keyframes_of_the_odometry(tmp_path: Path) -> None:
    from tests.cli import invoke

    truth = _write_bag(tmp_path / "bag")
    # Colour frames k = 0, 1, 2, 4 fall 123 ns after odometry sample j = 10 k + 2: (0.01 j, −0.02 j, 0.1 j). From
    # frame 0, frame 1 moved 0.22 m and turned 57°, frame 2 0.45 m; from frame 2, frame 4 moved 0.45 m.
    spacing = ("--set", "localization.keyframe_distance_m=0.4", "--set", "localization.keyframe_angle_deg=90")
    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "kf", *spacing)
    assert result.exit_code == 0, result.output
    assert "3 keyframes of 4 frames (every 0.4 m or 90° of odometry)" in result.output
    assert "4 of 5 colour images synchronised; dropped: 1 no depth image within 0.05 s" in result.output
    kept = read_sequence(tmp_path / "kf")
    stamps = [t / 1e9 for t in truth["stamps"]]
    np.testing.assert_array_equal(kept.timestamps(), [stamps[0], stamps[2], stamps[3]])
    np.testing.assert_array_equal(kept[1].rgb, truth["rgb"][2])

    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "all", "--all-frames", *spacing)
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(read_sequence(tmp_path / "all").timestamps(), stamps)


def test_a_storey_change_on_a_bag_topic_is_carried_through_convert(tmp_path: Path) -> None:
    from tests.cli import invoke

    # up a floor before colour frame 1 (synchronised, left out as no keyframe), down two before frame 3 (no depth)
    _write_bag(tmp_path / "bag", storey_changes={1: 1, 3: -2})
    spacing = ("--set", "localization.keyframe_distance_m=0.4", "--set", "localization.keyframe_angle_deg=90")
    topic = ("--set", "io.rosbag.storey_topic=/storey_change")
    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "kf", *spacing, *topic)
    assert result.exit_code == 0, result.output
    kept = read_sequence(tmp_path / "kf")  # colour frames 0, 2 and 4
    assert [f.extras.get(STOREY_CHANGE) for f in kept] == [None, 1.0, -2.0]
    assert kept.meta.extras["storey_changes"] == {"messages": 2, "frames": 2}
    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "no", *spacing)
    assert result.exit_code == 0 and not any(f.extras for f in read_sequence(tmp_path / "no"))
    result = invoke(
        "convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "odom", "--set", f"io.rosbag.storey_topic={ODOM}"
    )
    assert result.exit_code != 0 and "expected std_msgs/msg/Int32" in result.output


def test_topics_named_in_the_config_are_checked(tmp_path: Path, config: RosbagConfig) -> None:
    _write_bag(tmp_path / "bag", topics=(RGB, ODOM, INFO, "/tf_static"))
    named = config.model_copy(update={"depth_topic": "/cam/depth"})
    with pytest.raises(InputError) as exc_info:
        read_rosbag(tmp_path / "bag", named)
    message = str(exc_info.value)
    assert "\n" not in message
    assert "topic /cam/depth (io.rosbag.depth_topic) is not in the bag; it has: " in message
    assert f"{RGB} (sensor_msgs/msg/Image)" in message and f"{ODOM} (nav_msgs/msg/Odometry)" in message
    wrong = config.model_copy(update={"rgb_topic": ODOM})
    with pytest.raises(InputError, match=f"topic {ODOM} carries nav_msgs/msg/Odometry, expected sensor_msgs/msg/Image"):
        read_rosbag(tmp_path / "bag", wrong)


def test_several_candidate_topics_narrow_by_name_or_ask(tmp_path: Path, config: RosbagConfig) -> None:
    """Two depth topics: the aligned one wins; two colour topics with colour names: the error lists both."""
    bag = TestBag(tmp_path / "bag")
    bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))])
    for k in range(3):
        t_ns = T0_NS + k * FRAME_NS
        bag.odometry(ODOM, t_ns, _odom_pose(k))
        bag.image(RGB, t_ns, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
        bag.image("/cam/color/image_rect_color", t_ns, np.zeros((H, W, 3), np.uint8), "bgr8", CAMERA)
        bag.image("/cam/infra1/image_rect_raw", t_ns, np.zeros((H, W), np.uint8), "mono8", "infra")
        bag.image("/cam/depth/image_rect_raw", t_ns, np.ones((H, W), np.uint16), "16UC1", "depth_optical")
        bag.image(DEPTH, t_ns, np.ones((H, W), np.uint16), "16UC1", CAMERA)
    bag.write()
    with pytest.raises(InputError) as exc_info:
        read_rosbag(tmp_path / "bag", config)
    assert str(exc_info.value).endswith(
        f"several colour topics ({RGB}, /cam/color/image_rect_color); name one with --set io.rosbag.rgb_topic=TOPIC"
    )
    seq = read_rosbag(tmp_path / "bag", config.model_copy(update={"rgb_topic": RGB}))
    assert seq.meta.extras["topics"]["depth"] == DEPTH
    assert seq.meta.extras["topics"]["found_by_type"] == ["camera_info_topic", "depth_topic", "odom_topic"]
    assert len(seq) == 3


def test_intrinsics_passed_in_make_camera_info_optional(tmp_path: Path, config: RosbagConfig) -> None:
    _write_bag(tmp_path / "bag", topics=(RGB, DEPTH, ODOM, "/tf_static"))
    with pytest.raises(InputError, match="no sensor_msgs/msg/CameraInfo topic in the bag"):
        read_rosbag(tmp_path / "bag", config)
    K_given = CameraIntrinsics(W, H, 30.0, 30.0, 16.0, 12.0)
    seq = read_rosbag(tmp_path / "bag", config, intrinsics=K_given)
    assert seq.meta.intrinsics == K_given and len(seq) == N_FRAMES - 1


def test_odometry_outside_the_colour_span_or_across_a_gap_drops_frames(tmp_path: Path, config: RosbagConfig) -> None:
    bag = TestBag(tmp_path / "bag")
    bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))])
    for k in range(10):  # colour and depth at 10 Hz, 0 .. 0.9 s
        t_ns = T0_NS + k * FRAME_NS
        bag.image(RGB, t_ns, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
        bag.image(DEPTH, t_ns, np.ones((H, W), np.uint16), "16UC1", CAMERA)
    for t_s in (0.15, 0.2, 0.25, 0.3, 0.9, 1.0):  # odometry from 0.15 s, with a 0.6 s gap after 0.3 s
        bag.odometry(ODOM, T0_NS + round(t_s * 1e9), np.array([t_s, 0.0, 0.0]))
    bag.write()
    seq = read_rosbag(tmp_path / "bag", config)
    assert seq.meta.extras["frames"]["dropped"] == {
        "outside the odometry's time span": 2,  # 0.0 s and 0.1 s
        "odometry gap over 0.5 s": 5,  # 0.4 .. 0.8 s
    }
    np.testing.assert_allclose(seq.odometry()[:, 0], [0.2, 0.3, 0.9], atol=1e-9)
    widened = config.model_copy(update={"max_odom_gap_s": 1.0})
    np.testing.assert_allclose(read_rosbag(tmp_path / "bag", widened).odometry()[:, 0], np.arange(2, 10) / 10)


def test_interpolation_takes_the_shorter_arc() -> None:
    t = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [1.0, 2.0, -np.pi + 0.1], [3.0, 2.0, -np.pi + 0.1]])
    got = interpolate_planar(t, poses, np.array([-0.1, 0.5, 1.5, 2.0, 2.1]))
    assert np.isnan(got[[0, 4]]).all()
    np.testing.assert_allclose(got[1, :2], [0.5, 1.0])
    assert abs(wrap_angle(got[1, 2] - np.pi)) < 1e-12  # through ±π, not through 0
    np.testing.assert_allclose(got[2:4], [[2.0, 2.0, -np.pi + 0.1], [3.0, 2.0, -np.pi + 0.1]])


def test_the_mount_convention_of_camera_mount() -> None:
    from bimfactor.config import CameraSimConfig
    from bimfactor.sim.sensors import camera_mount

    sim = CameraSimConfig(
        width=8, height=8, hfov_deg=90, min_range_m=0.1, max_range_m=5, mount_height_m=0.35, mount_forward_m=0.15,
        mount_pitch_deg=10,
    )  # fmt: skip
    T = mount_from_xyz_rpy([0.15, 0, 0.35, 0, 10, 0])
    np.testing.assert_allclose(T, camera_mount(sim), atol=1e-12)  # the simulator's "positive pitch looks down"
    np.testing.assert_allclose(T[:3, 2], [np.cos(np.radians(10)), 0, -np.sin(np.radians(10))], atol=1e-12)
    values = [0.1, -0.2, 0.3, 4.0, -7.0, 30.0]
    np.testing.assert_allclose(mount_rpy_deg(mount_from_xyz_rpy(values)), values[3:], atol=1e-9)


def test_odometry_of_another_frame_is_moved_onto_the_base(tmp_path: Path, config: RosbagConfig) -> None:
    """Odometry of base_footprint, mount on base_link 0.1 m ahead of it: the sequence's base is base_link."""
    bag = TestBag(tmp_path / "bag")
    bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    bag.tf(
        "/tf_static",
        T0_NS,
        [("base_footprint", "base_link", rigid((0.1, 0.0, 0.05))), ("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))],
    )
    for k in range(3):
        t_ns = T0_NS + k * FRAME_NS
        bag.odometry(ODOM, t_ns, np.array([1.0, 2.0, np.pi / 2]), child="base_footprint")
        bag.image(RGB, t_ns, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
        bag.image(DEPTH, t_ns, np.ones((H, W), np.uint16), "16UC1", CAMERA)
    bag.write()
    np.testing.assert_allclose(read_rosbag(tmp_path / "bag", config).odometry()[0], [1.0, 2.1, np.pi / 2])
    footprint = config.model_copy(update={"base_frame": "base_footprint"})
    seq = read_rosbag(tmp_path / "bag", footprint)
    np.testing.assert_allclose(seq.odometry()[0], [1.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(seq.meta.T_base_camera[:3, 3], [0.1, 0.0, 0.05])
    # the same through the CLI's --base-frame
    from tests.cli import invoke

    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "seq", "--base-frame", "base_footprint")
    assert result.exit_code == 0, result.output
    assert "camera mount base_footprint → cam_optical: x 0.100 y 0.000 z 0.050 m" in result.stdout
    np.testing.assert_allclose(read_sequence(tmp_path / "seq").meta.T_base_camera[:3, 3], [0.1, 0.0, 0.05])


@pytest.mark.parametrize(
    ("edges", "says"),
    [
        (
            [("odom", "base_link", rigid()), ("map", "base_link", rigid()), ("base_link", CAMERA, rigid())],
            "tf: frame base_link has two parents on /tf_static, odom and map",
        ),
        (
            [("base_link", "cam_link", rigid()), ("cam_link", "base_link", rigid()), ("cam_link", CAMERA, rigid())],
            "form a cycle",
        ),
    ],
    ids=["two parents", "cycle"],
)
def test_a_tf_graph_that_is_no_tree_is_refused(tmp_path: Path, config: RosbagConfig, edges: list, says: str) -> None:
    """A frame with two parents, or frames that are each other's parents: no mount can be read from them (before,
    the last parent won and an inverted edge became the mount); one line, exit 2, no output."""
    from tests.cli import assert_one_line_error, invoke

    bag = TestBag(tmp_path / "bag")
    bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    bag.tf("/tf_static", T0_NS, edges)
    for k in range(3):
        t_ns = T0_NS + k * FRAME_NS
        bag.odometry(ODOM, t_ns, np.array([1.0, 2.0, 0.0]))
        bag.image(RGB, t_ns, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
        bag.image(DEPTH, t_ns, np.ones((H, W), np.uint16), "16UC1", CAMERA)
    bag.write()
    assert_one_line_error(invoke("convert", "rosbag", tmp_path / "bag", "-o", tmp_path / "seq"), contains=says)
    assert not (tmp_path / "seq").exists()


# ------------------------------------------------------------------------------------------ distortion


def _dots(size_wh: tuple[int, int], centres: np.ndarray) -> np.ndarray:
    """A black image with a white Gaussian blob (σ 1 px) on each (sub-pixel) centre."""
    vv, uu = np.mgrid[0 : size_wh[1], 0 : size_wh[0]]
    grey = sum(np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / 2.0) for u, v in centres)
    return np.repeat(np.rint(255 * np.clip(grey, 0, 1)).astype(np.uint8)[..., None], 3, axis=-1)


def _centroids(image: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Brightness centroid of the 9 x 9 window around each expected position."""
    grey = image[..., 0].astype(np.float64) if image.ndim == 3 else image
    out = []
    for u, v in np.rint(near).astype(int):
        window = grey[v - 4 : v + 5, u - 4 : u + 5]
        vv, uu = np.mgrid[v - 4 : v + 5, u - 4 : u + 5]
        out.append([(window * uu).sum() / window.sum(), (window * vv).sum() / window.sum()])
    return np.array(out)


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_distorted_images_are_undistorted(tmp_path: Path, config: RosbagConfig, model: str) -> None:
    w, h = 160, 120
    fx, fy, cx, cy = 100.0, 100.0, 79.5, 59.5
    D = np.array([-0.3, 0.08, 0.001, -0.001, 0.0] + ([0.01, 0.0, 0.0] if model == "rational_polynomial" else []))
    Kmat = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    # dots along a straight line of the pinhole image, drawn where the lens puts them
    line = np.stack([np.linspace(-0.6, 0.6, 7), np.full(7, -0.42)], -1)
    distorted, _ = cv2.projectPoints(np.c_[line, np.ones(7)], np.zeros(3), np.zeros(3), Kmat, D)
    distorted = distorted.reshape(-1, 2)
    expected = cv2.undistortPoints(distorted.reshape(-1, 1, 2), Kmat, D, P=Kmat).reshape(-1, 2)
    rgb = _dots((w, h), distorted)
    depth = np.full((h, w), 3.0, np.float32)
    depth[rgb[..., 0] > 100] = 1.0  # the dots are nearer

    bag = TestBag(tmp_path / "bag")
    bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))])
    for k in range(2):
        t_ns = T0_NS + k * FRAME_NS
        bag.camera_info(INFO, t_ns, CAMERA, (w, h), (fx, fy, cx, cy), D=D, model=model)
        bag.odometry(ODOM, t_ns, np.zeros(3))
        bag.image(RGB, t_ns, rgb, "rgb8", CAMERA)
        bag.depth_mm(DEPTH, t_ns, depth, CAMERA)
    bag.write()
    seq = read_rosbag(tmp_path / "bag", config)
    assert seq.meta.extras["distortion"]["model"] == model and seq.meta.extras["distortion"]["undistorted"]
    frame = seq[0]
    got = _centroids(frame.rgb, expected)
    np.testing.assert_allclose(got, expected, atol=0.25)  # where cv2.undistortPoints says
    # the straight line is straight again (it bent by pixels before)
    residual = lambda p: np.abs(np.polyval(np.polyfit(p[:, 0], p[:, 1], 1), p[:, 0]) - p[:, 1]).max()  # noqa: E731
    assert residual(distorted) > 1.5 and residual(got) < 0.3
    # depth moved with the colour, at the nearest pixel: the dots' depth lands on the undistorted dots
    for u, v in np.rint(expected).astype(int):
        assert frame.depth_m[v, u] == pytest.approx(1.0)
    assert set(np.unique(frame.depth_m[np.isfinite(frame.depth_m)]).tolist()) == {1.0, 3.0}


def test_distortion_and_intrinsics_that_do_not_fit_are_refused(tmp_path: Path, config: RosbagConfig) -> None:
    def bag_with(name: str, **info) -> Path:
        bag = TestBag(tmp_path / name)
        bag.camera_info(INFO, T0_NS, CAMERA, **{"size_wh": (W, H), "K": K, **info})
        bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))])
        bag.odometry(ODOM, T0_NS, np.zeros(3))
        bag.image(RGB, T0_NS, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
        bag.image(DEPTH, T0_NS, np.ones((H, W), np.uint16), "16UC1", CAMERA)
        return bag.write()

    fisheye = bag_with("fisheye", D=np.array([0.1, 0.01, 0.0, 0.0]), model="equidistant")
    with pytest.raises(InputError, match=r"distortion model 'equidistant' is not supported \(plumb_bob, rational_pol"):
        read_rosbag(fisheye, config)
    assert len(read_rosbag(bag_with("zero", D=np.zeros(4), model="equidistant"), config)) == 1  # nothing to undo
    off = bag_with("off", K=(25.0, 25.0, 40.0, 11.0))
    with pytest.raises(InputError, match=r"principal point \(40, 11\) lies outside the 32x24 image"):
        read_rosbag(off, config)


# ------------------------------------------------------------------------------------------ depth registration


def test_register_depth_shifts_by_the_baseline_and_keeps_the_nearest() -> None:
    """Depth camera 80 x 60 (f 50), colour 160 x 120 (f 100), depth camera 0.05 m to the colour camera's right: a
    depth pixel (u, v) at z lands on colour pixel (2u + 1 + 5/z, 2v + 1)."""
    Kd = np.array([[50.0, 0, 39.5], [0, 50.0, 29.5], [0, 0, 1]])
    Kc = np.array([[100.0, 0, 80.0], [0, 100.0, 60.0], [0, 0, 1]])
    T = rigid((0.05, 0.0, 0.0))
    depth = np.full((60, 80), 2.5, np.float32)  # a wall: shift 2 px
    depth[20:30, 30:40] = 1.25  # a box in front: shift 4 px
    depth[0, 0] = np.nan
    got = register_depth(depth, Kd, T, Kc, (160, 120))
    assert got.shape == (120, 160) and got.dtype == np.float32
    for v, u in [(5, 5), (25, 35), (25, 29), (40, 70)]:
        z = depth[v, u]
        assert got[2 * v + 1, 2 * u + 1 + round(5 / z)] == pytest.approx(z)
    assert np.isnan(got[1, 3])  # the missing depth pixel lands nowhere
    # the wall pixel (25, 40) lands on (51, 83), where the box pixel (25, 39) lands too: the box is nearer
    assert got[51, 83] == pytest.approx(1.25)
    # every valid pixel lands once, but for the occluded wall column and the last column, pushed off the image (161)
    assert np.isfinite(got).sum() == np.isfinite(depth).sum() - depth[20:30, 40].size - depth[:, 79].size


def test_unregistered_depth_in_a_bag_is_registered(tmp_path: Path, config: RosbagConfig) -> None:
    bag = TestBag(tmp_path / "bag")
    depth_frame = "cam_depth_optical"
    bag.tf(
        "/tf_static",
        T0_NS,
        [
            ("base_link", "cam_link", rigid((0.1, 0.0, 0.3))),
            ("cam_link", CAMERA, rigid(R=R_LINK_OPTICAL)),
            ("cam_link", "cam_depth_frame", rigid((0.0, -0.05, 0.0))),  # 5 cm to the right of the colour camera
            ("cam_depth_frame", depth_frame, rigid(R=R_LINK_OPTICAL)),
        ],
    )
    depth = np.full((60, 80), 2.5, np.float32)
    depth[20:30, 30:40] = 1.25
    for k in range(2):
        t_ns = T0_NS + k * FRAME_NS
        bag.camera_info(INFO, t_ns, CAMERA, (160, 120), (100.0, 100.0, 80.0, 60.0))
        bag.camera_info("/cam/depth/camera_info", t_ns, depth_frame, (80, 60), (50.0, 50.0, 39.5, 29.5))
        bag.odometry(ODOM, t_ns, np.zeros(3))
        bag.image(RGB, t_ns, np.zeros((120, 160, 3), np.uint8), "rgb8", CAMERA)
        bag.depth_mm("/cam/depth/image_rect_raw", t_ns + 2_000_000, depth, depth_frame)
    bag.write()
    seq = read_rosbag(tmp_path / "bag", config)
    extras = seq.meta.extras
    assert extras["topics"]["depth_camera_info"] == "/cam/depth/camera_info"
    assert extras["depth"]["registration"].startswith(f"registered to colour from {depth_frame} (tf static: ")
    assert extras["depth"]["baseline_m"] == pytest.approx(0.05)
    got = seq[1].depth_m
    assert got.shape == (120, 160)
    K_depth = np.array([[50.0, 0, 39.5], [0, 50.0, 29.5], [0, 0, 1]])
    want = register_depth(depth, K_depth, rigid((0.05, 0.0, 0.0)), seq.meta.intrinsics.K, (160, 120))
    np.testing.assert_array_equal(got, want)
    assert got[2 * 25 + 1, 2 * 35 + 1 + 4] == pytest.approx(1.25) and got[11, 11 + 2] == pytest.approx(2.5)


def test_depth_without_a_transform_to_colour_is_refused(tmp_path: Path, config: RosbagConfig) -> None:
    bag = TestBag(tmp_path / "bag")
    bag.tf("/tf_static", T0_NS, [("base_link", CAMERA, rigid(R=R_LINK_OPTICAL))])
    bag.camera_info(INFO, T0_NS, CAMERA, (W, H), K)
    bag.camera_info("/cam/depth/camera_info", T0_NS, "depth_optical", (W, H), K)
    bag.odometry(ODOM, T0_NS, np.zeros(3))
    bag.image(RGB, T0_NS, np.zeros((H, W, 3), np.uint8), "rgb8", CAMERA)
    bag.image("/cam/depth/image_raw", T0_NS, np.ones((H, W), np.uint16), "16UC1", "depth_optical")
    bag.write()
    with pytest.raises(InputError, match=r"depth \(depth_optical\) is not registered to colour \(cam_optical\) and "):
        read_rosbag(tmp_path / "bag", config)


# ------------------------------------------------------------------------------------------ files and decoding


def test_not_a_bag(tmp_path: Path, config: RosbagConfig) -> None:
    with pytest.raises(InputError, match="no such bag"):
        read_rosbag(tmp_path / "missing", config)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a readable ROS 2 bag"):
        read_rosbag(tmp_path / "empty", config)
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\nnot really")
    with pytest.raises(InputError, match=r"broken\.bag: not a readable ROS 1 bag \(") as exc_info:
        read_rosbag(tmp_path / "broken.bag", config)
    assert "\n" not in str(exc_info.value)
    (tmp_path / "latin.bag").write_bytes(b"\xff\xfe not a bag at all\n")  # not UTF-8: was a UnicodeDecodeError
    with pytest.raises(
        InputError, match=r"latin\.bag: not a readable ROS 1 bag: it does not begin with '#ROSBAG V2.0'"
    ):
        read_rosbag(tmp_path / "latin.bag", config)
    from tests.cli import assert_one_line_error, invoke

    result = invoke("convert", "rosbag", tmp_path / "latin.bag", "-o", tmp_path / "seq")
    assert_one_line_error(result, contains="does not begin with '#ROSBAG V2.0'")
    assert not (tmp_path / "seq").exists()


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


def _compressed(fmt: str, data: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(header=None, format=fmt, data=np.asarray(data, np.uint8))


def test_compressed_depth_of_32fc1_is_the_inverse_depth_quantisation_decoded() -> None:
    """image_transport's compressedDepth stores 32FC1 as quant_a / depth + quant_b in a 16-bit PNG (0: no return)."""
    quant_a, quant_b = 100.0 * 101.0, 1.0 - 100.0 * 101.0 / 10.0  # its defaults: quantisation 100, depth_max 10 m
    depth = np.array([[0.5, 1.0, 2.0], [4.0, 8.0, np.nan]])
    value = np.where(np.isnan(depth), 0, np.rint(quant_a / np.nan_to_num(depth, nan=1.0) + quant_b)).astype(np.uint16)
    header = np.array([(0, quant_a, quant_b)], dtype=[("f", "<i4"), ("a", "<f4"), ("b", "<f4")]).view(np.uint8)
    png = cv2.imencode(".png", value)[1].ravel()
    out = depth_image(_compressed("32FC1; compressedDepth png", np.concatenate([header, png])), "bag")
    assert np.isnan(out[1, 2]) and out.dtype == np.float32
    np.testing.assert_allclose(out[:, :2], depth[:, :2], rtol=0.01)
    np.testing.assert_allclose(out[0], depth[0], rtol=2e-4)
    with pytest.raises(InputError, match="RVL"):
        depth_image(_compressed("16UC1; compressedDepth rvl", np.zeros(40)), "bag")
    with pytest.raises(FormatError, match="OpenCV cannot decode"):
        rgb_image(_compressed("rgb8; jpeg compressed bgr8", np.arange(64)), "bag")
    grey = cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].ravel()
    with pytest.raises(InputError, match="colour encoding 'uint8, shape 4x4' not supported"):
        rgb_image(_compressed("mono8; png compressed", grey), "bag")
