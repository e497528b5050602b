"""A synthetic loop world for the back end's tests and benchmark: poses on a circle, landmarks around it.

Odometry and range / bearing noise are drawn with the config's own σ, so a consistent estimator's covariance
should contain the truth at its nominal rate. True landmark positions deviate from the "BIM" ones by
N(0, landmark_sigma_m²) when `as_built` is set, as the landmark prior assumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimfactor.backend.factors import odometry_noise_covariance
from bimfactor.config import BackendConfig, OdometryConfig
from bimfactor.localization.measurements.semantic import polar_coordinates
from bimfactor.types import Observations, se2_between, wrap_angle

PRECISE_ODOMETRY_ALPHA = [0.0025, 0.0003, 0.0025, 0.0003]
"""`odometry.alpha` of IMU-aided odometry: σ about 5 % of each motion, 1° of yaw per metre (the default's, the
simulator's wheel odometry, is about 22 % and 9° per metre)."""
PRECISE_ODOMETRY = OdometryConfig(alpha=PRECISE_ODOMETRY_ALPHA)
"""That odometry as an `OdometryConfig`, for `loop_scenario` and the pose graphs."""


@dataclass
class LoopScenario:
    """(T, 3) true poses, (T−1, 3) noisy increments, per-step observations and their true associations."""

    true_poses: np.ndarray
    increments: np.ndarray
    observations: list[Observations]
    associations: list[list[tuple[int, int]]]
    landmark_xy: np.ndarray
    true_landmark_xy: np.ndarray


def loop_scenario(
    rng: np.random.Generator,
    cfg: BackendConfig | None = None,
    odometry: OdometryConfig | None = None,
    n_poses: int = 20,
    n_landmarks: int = 6,
    n_obs: int = 4,
    radius_m: float = 4.0,
    as_built: bool = False,
) -> LoopScenario:
    """A counter-clockwise circle of `n_poses` keyframes; each sees its `n_obs` nearest landmarks (360° view).

    The odometry noise is drawn from `odometry_noise_covariance` with `cfg` and `odometry` (None: the default
    config's)."""
    if cfg is None or odometry is None:
        from bimfactor.config import load_config

        default = load_config()
        cfg = default.backend if cfg is None else cfg
        odometry = default.odometry if odometry is None else odometry
    angles = np.linspace(0.0, 2 * np.pi, n_poses, endpoint=False)
    true_poses = np.stack(
        [radius_m * np.cos(angles), radius_m * np.sin(angles), wrap_angle(angles + np.pi / 2)], axis=1
    )
    lm_angles = np.linspace(0.0, 2 * np.pi, n_landmarks, endpoint=False) + np.pi / n_landmarks
    lm_radius = np.where(np.arange(n_landmarks) % 2 == 0, radius_m + 2.0, radius_m - 2.0)
    landmark_xy = np.stack([lm_radius * np.cos(lm_angles), lm_radius * np.sin(lm_angles)], axis=1)
    true_landmark_xy = landmark_xy.copy()
    if as_built:
        true_landmark_xy += cfg.landmark_sigma_m * rng.standard_normal(landmark_xy.shape)
    increments = []
    for t in range(1, n_poses):
        true_inc = se2_between(true_poses[t - 1], true_poses[t])
        covariance = odometry_noise_covariance(true_inc, cfg, odometry)
        noisy = true_inc + np.linalg.cholesky(covariance) @ rng.standard_normal(3)
        noisy[2] = wrap_angle(noisy[2])
        increments.append(noisy)
    observations, associations = [], []
    sigma_b, sigma_r = np.deg2rad(cfg.bearing_sigma_deg), cfg.range_sigma_m
    dim = 8
    for t in range(n_poses):
        d, alpha = polar_coordinates(true_poses[t], true_landmark_xy)
        seen = np.argsort(d)[:n_obs]
        embeddings = np.zeros((len(seen), dim), np.float32)
        embeddings[np.arange(len(seen)), seen % dim] = 1.0
        observations.append(
            Observations(
                embeddings,
                d[seen] + sigma_r * rng.standard_normal(len(seen)),
                wrap_angle(alpha[seen] + sigma_b * rng.standard_normal(len(seen))),
                labels=[f"object {j}" for j in seen],
            )
        )
        associations.append([(k, int(j)) for k, j in enumerate(seen)])
    return LoopScenario(true_poses, np.array(increments), observations, associations, landmark_xy, true_landmark_xy)


def nearest_landmark_associator(landmark_xy: np.ndarray, observations: Observations, gate_m: float = 1.0):
    """An `AssociateFn` for the synthetic worlds: each observation → the landmark nearest to where the pose puts it,
    within `gate_m`."""

    def associate(pose: np.ndarray, storey: int) -> list[tuple[int, int]]:
        angle = pose[2] + np.asarray(observations.bearing_rad)
        xy = pose[:2] + np.asarray(observations.range_m)[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        gaps = np.linalg.norm(xy[:, None, :] - np.asarray(landmark_xy)[None, :, :2], axis=2)
        return [(k, int(np.argmin(g))) for k, g in enumerate(gaps) if g.min() < gate_m]

    return associate
