"""`bimfactor convert rosbag` on bags recorded from the simulator: a camera 0.35 m high pitched 10° down on tf_static,
odometry at 50 Hz, colour at 15 Hz, depth 4 ms after it. The bag is written as ROS 2 sqlite3, ROS 2 mcap and ROS 1;
the conversion must find every topic by type and recover the mount, the intrinsics and the odometry."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import Config
from bimfactor.io.rosbag import read_rosbag
from bimfactor.io.sequence import quantize_depth_m, read_sequence
from bimfactor.types import CameraIntrinsics, wrap_angle
from tests.cli import assert_one_line_error, invoke
from tests.io.bags import R_LINK_OPTICAL, TestBag, rigid, rpy_deg
from tests.sim.conftest import Building, config_with

pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")

T0_NS = 1_700_000_000_000_000_000
COLOUR_HZ, ODOM_HZ = 15, 50
DEPTH_AFTER_NS = 4_000_000
N_FRAMES = 12
START_S = 1.0  # into the simulated drive, once the robot moves
MOUNT_XYZ = (0.15, 0.0, 0.35)
COLOUR_FRAME = "camera_color_optical_frame"


@dataclass
class SimRun:
    """What the simulator rendered and drove, on the bag's clock."""

    intrinsics: CameraIntrinsics
    T_base_camera: np.ndarray
    colour_ns: np.ndarray  # (N,)
    rgb: list[np.ndarray]
    depth_m: list[np.ndarray]
    odom_ns: np.ndarray  # (M,) 50 Hz
    odom: np.ndarray  # (M, 3)


