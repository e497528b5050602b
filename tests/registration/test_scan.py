"""Back-projection of depth into the base frame, height filtering, and submap stitching."""

from __future__ import annotations

import numpy as np

from bimfactor.config import Config
from bimfactor.localization.measurements.scan import DepthPoints
from bimfactor.registration.scan import frame_scan, stitch_submap
from bimfactor.sim.sensors import camera_mount
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta, se2_inverse, se2_to_matrix


def _camera(cfg: Config) -> tuple[CameraIntrinsics, np.ndarray]:
    cam = cfg.sim.camera
    return CameraIntrinsics.from_hfov(64, 48, cam.hfov_deg), camera_mount(cam)


def test_depth_plane_backprojects_to_a_wall_ahead(test_config: Config) -> None:
    intrinsics, T_base_camera = _camera(test_config)
    depth = np.full((48, 64), 3.0, dtype=np.float32)
    depth[0, :] = np.nan  # no return on the top row
    points = DepthPoints.of(depth, intrinsics, T_base_camera).base
    assert len(points) == 47 * 64
    cam = test_config.sim.camera
    # A level camera looking along base x: a fronto-parallel depth plane is the plane x = forward + 3.
    np.testing.assert_allclose(points[:, 0], cam.mount_forward_m + 3.0, atol=1e-9)
    # Pixel (u, v) lands at y = −(u − cx)/fx·z (left is +y) and z = h − (v − cy)/fy·z (up is +z).
    v, u = 10, 5
    row = (v - 1) * 64 + u
    np.testing.assert_allclose(points[row, 1], -(u - intrinsics.cx) / intrinsics.fx * 3.0, atol=1e-9)
    z_expected = cam.mount_height_m - (v - intrinsics.cy) / intrinsics.fy * 3.0
    np.testing.assert_allclose(points[row, 2], z_expected, atol=1e-9)


def test_frame_scan_keeps_the_wall_band_only(test_config: Config) -> None:
    intrinsics, T_base_camera = _camera(test_config)
    depth = np.full((48, 64), 3.0, dtype=np.float32)
    meta = SequenceMeta("t", "test", intrinsics, T_base_camera)
    frame = Frame(0, 0.0, np.zeros((48, 64, 3), np.uint8), depth, np.zeros(3))
    rc, sensor = test_config.registration, test_config.sensor
    scan = frame_scan(frame, meta, rc, sensor)
    assert len(scan) > 0
    assert scan[:, 2].min() >= sensor.min_z_m and scan[:, 2].max() <= rc.scan_max_z_m
    far = frame_scan(Frame(0, 0.0, frame.rgb, depth + sensor.max_range_m, np.zeros(3)), meta, rc, sensor)
    assert len(far) == 0


def test_submap_stitches_scans_into_the_current_base_frame() -> None:
    world_points = np.array([[5.0, 1.0, 1.0], [6.0, -2.0, 0.5], [4.0, 3.0, 1.5]])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.4]])  # odometry frame poses of two keyframes
    scans = []
    for pose in poses:
        T = se2_to_matrix(se2_inverse(pose))
        scans.append(world_points @ T[:3, :3].T + T[:3, 3])
    submap = stitch_submap(scans, poses, voxel_m=0.01)
    # Both scans saw the same points: stitched into the last frame they coincide with that frame's own scan.
    expected = scans[-1]
    assert len(submap) == len(expected)
    for point in expected:
        assert np.min(np.linalg.norm(submap - point, axis=1)) < 1e-9
