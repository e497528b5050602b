"""TUM trajectories (planar round trip, 3D projection) and TUM RGB-D folders (association, depth scale)."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from bimfactor.errors import FormatError, InputError
from bimfactor.io.sequence import level_camera_mount, read_sequence, write_sequence
from bimfactor.io.tum import read_tum_poses, read_tum_trajectory, write_tum_trajectory
from bimfactor.io.tum_rgbd import TUM_ROS_DEFAULT, read_tum_rgbd, tum_default_intrinsics
from bimfactor.types import CameraIntrinsics, se2_to_matrix, wrap_angle

W, H = 32, 24
MAX_DT = 0.02  # io.tum_max_sync_dt_s


def test_trajectory_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    timestamps = 1_305_031_102.175304 + np.cumsum(rng.uniform(0.01, 0.05, size=20))
    poses = rng.normal(size=(20, 3)) * [4.0, 4.0, 3.0]
    write_tum_trajectory(tmp_path / "traj.txt", timestamps, poses, comment="planar test")
    t, got = read_tum_trajectory(tmp_path / "traj.txt")
    np.testing.assert_array_equal(t, timestamps)
    np.testing.assert_array_equal(got[:, :2], poses[:, :2])
    np.testing.assert_allclose(wrap_angle(got[:, 2] - poses[:, 2]), 0.0, atol=1e-12)
    assert np.all((got[:, 2] >= -np.pi) & (got[:, 2] < np.pi))


def _rotation_xyzw(yaw: float, roll: float) -> list[float]:
    """Quaternion of Rz(yaw) · Rx(roll): heading `yaw`, tilted by `roll` about the pose's own x-axis."""
    qz = [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]
    qx = [np.sin(roll / 2), 0.0, 0.0, np.cos(roll / 2)]
    x1, y1, z1, w1 = qz
    x2, y2, z2, w2 = qx
    return [
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ]