def _interp_planar(t: np.ndarray, t_samples: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """x, y linear and yaw linear on the unwrapped angle: an independent reference for the reader's interpolation."""
    yaw = np.unwrap(poses[:, 2])
    out = np.stack(
        [np.interp(t, t_samples, poses[:, 0]), np.interp(t, t_samples, poses[:, 1]), np.interp(t, t_samples, yaw)], -1
    )
    out[:, 2] = wrap_angle(out[:, 2])
    return out


@pytest.fixture(scope="module")
def sim_run(paper_floor: Building, config_overrides: list[str]) -> SimRun:
    from bimfactor.sim.sensors import RgbdCamera
    from bimfactor.sim.simulate import build_world
    from bimfactor.sim.trajectory import TrajectorySimulator

    cfg = config_with(config_overrides, "sim.camera.mount_height_m=0.35", "sim.camera.mount_pitch_deg=10")
    world = build_world(paper_floor.prior, paper_floor.model, cfg, 0)
    drive = TrajectorySimulator(paper_floor.prior, cfg).trajectory(0, 0)
    elevation = paper_floor.prior.storeys[drive.storey_index].storey.elevation_m
    camera = RgbdCamera.from_config(world, cfg)
    t_colour = START_S + np.arange(N_FRAMES) / COLOUR_HZ
    t_odom = np.arange(round((START_S - 0.1) * ODOM_HZ), round((t_colour[-1] + 0.1) * ODOM_HZ) + 1) / ODOM_HZ
    odom = _interp_planar(t_odom, drive.times_s, drive.poses)
    poses = _interp_planar(t_colour, t_odom, odom)
    renders = [camera.render(pose, elevation) for pose in poses]
    return SimRun(
        camera.intrinsics,
        camera.T_base_camera,
        T0_NS + np.rint(t_colour * 1e9).astype(np.int64),
        [r.rgb for r in renders],
        [r.depth_m for r in renders],
        T0_NS + np.rint(t_odom * 1e9).astype(np.int64),
        odom,
    )


def write_sim_bag(
    path: Path,
    run: SimRun,
    fmt: str = "sqlite3",
    *,
    camera_info: bool = True,
    depth: bool = True,
    tf_static: bool = True,
    odometry: str = "topic",
    depth_after_ns: int = DEPTH_AFTER_NS,
    info_size: tuple[int, int] | None = None,
    frames: int = N_FRAMES,
    images: str = "raw",
) -> Path:
    """The simulated run (its first `frames` colour frames) as a RealSense-like recording; the switches leave parts
    out or break them."""
    bag = TestBag(path, fmt)
    K = run.intrinsics
    if tf_static:
        mount = rigid(MOUNT_XYZ, rpy_deg(0, 10, 0))
        bag.tf(
            "/tf_static",
            int(run.colour_ns[0]) - 50_000_000,
            [("base_link", "camera_link", mount), ("camera_link", COLOUR_FRAME, rigid(R=R_LINK_OPTICAL))],
        )
    for t_ns, rgb, depth_m in list(zip(run.colour_ns.tolist(), run.rgb, run.depth_m, strict=True))[:frames]:
        if images in ("raw", "both"):
            bag.image("/camera/color/image_raw", t_ns, rgb, "rgb8", COLOUR_FRAME)
        if images in ("compressed", "both"):
            bag.compressed("/camera/color/image_raw/compressed", t_ns, rgb, "rgb8; jpeg compressed bgr8", COLOUR_FRAME)
        if camera_info:
            bag.camera_info(
                "/camera/color/camera_info",
                t_ns,
                COLOUR_FRAME,
                info_size or (K.width, K.height),
                (K.fx, K.fy, K.cx, K.cy),
            )
        if depth and images in ("raw", "both"):
            bag.depth_mm("/camera/aligned_depth_to_color/image_raw", t_ns + depth_after_ns, depth_m, COLOUR_FRAME)
        if depth and images in ("compressed", "both"):
            mm = np.clip(np.nan_to_num(np.rint(depth_m.astype(np.float64) * 1000.0), nan=0.0), 0, 65535)
            mm = mm.astype(np.uint16)
            topic, fmt = "/camera/aligned_depth_to_color/image_raw/compressedDepth", "16UC1; compressedDepth png"
            bag.compressed(topic, t_ns + depth_after_ns, mm, fmt, COLOUR_FRAME)
    for t_ns, pose in zip(run.odom_ns.tolist(), run.odom, strict=True):
        if odometry == "topic":
            bag.odometry("/odom", t_ns, pose)
        elif odometry == "tf":
            x, y, yaw = pose
            bag.tf("/tf", t_ns, [("odom", "base_link", rigid((x, y, 0.0), rpy_deg(0, 0, np.rad2deg(yaw))))])
    return bag.write()


def _assert_recovers_the_run(out: Path, run: SimRun) -> None:
    seq = read_sequence(out)
    meta = seq.meta
    # the mount within 1 mm and 0.1°
    np.testing.assert_allclose(meta.T_base_camera[:3, 3], run.T_base_camera[:3, 3], atol=1e-3)
    R_err = meta.T_base_camera[:3, :3].T @ run.T_base_camera[:3, :3]
    assert np.rad2deg(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 0.1
    assert meta.extras["camera_mount"]["rpy_deg"] == pytest.approx([0.0, 10.0, 0.0], abs=0.1)
    K = meta.intrinsics
    assert (K.width, K.height) == (run.intrinsics.width, run.intrinsics.height)
    assert (K.fx, K.fy, K.cx, K.cy) == pytest.approx(
        (run.intrinsics.fx, run.intrinsics.fy, run.intrinsics.cx, run.intrinsics.cy)
    )
    # every colour frame kept, odometry interpolated at its stamp
    assert len(seq) == N_FRAMES
    np.testing.assert_array_equal(seq.timestamps(), run.colour_ns / 1e9)
    want = _interp_planar((run.colour_ns - T0_NS) / 1e9, (run.odom_ns - T0_NS) / 1e9, run.odom)
    got = seq.odometry()
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(got[:, 2] - want[:, 2]), 0.0, atol=1e-9)
    assert np.linalg.norm(got[-1, :2] - got[0, :2]) > 0.1  # the robot moved
    for k in (0, N_FRAMES - 1):
        np.testing.assert_array_equal(seq[k].rgb, run.rgb[k])
        np.testing.assert_array_equal(seq[k].depth_m, quantize_depth_m(run.depth_m[k]))
    sync = meta.extras["sync"]
    assert sync["depth_dt_median_s"] == pytest.approx(DEPTH_AFTER_NS / 1e9) == pytest.approx(sync["depth_dt_max_s"])
    assert 0 <= sync["odom_dt_max_s"] <= 0.5 / ODOM_HZ + 1e-9


@pytest.mark.parametrize("fmt", ["sqlite3", "mcap"])
def test_convert_finds_everything_in_a_ros2_bag(tmp_path: Path, sim_run: SimRun, fmt: str, test_config: Config) -> None:
    bag = write_sim_bag(tmp_path / "bag", sim_run, fmt)
    assert any(p.suffix == (".mcap" if fmt == "mcap" else ".db3") for p in bag.iterdir())
    out = tmp_path / "seq"
    result = invoke("convert", "rosbag", bag, "-o", out, "--all-frames")
    assert result.exit_code == 0, result.output
    _assert_recovers_the_run(out, sim_run)
    # the report: topics found, the mount and where it came from, intrinsics, offsets, frames
    report = result.stdout
    assert f"ROS 2 ({fmt}) bag; colour /camera/color/image_raw (found by type)" in report
    assert "depth /camera/aligned_depth_to_color/image_raw (found by type), odometry /odom (found by type)" in report
    assert "x 0.150 y 0.000 z 0.350 m, roll 0.00° pitch 10.00° yaw 0.00°" in report
    assert "tf static: base_link → camera_link → camera_color_optical_frame" in report
    assert "intrinsics 320x240 fx 160.00 fy 160.00 cx 159.50 cy 119.50" in report
    assert "depth |Δt| median 4.0 ms, max 4.0 ms" in report
    assert f"{N_FRAMES} of {N_FRAMES} colour images synchronised" in report
    extras = json.loads((out / "sequence.json").read_text())["extras"]
    assert extras["topics"]["camera_info"] == "/camera/color/camera_info"
    if fmt == "mcap":  # the storage file alone reads too
        alone = read_rosbag(next(bag.glob("*.mcap")), test_config.io.rosbag)
        assert len(alone) == N_FRAMES and alone.meta.extras["bag_format"] == "ROS 2 (mcap)"
    assert extras["depth"]["registration"].startswith("as recorded: already in the colour frame")


@pytest.mark.parametrize(
    ("name", "options", "says"),
    [
        ("run.bag", {"kind": "ros1"}, "ROS 1 bag; colour /camera/color/image_raw"),  # a ROS 1 bag reads the same
        ("bag", {"odometry": "tf"}, "odometry tf odom → base_link"),  # no odometry topic: odom → base on /tf
    ],
    ids=["ros1", "odometry-from-tf"],
)
def test_other_recordings_read_the_same(
    tmp_path: Path, sim_run: SimRun, name: str, options: dict[str, str], says: str
) -> None:
    options = dict(options)
    bag = write_sim_bag(tmp_path / name, sim_run, *([options.pop("kind")] if "kind" in options else []), **options)
    out = tmp_path / "seq"
    result = invoke("convert", "rosbag", bag, "-o", out, "--all-frames")
    assert result.exit_code == 0, result.output
    assert says in result.stdout
    _assert_recovers_the_run(out, sim_run)


def test_camera_mount_flag_replaces_tf(tmp_path: Path, sim_run: SimRun) -> None:
    bag = write_sim_bag(tmp_path / "bag", sim_run, tf_static=False)
    out = tmp_path / "seq"
    result = invoke("convert", "rosbag", bag, "-o", out, "--all-frames", "--camera-mount", "0.15,0,0.35,0,10,0")
    assert result.exit_code == 0, result.output
    assert "(from --camera-mount)" in result.stdout
    _assert_recovers_the_run(out, sim_run)
    # the converted recording's mount check finds the floor at z = 0 and draws checks.png ...
    found = re.search(r"mount check: the floor lies at z = ([-+0-9.]+) m in the base frame .* \(ok\)", result.stdout)
    assert found and abs(float(found[1])) <= 0.02 and (out / "checks.png").stat().st_size > 0
    # ... and a mount 15 cm too low puts it 15 cm below
    low = tmp_path / "low"
    result = invoke("convert", "rosbag", bag, "-o", low, "--all-frames", "--camera-mount", "0.15,0,0.20,0,10,0")
    found = re.search(r"the floor lies at z = ([-+0-9.]+) m .* \(WRONG MOUNT\? expected 0 ± 0.05 m\)", result.stdout)
    assert result.exit_code == 0 and found and float(found[1]) == pytest.approx(-0.15, abs=0.02), result.stdout
    assert_one_line_error(
        invoke("convert", "rosbag", bag, "-o", tmp_path / "x", "--camera-mount", "0.15,0,0.35"),
        contains="--camera-mount '0.15,0,0.35': expected X,Y,Z,ROLL,PITCH,YAW",
    )
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("broken", "message"),
    [
        (
            {"camera_info": False},
            "no sensor_msgs/msg/CameraInfo topic in the bag: the colour camera's intrinsics are unknown",
        ),
        (
            {"depth": False},
            "no depth image topic (sensor_msgs/Image or CompressedImage in 16UC1, 32FC1); image topics: "
            "/camera/color/image_raw (rgb8)",
        ),
        (
            {"tf_static": False},
            "no transform from base_link to camera_color_optical_frame in /tf_static or /tf (frames seen: none); "
            "give --camera-mount x,y,z,roll,pitch,yaw",
        ),
        (
            {"depth_after_ns": 1_000_000_000},
            "are never within io.rosbag.max_sync_dt_s = 0.05 s of each other: the nearest depth image is 0.267 s to "
            "1.000 s (median 0.633 s) from each colour image; the streams are not synchronised",
        ),
        (
            {"info_size": (640, 480)},
            "colour images are 320x240 but CameraInfo on /camera/color/camera_info says 640x480",
        ),
    ],
    ids=["no camera info", "no depth", "no tf to the camera", "depth 1 s off", "intrinsics of another size"],
)
def test_a_bag_that_cannot_be_converted_is_one_line(
    tmp_path: Path, sim_run: SimRun, broken: dict, message: str
) -> None:
    bag = write_sim_bag(tmp_path / "bag", sim_run, **broken)
    out = tmp_path / "seq"
    assert_one_line_error(invoke("convert", "rosbag", bag, "-o", out), contains=message)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # no temporary folder left either


