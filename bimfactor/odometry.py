"""Wheel odometry: the increment between two odometry poses, the odometry motion model's noise, and keyframes.

The increments and their noise (Probabilistic Robotics, Table 5.6) are shared by the simulator (`sim.sensors`), the
back end's odometry factors and the localizer's motion model. The motion model's noise does not scale with the
increment, so a filter step is a keyframe (`keyframe_due`; `keyframe_indices` for a recording): docs/sequences.md.
"""

from __future__ import annotations

import math

import numpy as np

from bimfactor.types import se2_between, wrap_angle

ODOMETRY_MIN_TRANSLATION_M = 1e-4  # below this an increment is a pure turn: δrot1 = 0, δrot2 = Δθ


def keyframe_due(last: np.ndarray, pose: np.ndarray, distance_m: float, angle_rad: float) -> bool:
    """Whether `pose` (x, y, yaw) has moved `distance_m` or turned `angle_rad` from the `last` keyframe's pose."""
    moved = math.hypot(pose[0] - last[0], pose[1] - last[1])
    turned = abs(float(wrap_angle(pose[2] - last[2])))
    return moved >= distance_m or turned >= angle_rad


def keyframe_indices(poses: np.ndarray, distance_m: float, angle_rad: float) -> np.ndarray:
    """Rows of (N, 3) poses that are keyframes: the first, then each one `keyframe_due` from the last kept."""
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    kept = [0] if len(poses) else []
    for i in range(1, len(poses)):
        if keyframe_due(poses[kept[-1]], poses[i], distance_m, angle_rad):
            kept.append(i)
    return np.asarray(kept, np.int64)


def odometry_increment(odom_prev: np.ndarray, odom_curr: np.ndarray) -> np.ndarray:
    """(3,) dx, dy, dyaw in the robot frame between two consecutive (3,) odometry poses T_odom_base."""
    return se2_between(np.asarray(odom_prev, float), np.asarray(odom_curr, float))


def odometry_increments(poses: np.ndarray) -> np.ndarray:
    """(N, 3) poses → (N−1, 3) increments (δrot1, δtrans, δrot2) of the odometry motion model.

    Backward motion is a negative δtrans with δrot1 ∈ (−π/2, π/2] (as AMCL's odometry model treats it), not a turn
    by π: otherwise the few centimetres an in-place turn slips backwards would read as δrot1 = π, δrot2 = Δθ − π, and
    the noise model (α1 δrot1², α1 δrot2²) would give that keyframe's heading σ ≈ 55° instead of a few degrees.
    """
    poses = np.asarray(poses, float)
    d = np.diff(poses[:, :2], axis=0)
    trans = np.hypot(d[:, 0], d[:, 1])
    turn = wrap_angle(np.diff(poses[:, 2]))
    rot1 = np.where(trans >= ODOMETRY_MIN_TRANSLATION_M, wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - poses[:-1, 2]), 0.0)
    backward = np.abs(rot1) > np.pi / 2
    rot1 = np.where(backward, wrap_angle(rot1 + np.pi), rot1)
    trans = np.where(backward, -trans, trans)
    rot2 = wrap_angle(turn - rot1)
    return np.stack([rot1, trans, rot2], axis=1)


def odometry_increment_variances(increments: np.ndarray, alpha: list[float] | np.ndarray) -> np.ndarray:
    """(N, 3) variances of the noise on (δrot1, δtrans, δrot2) for (N, 3) increments (Thrun et al., Table 5.6)."""
    a1, a2, a3, a4 = alpha
    rot1, trans, rot2 = np.asarray(increments, float).T
    return np.stack(
        [a1 * rot1**2 + a2 * trans**2, a3 * trans**2 + a4 * (rot1**2 + rot2**2), a1 * rot2**2 + a2 * trans**2], axis=1
    )


def odometry_covariance(increment: np.ndarray, alpha: list[float] | np.ndarray) -> np.ndarray:
    """(3, 3) covariance of a (3,) robot-frame increment (dx, dy, dyaw) under the odometry motion model's noise
    (α1..α4 as in `odometry_increment_variances`), propagated through (δrot1, δtrans, δrot2) → (dx, dy, dyaw)."""
    dx, dy, dyaw = np.asarray(increment, np.float64)
    rot1, trans, rot2 = odometry_increments(np.array([[0.0, 0.0, 0.0], [dx, dy, dyaw]]))[0]
    variances = odometry_increment_variances(np.array([[rot1, trans, rot2]]), alpha)[0]
    c, s = np.cos(rot1), np.sin(rot1)
    jacobian = np.array([[-trans * s, c, 0.0], [trans * c, s, 0.0], [1.0, 0.0, 1.0]])
    return jacobian @ np.diag(variances) @ jacobian.T
