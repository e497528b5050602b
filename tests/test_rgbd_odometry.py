"""RGB-D odometry (`bimfactor.io.rgbd_odometry`): the mount projection, the fall-backs when features or depth give
out, the noise model's fit, simulated textureless pairs and the real slambook frames. The simulated drift of a
converted recording is tests/io/test_convert_odometry.py's; `-s` prints the figures."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import load_config
from bimfactor.io import rgbd_odometry as ro
from bimfactor.io.sequence import FrameImages, Sequence, level_camera_mount
from bimfactor.sim.sensors import camera_mount, simulate_odometry
from bimfactor.types import CameraIntrinsics, SequenceMeta, matrix_to_se2, se2_between, se2_compose, se2_to_matrix

SLAMBOOK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "slambook-dining"
SLAMBOOK_K = CameraIntrinsics(640, 480, 518.0, 519.0, 325.5, 253.5)  # its README
SMALL_K = CameraIntrinsics.from_hfov(160, 120, 90.0)
GREY = np.full((SMALL_K.height, SMALL_K.width, 3), 128, np.uint8)  # no texture: ORB finds nothing, PnP fails


def _relative_pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) of T_true⁻¹ T."""
    D = np.linalg.inv(T_true) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))))


def _ray_slopes() -> tuple[np.ndarray, np.ndarray]:
    """(H, W) x/z and y/z of each pixel's ray (camera frame: x right, y down)."""
    u, v = np.meshgrid(np.arange(SMALL_K.width), np.arange(SMALL_K.height))
    return (u - SMALL_K.cx) / SMALL_K.fx, (v - SMALL_K.cy) / SMALL_K.fy


