"""GTSAM factors and noise models of the per-mode pose graphs, built from config values.

Keys: `X(i)` is the robot pose (gtsam.Pose2) at keyframe i, `L(j)` the BIM object with id j (gtsam.Point2); the
door plates (`bim.plates`) follow the objects as landmarks N, N + 1, … of a prior with N objects, and a step's
measurement k is its node k or, past its K nodes, its text reading k − K (`Observations.measurements`).
GTSAM's Pose2 tangent space is body-frame (dx, dy, dθ); covariances the rest of bimfactor reads are world-frame
(x, y, yaw), so `covariance_world_to_body` / `covariance_body_to_world` rotate between the two.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from bimfactor.bim.plates import PLATE_REACH_M, door_plates
from bimfactor.config import BackendConfig, OdometryConfig
from bimfactor.odometry import odometry_covariance
from bimfactor.types import Observations

__all__ = [
    "L",
    "Landmarks",
    "X",
    "bearing_range_noise",
    "covariance_body_to_world",
    "covariance_world_to_body",
    "from_pose2",
    "information_pose_factor",
    "landmark_factors",
    "landmark_prior_factor",
    "odometry_factor",
    "odometry_noise_covariance",
    "pose_prior_factor",
    "to_pose2",
]

Association = Sequence[tuple[int, int]]  # (measurement index, landmark id) pairs


@dataclass(frozen=True)
class Landmarks:
    """The BIM objects as landmarks, row = object id: (N, 2) footprint centres and (N, 2) footprint sizes (x, y)."""

    xy: np.ndarray
    size: np.ndarray

    @classmethod
    def of(cls, landmarks: Landmarks | np.ndarray) -> Landmarks:
        """Landmarks as given, or point landmarks (zero footprint) at the first two columns of an (N, ≥2) array."""
        if isinstance(landmarks, Landmarks):
            return landmarks
        xy = np.asarray(landmarks, np.float64).reshape(len(landmarks), -1)[:, :2].copy()
        return cls(xy, np.zeros_like(xy))

    @classmethod
    def from_prior(cls, prior: Any) -> Landmarks:
        """A BimPrior's objects (their footprint boxes' centres and sizes), then its door plates in `door_plates`
        order: each at its door's centre, as long along the wall as the door plus `PLATE_REACH_M` either side (where
        the plate hangs beside the door is not in the model)."""
        xy, size = prior.object_positions()[:, :2], prior.object_sizes()[:, :2]
        plates = door_plates(prior)
        if plates:
            span = np.array([p.door_width_m + 2 * PLATE_REACH_M for p in plates])
            xy = np.vstack([xy, [p.xy for p in plates]])
            size = np.vstack([size, np.abs([p.axis_xy for p in plates]) * span[:, None]])
        return cls(np.asarray(xy, np.float64).copy(), np.asarray(size, np.float64).copy())


def to_pose2(pose: np.ndarray) -> gtsam.Pose2:
    """(3,) x, y, yaw → gtsam.Pose2."""
    x, y, yaw = np.asarray(pose, np.float64)
    return gtsam.Pose2(float(x), float(y), float(yaw))


def from_pose2(pose: gtsam.Pose2) -> np.ndarray:
    """gtsam.Pose2 → (3,) x, y, yaw."""
    return np.array([pose.x(), pose.y(), pose.theta()])


def _rotation3(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def covariance_world_to_body(covariance: np.ndarray, yaw: float) -> np.ndarray:
    """(3, 3) world-frame (x, y, yaw) covariance → GTSAM's body-frame Pose2 tangent covariance at heading `yaw`."""
    R = _rotation3(yaw)
    return R.T @ np.asarray(covariance, np.float64) @ R


def covariance_body_to_world(covariance: np.ndarray, yaw: float) -> np.ndarray:
    """(3, 3) GTSAM body-frame Pose2 covariance → world-frame (x, y, yaw) covariance at heading `yaw`."""
    R = _rotation3(yaw)
    return R @ np.asarray(covariance, np.float64) @ R.T


# ------------------------------------------------------------------------------------------ noise models


def odometry_noise_covariance(increment: np.ndarray, cfg: BackendConfig, odometry: OdometryConfig) -> np.ndarray:
    """(3, 3) covariance of one (3,) robot-frame odometry increment: the odometry motion model's (α1..α4 =
    `odometry.alpha`, `bimfactor.odometry.odometry_covariance`) plus a diagonal floor (`cfg.odom_sigma_*`)."""
    floor = np.array([cfg.odom_sigma_trans_m, cfg.odom_sigma_trans_m, np.deg2rad(cfg.odom_sigma_rot_deg)]) ** 2
    return odometry_covariance(increment, odometry.alpha) + np.diag(floor)


