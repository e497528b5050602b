"""Wheel odometry: exact without noise, and the odometry motion model's variances with it."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.sim.sensors import simulate_odometry
from bimfactor.sim.trajectory import SimTrajectory
from bimfactor.types import se2_between, se2_compose

ALPHA = (0.05, 0.01, 0.02, 0.01)  # small enough that a noisy δtrans never changes sign in these tests
SAMPLES = 20_000


def _repeat(increment: np.ndarray, n: int, start: np.ndarray) -> np.ndarray:
    """(n + 1, 3) poses from `start`, each the previous one composed with `increment`."""
    poses = [np.asarray(start, float)]
    for _ in range(n):
        poses.append(se2_compose(poses[-1], increment))
    return np.asarray(poses)


def _model_terms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3) (δrot1, δtrans, δrot2) between consecutive (N, 3) poses a → b, written out independently."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    rot1 = np.arctan2(dy, dx) - a[:, 2]
    rot2 = b[:, 2] - a[:, 2] - rot1
    wrap = lambda x: np.arctan2(np.sin(x), np.cos(x))  # noqa: E731
    return np.column_stack([wrap(rot1), np.hypot(dx, dy), wrap(rot2)])


def test_without_noise_odometry_increments_equal_ground_truth(six_trajectories: list[SimTrajectory]) -> None:
    gt = six_trajectories[0].keyframe_poses
    odom = simulate_odometry(gt, [0.0, 0.0, 0.0, 0.0], np.random.default_rng(0))
    np.testing.assert_array_equal(odom[0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(se2_between(odom[:-1], odom[1:]), se2_between(gt[:-1], gt[1:]), atol=1e-9)
    # Odometry is the ground truth seen from its own start: one rigid transform maps one onto the other.
    np.testing.assert_allclose(se2_compose(gt[0], odom), gt, atol=1e-9)


@pytest.mark.parametrize("increment", [(0.45, 0.12, 0.3), (0.5, 0.0, 0.0), (0.0, 0.0, 0.26)])
def test_increment_errors_follow_the_model(increment: tuple[float, float, float]) -> None:
    inc = np.asarray(increment)
    gt = _repeat(inc, SAMPLES, start=np.array([3.0, -2.0, 1.0]))
    odom = simulate_odometry(gt, ALPHA, np.random.default_rng(7))
    truth = _model_terms(gt[:1], gt[1:2])[0]
    if truth[1] < 1e-9:  # a pure turn: the model puts all of it into δrot2
        truth[0], truth[2] = 0.0, inc[2]
    noisy = _model_terms(odom[:-1], odom[1:])
    if truth[1] < 1e-9:  # δrot1 stays 0, so δtrans is the signed step along the heading
        d = odom[1:, :2] - odom[:-1, :2]
        heading = odom[:-1, 2]
        np.testing.assert_allclose(d[:, 0] * np.sin(heading) - d[:, 1] * np.cos(heading), 0.0, atol=1e-12)
        noisy[:, 0] = 0.0
        noisy[:, 1] = d[:, 0] * np.cos(heading) + d[:, 1] * np.sin(heading)
        noisy[:, 2] = np.arctan2(np.sin(odom[1:, 2] - heading), np.cos(odom[1:, 2] - heading))
    a1, a2, a3, a4 = ALPHA
    rot1, trans, rot2 = truth
    variance = np.array(
        [a1 * rot1**2 + a2 * trans**2, a3 * trans**2 + a4 * (rot1**2 + rot2**2), a1 * rot2**2 + a2 * trans**2]
    )
    error = noisy - truth
    for k in range(3):
        if variance[k] == 0:
            assert np.abs(error[:, k]).max() < 1e-9
            continue
        assert abs(error[:, k].mean()) < 4 * np.sqrt(variance[k] / SAMPLES)
        assert error[:, k].var() == pytest.approx(variance[k], rel=0.05)
