"""The kinematic motion model: increments from odometry and velocities, the noise the paper adds, and the odometry
motion model's covariance the pose graphs use."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.localization.motion import propagate, propagate_velocity, velocity_increment
from bimfactor.odometry import (
    keyframe_due,
    keyframe_indices,
    odometry_covariance,
    odometry_increment,
    odometry_increment_variances,
    odometry_increments,
)

SIGMA_TRANS_M = 0.2
SIGMA_ROT_RAD = np.deg2rad(10.0)


def test_increment_between_odometry_poses_is_in_the_robot_frame():
    np.testing.assert_allclose(
        odometry_increment([1.0, 1.0, 0.0], [1.0, 2.0, np.pi / 2]), [0.0, 1.0, np.pi / 2], atol=1e-12
    )
    np.testing.assert_allclose(
        odometry_increment([0.0, 0.0, np.pi / 2], [0.0, 1.0, np.pi / 2]), [1.0, 0.0, 0.0], atol=1e-12
    )


def test_velocity_increment_is_an_arc_or_a_straight_line():
    r = 2.0 / np.pi  # a quarter turn at 1 m/s and π/2 rad/s
    np.testing.assert_allclose(velocity_increment(1.0, np.pi / 2, 1.0), [r, r, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(velocity_increment(0.5, 0.0, 2.0), [1.0, 0.0, 0.0])


def test_noise_free_propagation_applies_the_increment_in_each_particle_frame():
    particles = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, np.pi / 2], [2.0, 0.0, np.pi]])
    moved = propagate(particles, [1.0, 0.0, 0.1], 0.0, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(
        moved, [[1.0, 0.0, 0.1], [1.0, 2.0, np.pi / 2 + 0.1], [1.0, 0.0, -np.pi + 0.1]], atol=1e-12
    )
    np.testing.assert_allclose(particles[0], [0.0, 0.0, 0.0])  # the input is not changed


def test_noise_mean_and_covariance_match_the_sigmas():
    n = 200_000
    start = np.tile([2.0, -1.0, 0.3], (n, 1))
    moved = propagate(start, [0.5, 0.0, 0.2], SIGMA_TRANS_M, SIGMA_ROT_RAD, np.random.default_rng(42))
    expected_mean = [2.0 + 0.5 * np.cos(0.3), -1.0 + 0.5 * np.sin(0.3), 0.5]
    np.testing.assert_allclose(moved.mean(axis=0), expected_mean, atol=3e-3)
    cov = np.cov(moved.T)
    expected = np.diag([SIGMA_TRANS_M**2, SIGMA_TRANS_M**2, SIGMA_ROT_RAD**2])
    np.testing.assert_allclose(cov, expected, rtol=0.03, atol=3e-4)


def test_yaw_noise_wraps_across_pi():
    start = np.tile([0.0, 0.0, np.pi - 0.01], (10_000, 1))
    moved = propagate(start, [0.0, 0.0, 0.0], 0.0, SIGMA_ROT_RAD, np.random.default_rng(1))
    assert np.all(moved[:, 2] >= -np.pi) and np.all(moved[:, 2] < np.pi)
    assert (moved[:, 2] < 0).mean() > 0.4  # about half the particles crossed to −π


def test_velocity_form_equals_increment_form_with_the_same_generator():
    particles = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, -1.0]])
    a = propagate_velocity(particles, 0.8, 0.3, 0.5, 0.1, 0.05, np.random.default_rng(7))
    b = propagate(particles, velocity_increment(0.8, 0.3, 0.5), 0.1, 0.05, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("increment", [[0.5, 0.0, 0.0], [0.4, 0.1, 0.3], [0.0, 0.0, 0.3], [-0.4, 0.1, 0.3]])
def test_odometry_covariance_matches_the_sampled_motion_model(increment):
    """Sample the odometry motion model (as the simulator does) and compare the increments' spread."""
    alpha = [0.05, 0.01, 0.05, 0.01]
    rng = np.random.default_rng(0)
    start = np.zeros(3)
    parts = odometry_increments(np.array([start, increment]))[0]
    sigma = np.sqrt(odometry_increment_variances(parts[None], alpha)[0])
    rot1, trans, rot2 = (parts + sigma * rng.standard_normal((100_000, 3))).T
    sampled = np.column_stack([trans * np.cos(rot1), trans * np.sin(rot1), rot1 + rot2])
    expected = odometry_covariance(np.array(increment), alpha)
    np.testing.assert_allclose(np.cov(sampled.T), expected, rtol=0.1, atol=1e-4)


def test_backward_motion_is_a_negative_translation_not_a_half_turn():
    rot1, trans, rot2 = odometry_increments(
        np.array([[1.0, 2.0, 0.5], [1.0 - 0.4 * np.cos(0.5), 2.0 - 0.4 * np.sin(0.5), 0.8]])
    )[0]
    np.testing.assert_allclose([rot1, trans, rot2], [0.0, -0.4, 0.3], atol=1e-12)


def test_an_in_place_turn_that_slips_backwards_keeps_its_heading_sigma():
    """An 18° turn on the spot that slips 2.6 cm is as certain in heading whichever way it slipped (it was 54° when
    the backward slip read as a turn by π)."""
    alpha = [0.05, 0.01, 0.05, 0.01]
    forward = odometry_covariance(np.array([0.026, 0.0, 0.314]), alpha)
    backward = odometry_covariance(np.array([-0.026, 0.0, 0.314]), alpha)
    np.testing.assert_allclose(np.diag(backward), np.diag(forward), atol=1e-12)  # the y–yaw term turns sign
    assert np.rad2deg(np.sqrt(backward[2, 2])) < 5.0
    assert np.sqrt(backward[0, 0]) < 0.05


def test_keyframes_every_distance_or_turn_from_the_last_kept():
    turn = np.deg2rad(15.0)
    poses = np.array(
        [
            [0.0, 0.0, 0.0],  # first: always
            [0.3, 0.0, 0.0],  # 0.3 m
            [0.5, 0.0, 0.0],  # 0.5 m from the first: kept
            [0.6, 0.1, 0.2],  # 0.14 m, 11.5°
            [0.6, 0.1, 0.27],  # 15.5° from the last kept: kept
            [0.6, 0.1, 0.27 + 2 * np.pi],  # the same heading, one turn on
            [0.9, 0.5, 0.27],  # 0.5 m: kept
            [0.9, 0.5, np.pi - 0.1],  # 149° from the last kept, across the seam below: kept
            [0.9, 0.5, -np.pi + 0.1],  # 11.5° on across ±π
        ]
    )
    np.testing.assert_array_equal(keyframe_indices(poses, 0.5, turn), [0, 2, 4, 6, 7])
    assert keyframe_indices(np.zeros((0, 3)), 0.5, turn).shape == (0,)
    assert not keyframe_due(poses[7], poses[8], 0.5, turn)
    assert keyframe_due(poses[7], poses[8], 0.5, np.deg2rad(11.0))