def _robust(base: gtsam.noiseModel.Base, kernel: str, k: float) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian noise model in an M-estimator ('huber' or 'cauchy' of width `k` σ; 'none': as is)."""
    if kernel == "none":
        return base
    if kernel == "huber":
        estimator = gtsam.noiseModel.mEstimator.Huber.Create(k)
    else:
        estimator = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    return gtsam.noiseModel.Robust.Create(estimator, base)


def bearing_range_noise(cfg: BackendConfig) -> gtsam.noiseModel.Base:
    """(bearing, range) noise of an object observation, robust per `cfg.robust_kernel`."""
    sigmas = np.array([np.deg2rad(cfg.bearing_sigma_deg), cfg.range_sigma_m])
    return _robust(gtsam.noiseModel.Diagonal.Sigmas(sigmas), cfg.robust_kernel, cfg.robust_k)


# ------------------------------------------------------------------------------------------ factors


def pose_prior_factor(i: int, pose: np.ndarray, covariance_world: np.ndarray) -> gtsam.PriorFactorPose2:
    """Prior on X(i) at a (3,) pose with a (3, 3) world-frame covariance (rotated into GTSAM's body frame)."""
    body = covariance_world_to_body(covariance_world, float(pose[2]))
    return gtsam.PriorFactorPose2(X(i), to_pose2(pose), gtsam.noiseModel.Gaussian.Covariance(body))


def information_pose_factor(i: int, pose: np.ndarray, information_body: np.ndarray) -> gtsam.PriorFactorPose2:
    """Prior on X(i) with a (3, 3) information matrix in GTSAM's body frame (e.g. an ICP registration's Hessian)."""
    noise = gtsam.noiseModel.Gaussian.Information(np.asarray(information_body, np.float64))
    return gtsam.PriorFactorPose2(X(i), to_pose2(pose), noise)


def odometry_factor(
    i: int,
    increment: np.ndarray,
    cfg: BackendConfig,
    odometry: OdometryConfig,
    covariance: np.ndarray | None = None,
) -> gtsam.BetweenFactorPose2:
    """X(i−1) → X(i) by a (3,) robot-frame increment; noise from `odometry_noise_covariance` or a given (3, 3)
    covariance, robust per `cfg.odom_robust_kernel` (the covariance is the measured increment's, so a wheel slip is many
    σ off: a heavy-tailed kernel lets the landmark and scan factors overrule it)."""
    if covariance is None:
        covariance = odometry_noise_covariance(increment, cfg, odometry)
    gaussian = gtsam.noiseModel.Gaussian.Covariance(np.asarray(covariance, np.float64))
    noise = _robust(gaussian, cfg.odom_robust_kernel, cfg.odom_robust_k)
    return gtsam.BetweenFactorPose2(X(i - 1), X(i), to_pose2(increment), noise)


def landmark_prior_factor(object_id: int, landmarks: Landmarks, cfg: BackendConfig) -> gtsam.PriorFactorPoint2:
    """Holds L(j) at its footprint's centre; per axis σ² = `landmark_sigma_m`² (as-built deviates from the model)
    + size² / 12 (a perceived node is the centroid of the part seen, anywhere on the footprint: its variance as a
    uniform point of the box), so one end of a 3 m table holds L(j) 0.9 m along the table, not at the centre."""
    sigmas = np.sqrt(cfg.landmark_sigma_m**2 + landmarks.size[object_id] ** 2 / 12.0)
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    return gtsam.PriorFactorPoint2(L(object_id), landmarks.xy[object_id].copy(), noise)


def landmark_factors(
    i: int, observations: Observations, association: Association, noise: gtsam.noiseModel.Base
) -> list[gtsam.BearingRangeFactor2D]:
    """One BearingRangeFactor2D X(i) → L(j) per (measurement index, landmark id) pair."""
    ranges, bearings = observations.measurements()
    factors = []
    for k, object_id in association:
        bearing = gtsam.Rot2(float(bearings[k]))
        factors.append(gtsam.BearingRangeFactor2D(X(i), L(int(object_id)), bearing, float(ranges[k]), noise))
    return factors