def test_a_bag_without_odometry_gets_rgbd_odometry(tmp_path: Path, sim_run: SimRun) -> None:
    """A handheld camera's bag: images, CameraInfo and the mount, no odometry on any topic or on /tf."""
    bag = write_sim_bag(tmp_path / "bag", sim_run, odometry="none", frames=10)
    out = tmp_path / "seq"
    result = invoke("convert", "rosbag", bag, "-o", out, "--all-frames")
    assert result.exit_code == 0, result.output
    assert "odometry none in the bag" in result.stdout
    # colour at 15 Hz: the odometry runs on every third frame (5 Hz), and the sequence keeps those
    assert "odometry: RGB-D odometry over 4 frames (of 10: one every 0.2 s)" in result.stdout
    converted = read_sequence(out)
    odom = converted.odometry()
    assert odom is not None and np.isfinite(odom).all() and len(odom) == 4
    # the converted odometry moves as the simulated robot did, to within the RGB-D odometry's drift
    truth = _interp_planar(converted.timestamps() - (T0_NS / 1e9), (sim_run.odom_ns - T0_NS) / 1e9, sim_run.odom)
    travelled = np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()
    moved = np.hypot(*np.diff(odom[:, :2], axis=0).T).sum()
    assert moved == pytest.approx(travelled, rel=0.1), (moved, travelled)
    turned = np.rad2deg(wrap_angle(truth[-1, 2] - truth[0, 2]))
    assert np.rad2deg(wrap_angle(odom[-1, 2] - odom[0, 2])) == pytest.approx(turned, abs=3.0)
    refused = invoke("convert", "rosbag", bag, "-o", tmp_path / "x", "--odometry", "none")
    assert_one_line_error(refused, contains="no nav_msgs/msg/Odometry")