def _depth(surfaces: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The nearest of (S, H, W) surface depths (inf: missed), with 2 mm noise; beyond 8 m no return (NaN)."""
    depth = surfaces.min(axis=0) + rng.normal(0.0, 0.002, surfaces.shape[1:])
    return np.where(depth < 8.0, depth, np.nan).astype(np.float32)


def _floor(slope_y: np.ndarray) -> np.ndarray:
    """Depth of an endless floor 0.5 m below a level camera."""
    with np.errstate(divide="ignore"):
        return np.where(slope_y > 0, 0.5 / slope_y, np.inf)


def _facing_wall(wall_m: float, rng: np.random.Generator) -> np.ndarray:
    """A level camera 0.5 m above an endless floor, facing an endless wall `wall_m` ahead."""
    _, slope_y = _ray_slopes()
    return _depth(np.stack([_floor(slope_y), np.full(slope_y.shape, wall_m)]), rng)


def _wall_on_the_left(wall_m: float, rng: np.random.Generator) -> np.ndarray:
    """A level camera 0.5 m above an endless floor, looking along an endless wall `wall_m` to its left."""
    slope_x, slope_y = _ray_slopes()
    with np.errstate(divide="ignore"):
        wall = np.where(slope_x < 0, wall_m / -slope_x, np.inf)
    return _depth(np.stack([_floor(slope_y), wall]), rng)


def _base_step(pair: ro.PairOdometry) -> np.ndarray:
    mount = level_camera_mount(0.5)
    return matrix_to_se2(mount @ pair.T_prev_curr @ np.linalg.inv(mount))


def test_camera_motion_becomes_base_motion_through_a_pitched_raised_mount() -> None:
    """T_odom_base = T_base_camera · T_cam0_cam · T_base_camera⁻¹ undoes the mount exactly for a planar drive."""
    camera = load_config().sim.camera.model_copy(
        update={"mount_pitch_deg": -20.0, "mount_forward_m": 0.2, "mount_height_m": 0.6}
    )
    mount = camera_mount(camera)
    base = np.array([[1.0, 2.0, 0.3], [1.5, 2.2, 0.5], [2.0, 2.1, -0.4], [1.2, 1.0, 2.9]])  # T_world_base
    cameras = [se2_to_matrix(b) @ mount for b in base]
    relative = [np.linalg.inv(a) @ b for a, b in itertools.pairwise(cameras)]
    odom = ro.planar_odometry(ro.chain_relative_poses(relative), mount)
    np.testing.assert_allclose(odom, se2_between(base[0], base), atol=1e-9)
    assert np.allclose(odom[0], 0.0)


def test_along_a_wall_the_depth_measures_the_distance_and_the_prior_the_travel() -> None:
    """Driving along a wall over a floor (no texture: the pair falls back), depth sees the robot close in on the wall
    by 0.1 m but not how far it went along it: that is the previous motion's, whatever it was."""
    odometry = ro.RgbdOdometry(SMALL_K, level_camera_mount(0.5))
    rng = np.random.default_rng(0)
    prev = odometry.prepare(GREY, _wall_on_the_left(1.0, rng))
    curr = odometry.prepare(GREY, _wall_on_the_left(0.9, rng))
    for travel_m in (0.5, 0.3):
        previous = np.eye(4)
        previous[2, 3] = travel_m  # camera z is the base's x
        pair = odometry.relative_pose(prev, curr, previous)
        assert pair.fell_back and pair.start == "previous" and pair.measured_directions == 1 and pair.fitness > 0.8
        np.testing.assert_allclose(_base_step(pair), [travel_m, 0.1, 0.0], atol=3e-3)


def test_where_depth_cannot_tell_a_wheeled_base_does_not_slide_sideways() -> None:
    """Facing a wall, depth measures the approach (0.1 m) but not a slide along it: a wheeled base (the default) drives
    no sideways step whatever the previous motion did; a handheld camera (`nonholonomic=False`) keeps the previous
    motion's slide."""
    rng = np.random.default_rng(1)
    for nonholonomic in (True, False):
        odometry = ro.RgbdOdometry(SMALL_K, level_camera_mount(0.5), nonholonomic=nonholonomic)
        prev = odometry.prepare(GREY, _facing_wall(2.0, rng))
        curr = odometry.prepare(GREY, _facing_wall(1.9, rng))
        previous = np.eye(4)
        previous[0, 3] = 0.3  # camera x (right) is the base's −y
        pair = odometry.relative_pose(prev, curr, previous)
        assert pair.measured_directions == 1 and pair.fitness > 0.9
        np.testing.assert_allclose(_base_step(pair), [0.1, 0.0 if nonholonomic else -0.3, 0.0], atol=3e-3)


def test_a_frame_without_depth_keeps_the_previous_motion() -> None:
    odometry = ro.RgbdOdometry(SMALL_K, level_camera_mount(0.5))
    rng = np.random.default_rng(1)
    prev = odometry.prepare(GREY, _facing_wall(2.0, rng))
    blind = odometry.prepare(GREY, np.full((SMALL_K.height, SMALL_K.width), np.nan, np.float32))
    previous = se2_to_matrix([0.0, 0.0, 0.2])
    pair = odometry.relative_pose(prev, blind, previous)
    np.testing.assert_array_equal(pair.T_prev_curr, previous)
    assert pair.fitness == 0.0 and pair.measured_directions == 0 and pair.start == "previous"
    zeros = odometry.prepare(GREY, np.zeros((SMALL_K.height, SMALL_K.width), np.float32))  # 0 = no return too
    assert len(zeros.clouds[0].points) == 0 and np.isnan(zeros.keypoints_camera).all()


def test_a_single_frame_has_the_origin_as_odometry() -> None:
    meta = SequenceMeta("one", "test", SMALL_K, level_camera_mount(0.5))
    depth = _facing_wall(2.0, np.random.default_rng(2))
    sequence = Sequence(meta, np.array([0.0]), lambda i: FrameImages(GREY, depth, None))
    result = ro.rgbd_odometry(sequence, show_progress=False)
    np.testing.assert_array_equal(result.odom_poses, np.zeros((1, 3)))
    assert result.pairs == [] and result.fell_back.shape == (0,)


def test_the_noise_model_fit_recovers_the_alpha_that_made_the_noise() -> None:
    """Odometry drawn by the simulator's motion model (Thrun's sample_motion_model_odometry) with known α gives that
    α back; perfect odometry gives α = 0 and no drift."""
    rng = np.random.default_rng(4)
    alpha = [0.05, 0.01, 0.05, 0.01]
    step_kinds = np.array([[0.5, 0.0, 0.0], [0.0, 0.0, np.radians(18.0)], [0.45, 0.05, np.radians(12.0)]])
    truths, noisy = [], []
    for _ in range(40):
        steps = step_kinds[rng.integers(0, 3, 200)]
        steps[:, 2] *= rng.choice([-1.0, 1.0], 200)  # left and right turns
        poses = [np.zeros(3)]
        for step in steps:
            poses.append(se2_compose(poses[-1], step))
        truths.append(np.array(poses))
        noisy.append(simulate_odometry(truths[-1], alpha, rng))
    noise = ro.odometry_noise(noisy, truths)
    np.testing.assert_allclose(noise.alpha, alpha, rtol=0.2)
    assert noise.steps == 40 * 200 and len(noise.drift_pct) == 40 and min(noise.drift_pct) > 0.5
    exact = ro.odometry_noise(truths[:2], truths[:2])
    assert np.all(exact.alpha == 0) and exact.drift_pct == [0.0, 0.0] and exact.yaw_err_deg == 0.0


def test_simulated_textureless_pairs_are_carried_by_the_depth(drive) -> None:
    """The simulated drive with its colour blanked: no pair has a feature guess, and the depth alignment still gets
    most pairs (0.13–0.52 m, up to 18° apart) to within a centimetre and a tenth of a degree."""
    frames = [dataclasses.replace(f, rgb=np.full_like(f.rgb, 128)) for f in drive.frames[:8]]
    result = ro.rgbd_odometry(Sequence.from_frames(drive.meta, frames), show_progress=False)
    assert result.fell_back.all()
    mount = drive.meta.T_base_camera
    errors = []
    for k, pair in enumerate(result.pairs):
        truth = np.linalg.inv(se2_to_matrix(frames[k].gt_pose) @ mount) @ se2_to_matrix(frames[k + 1].gt_pose) @ mount
        errors.append(_relative_pose_error(pair.T_prev_curr, truth))
    trans_err, rot_err = np.median(errors, axis=0)
    assert trans_err < 0.01 and rot_err < 0.1, errors


@pytest.fixture(scope="module")
def slambook_result() -> tuple[ro.RgbdOdometryResult, list[np.ndarray]]:
    if not SLAMBOOK.is_dir():
        pytest.skip(f"real frames not available: {SLAMBOOK}")
    from bimfactor.io.tum import read_tum_poses
    from bimfactor.io.tum_rgbd import read_tum_rgbd

    sequence = read_tum_rgbd(SLAMBOOK, max_sync_dt_s=0.02, intrinsics=SLAMBOOK_K)
    _, published = read_tum_poses(SLAMBOOK / "groundtruth.txt")
    return ro.rgbd_odometry(sequence, show_progress=False), list(published)


def test_real_pairs_are_within_12_cm_and_3_degrees_of_the_published_poses(slambook_result) -> None:
    """Five real Kinect frames (published poses good to a few cm; the first pair turns 25.5° over 0.41 m): every pair
    has a feature guess, and each relative pose and the chained last pose are within 12 cm and 3°."""
    result, published = slambook_result
    assert len(result.pairs) == 4 and not result.fell_back.any()
    for k, pair in enumerate(result.pairs):
        metres, degrees = _relative_pose_error(pair.T_prev_curr, np.linalg.inv(published[k]) @ published[k + 1])
        assert metres < 0.12 and degrees < 3.0, (k, metres, degrees)
    metres, degrees = _relative_pose_error(result.T_cam0_cam[-1], np.linalg.inv(published[0]) @ published[-1])
    assert metres < 0.12 and degrees < 3.0, (metres, degrees)


def test_the_odometry_runs_on_frames_at_least_a_fifth_of_a_second_apart() -> None:
    """A 30 Hz recording is processed at 5 Hz; frames already further apart are all kept, and so is the first."""
    thirty_hz = 100.0 + np.arange(90) / 30.0
    taken = ro.odometry_frames(thirty_hz)
    assert taken[0] == 0 and np.all(np.diff(thirty_hz[taken]) >= ro.FRAME_INTERVAL_S - 1e-3)
    assert np.all(np.diff(thirty_hz[taken]) < ro.FRAME_INTERVAL_S + 1.0 / 30.0)
    assert len(taken) == 15
    one_hz = np.arange(10.0)
    np.testing.assert_array_equal(ro.odometry_frames(one_hz), np.arange(10))