def test_3d_poses_project_to_yaw_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "traj.txt"
    q_level = _rotation_xyzw(0.5, 0.0)
    q_tilted = _rotation_xyzw(-2.0, np.deg2rad(10.0))
    path.write_text(
        f"# comment\n1.0 1.0 2.0 1.5 {' '.join(map(str, q_level))}\n2.0 -1.0 0.5 1.4 {' '.join(map(str, q_tilted))}\n"
    )
    with caplog.at_level(logging.WARNING):
        _, poses = read_tum_trajectory(path)
    np.testing.assert_allclose(poses, [[1.0, 2.0, 0.5], [-1.0, 0.5, -2.0]], atol=1e-12)
    assert "roll/pitch up to 10.0°" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        read_tum_trajectory(path, max_tilt_deg=15.0)
    assert caplog.text == ""


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("1.0 0 0 0 0 0 0 1\n1.5 0 0 0 0 0 1\n", "line 2: 7 fields, expected 8"),
        ("1.0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n", "line 2: timestamp 0.5 is not after"),
        ("1.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", "line 2: timestamp 1.0 is not after"),
        ("1.0 0 x 0 0 0 0 1\n", "line 1: not a number"),
        ("1.0 0 0 0 0 0 0 0\n", "line 1: zero quaternion"),
        ("# only a comment\n", "no poses"),
    ],
)
def test_malformed_trajectories(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "traj.txt"
    path.write_text(content)
    with pytest.raises(FormatError, match=match):
        read_tum_poses(path)


def test_default_intrinsics_by_camera() -> None:
    assert tum_default_intrinsics("rgbd_dataset_freiburg2_pioneer_360").fx == 520.9
    assert tum_default_intrinsics("rgbd_dataset_freiburg3_long_office_household").fy == 539.2
    k = tum_default_intrinsics("my_recording")
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (640, 480, *TUM_ROS_DEFAULT)


# ------------------------------------------------------------------------------------------ RGB-D folders


def _write_tum_folder(folder: Path) -> dict:
    """A tiny TUM-style folder: 6 colour images, depth slightly offset, one colour image without depth."""
    rng = np.random.default_rng(2)
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    t0 = 1_311_868_164.363181
    rgb_times = t0 + np.arange(6) / 30.0
    depth_times = rgb_times + 0.004
    depth_times = np.delete(depth_times, 3)  # colour image 3 has no depth: dropped
    depth_times = np.append(depth_times, depth_times[-1] + 1.0)  # a depth image without a colour one
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    rgb_images, depth_raw = {}, {}
    for t in rgb_times:
        name = f"rgb/{t:.6f}.png"
        rgb_images[t] = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / name), cv2.cvtColor(rgb_images[t], cv2.COLOR_RGB2BGR))
        rgb_lines.append(f"{t:.6f} {name}")
    for t in depth_times:
        name = f"depth/{t:.6f}.png"
        depth_raw[t] = rng.integers(0, 40000, size=(H, W), dtype=np.uint16)
        depth_raw[t][:2] = 0
        cv2.imwrite(str(folder / name), depth_raw[t])
        depth_lines.append(f"{t:.6f} {name}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "accelerometer.txt").write_text("# accelerometer data\n1311868164.36 0.1 -9.8 0.2\n")

    # ground truth at 100 Hz for the first 0.1 s only: colour images 4 and 5 have none; poses of the camera
    gt_times = t0 - 0.003 + np.arange(11) / 100.0
    base = np.stack([0.1 * np.arange(11), 0.05 * np.arange(11), 0.3 - 0.02 * np.arange(11)], axis=-1)
    lines = ["# ground truth trajectory"]
    for t, pose in zip(gt_times, base, strict=True):
        T_world_camera = se2_to_matrix(pose) @ level_camera_mount()
        q = _matrix_to_xyzw(T_world_camera[:3, :3])
        lines.append(f"{t:.4f} {float(pose[0])!r} {float(pose[1])!r} 0.0 {' '.join(map(repr, q))}")
    (folder / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return {"rgb_times": rgb_times, "rgb": rgb_images, "depth": depth_raw, "gt_times": gt_times, "gt": base}


def _matrix_to_xyzw(R: np.ndarray) -> list[float]:
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    return [float(x), float(y), float(z), float(w)]


def test_tum_rgbd_folder(tmp_path: Path) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg2_tiny"
    truth = _write_tum_folder(folder)
    K = CameraIntrinsics(W, H, 25.0, 25.0, 15.5, 11.5)
    seq = read_tum_rgbd(folder, max_sync_dt_s=MAX_DT, intrinsics=K)

    assert seq.meta.source == "tum" and seq.meta.intrinsics == K
    kept = [0, 1, 2, 4, 5]
    rgb_times = truth["rgb_times"][kept]
    np.testing.assert_array_equal(seq.timestamps(), [float(f"{t:.6f}") for t in rgb_times])
    assert seq.odometry() is None
    depth_by_rgb = sorted(truth["depth"])  # depth time order; depth image k+0.004 s after colour image k
    for frame, t in zip(seq, rgb_times, strict=True):
        np.testing.assert_array_equal(frame.rgb, truth["rgb"][t])
        raw = truth["depth"][min(depth_by_rgb, key=lambda d, t=t: abs(d - t))]
        want = raw.astype(np.float32) / np.float32(5000)
        want[raw == 0] = np.nan
        np.testing.assert_array_equal(frame.depth_m, want)
        assert np.isnan(frame.odom_pose).all()
        assert frame.instance_ids is None

    gt = seq.ground_truth()
    # colour images 0, 1, 2 (t0, t0 + 1/30, t0 + 2/30) have ground truth at t0 - 0.003 + k / 100 within 0.02 s
    for row, t in enumerate(rgb_times[:3]):
        k = int(np.argmin(np.abs(truth["gt_times"] - t)))
        np.testing.assert_allclose(gt[row], truth["gt"][k], atol=1e-9)
    assert np.isnan(gt[3:]).all()
    assert seq[4].gt_pose is None

    # the converter path: TUM → bimfactor sequence (no odometry) → read back
    write_sequence(tmp_path / "converted", seq.meta, seq)
    back = read_sequence(tmp_path / "converted")
    assert back.odometry() is None and len(back) == len(seq)
    np.testing.assert_array_equal(back[2].rgb, seq[2].rgb)


def test_tum_rgbd_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such TUM RGB-D folder"):
        read_tum_rgbd(tmp_path / "nothing", max_sync_dt_s=MAX_DT)
    folder = tmp_path / "tum"
    _write_tum_folder(folder)
    (folder / "depth.txt").unlink()
    with pytest.raises(FormatError, match=r"not a TUM RGB-D folder \(depth.txt missing\)"):
        read_tum_rgbd(folder, max_sync_dt_s=MAX_DT)

    folder = tmp_path / "tum2"
    _write_tum_folder(folder)
    # default intrinsics are 640x480: the 32x24 images are refused when loaded, with the file named
    seq = read_tum_rgbd(folder, max_sync_dt_s=MAX_DT)
    with pytest.raises(FormatError, match=r"\.png: image is 32x24, expected 640x480"):
        seq[0]