def test_compressed_images_read_as_the_raw_ones(tmp_path: Path, sim_run: SimRun) -> None:
    """image_transport's JPEG colour and compressedDepth PNG depth convert to the raw recording's frames (colour within
    JPEG's error, depth exactly); a bag with both takes the raw topics."""
    raw, packed, both = (
        write_sim_bag(tmp_path / name, sim_run, frames=4, images=name) for name in ("raw", "compressed", "both")
    )
    outs = {}
    for bag in (raw, packed, both):
        outs[bag.name] = tmp_path / f"{bag.name}-seq"
        result = invoke("convert", "rosbag", bag, "-o", outs[bag.name], "--all-frames")
        assert result.exit_code == 0, result.output
    a, b = read_sequence(outs["raw"]), read_sequence(outs["compressed"])
    assert b.meta.extras["topics"]["rgb"] == "/camera/color/image_raw/compressed"
    assert read_sequence(outs["both"]).meta.extras["topics"]["rgb"] == "/camera/color/image_raw"
    np.testing.assert_array_equal(a.meta.T_base_camera, b.meta.T_base_camera)
    assert len(a) == len(b) == 4
    for fa, fb in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.isnan(fa.depth_m), np.isnan(fb.depth_m))
        np.testing.assert_allclose(fa.depth_m, fb.depth_m, equal_nan=True)
        assert np.abs(fa.rgb.astype(int) - fb.rgb.astype(int)).mean() < 3.0
