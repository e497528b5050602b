"""Lifting masks to 3D: back-projection, the camera mount and odometry pose, voxels, DBSCAN denoising."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import Config
from bimfactor.perception.lifting import (
    T_odom_camera,
    backproject,
    largest_cluster,
    lift_mask,
    pack_voxels,
    transform_points,
    unpack_voxels,
    voxel_centres,
    voxelize,
)
from bimfactor.sim.sensors import camera_mount
from bimfactor.types import CameraIntrinsics

K = CameraIntrinsics.from_hfov(32, 24, 90.0)


def test_backproject_fronto_parallel_plane_gives_pinhole_points() -> None:
    depth = np.full((24, 32), 2.0, np.float32)
    points = backproject(depth, np.ones((24, 32), bool), K, max_depth_m=10.0, max_points=10_000)
    v, u = np.divmod(np.arange(24 * 32), 32)
    expected = np.column_stack([(u - K.cx) / K.fx * 2.0, (v - K.cy) / K.fy * 2.0, np.full(len(u), 2.0)])
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-12)


def test_wall_ahead_lands_where_the_mount_and_odometry_pose_put_it(test_config: Config) -> None:
    """A wall 3 m ahead of the camera, robot at odometry pose (1, 2, 90°): the wall is the plane y = 2 + 3.15."""
    mount = camera_mount(test_config.sim.camera)  # 0.15 m ahead of the base, 0.5 m up, level
    depth = np.full((24, 32), 3.0, np.float32)
    camera_points = backproject(depth, np.ones((24, 32), bool), K, 10.0, 10_000)
    odom_points = transform_points(T_odom_camera(np.array([1.0, 2.0, np.pi / 2]), mount), camera_points)
    # camera x (right) → base −y → odom +x; camera y (down) → −z; camera z (forward) → base x → odom +y
    expected = np.column_stack([1.0 + camera_points[:, 0], 2.0 + 0.15 + camera_points[:, 2], 0.5 - camera_points[:, 1]])
    np.testing.assert_allclose(odom_points, expected, rtol=0, atol=1e-12)
    assert np.allclose(odom_points[:, 1], 5.15)


def test_no_return_far_depth_and_unmasked_pixels_are_not_lifted() -> None:
    depth = np.full((24, 32), 2.0, np.float32)
    depth[0, :] = np.nan
    depth[1, :] = 9.0
    mask = np.ones((24, 32), bool)
    mask[:, :4] = False
    points = backproject(depth, mask, K, max_depth_m=6.0, max_points=10_000)
    assert len(points) == 22 * 28
    assert np.all(points[:, 2] == 2.0)
    assert len(backproject(depth, mask, K, 6.0, max_points=100)) == 100


def test_voxel_keys_round_trip_with_negative_indices() -> None:
    voxels = np.array([[0, 0, 0], [-1, 5, -7], [1000, -1000, 3], [-(2**20), 2**20 - 1, 0]])
    np.testing.assert_array_equal(unpack_voxels(pack_voxels(voxels)), voxels)


def test_voxelize_downsamples_to_unique_voxel_centres() -> None:
    points = np.array([[0.01, 0.01, 0.01], [0.04, 0.02, 0.03], [0.06, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    keys = voxelize(points, 0.05)
    np.testing.assert_allclose(
        voxel_centres(keys, 0.05), [[-0.025, 0.025, 0.025], [0.025, 0.025, 0.025], [0.075, 0.025, 0.025]]
    )


def test_largest_cluster_keeps_the_big_blob_only() -> None:
    rng = np.random.default_rng(0)
    big = rng.uniform(0, 0.5, (300, 3))
    small = rng.uniform(0, 0.2, (40, 3)) + 3.0
    strays = np.array([[10.0, 0, 0], [0, 10.0, 0]])
    keep = largest_cluster(np.concatenate([big, small, strays]), eps_m=0.12, min_points=4)
    np.testing.assert_array_equal(keep, np.r_[np.ones(300, bool), np.zeros(42, bool)])
    assert not largest_cluster(strays, 0.12, 4).any()


def test_lift_mask_drops_the_background_a_mask_bleeds_into(test_config: Config) -> None:
    """An object surface at 2 m (320 × 240 camera); the mask also holds scattered wall pixels 3 m behind it."""
    cfg = test_config.perception
    k = CameraIntrinsics.from_hfov(320, 240, 90.0)
    depth = np.full((240, 320), 5.0, np.float32)
    depth[60:180, 80:240] = 2.0
    mask = np.zeros((240, 320), bool)
    mask[60:180, 80:240] = True
    mask[[20, 200, 220, 30], [30, 280, 50, 300]] = True
    keys = lift_mask(depth, mask, k, np.eye(4), cfg)
    centres = voxel_centres(keys, cfg.voxel_size_m)
    assert len(keys) > 20
    assert centres[:, 2].max() < 2.0 + cfg.voxel_size_m
    assert centres[:, 2].min() >= 2.0 - cfg.voxel_size_m


@pytest.mark.parametrize("pose", [(0.0, 0.0, 0.0), (3.0, -1.0, 2.5)])
def test_T_odom_camera_is_the_planar_pose_times_the_mount(pose, test_config: Config) -> None:
    mount = camera_mount(test_config.sim.camera)
    T = T_odom_camera(np.array(pose), mount)
    origin = transform_points(T, np.zeros((1, 3)))[0]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    np.testing.assert_allclose(origin, [pose[0] + 0.15 * c, pose[1] + 0.15 * s, 0.5], atol=1e-12)
