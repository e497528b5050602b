"""The S-MCL kinematic motion model (paper Sec. II.C): apply the odometry increment, add Gaussian noise.

x_t = x_{t-1} ⊕ u_t + [ε_trans, ε_rot] with ε_trans ~ N(0, σ_trans² I) (metres, world frame: the noise is
isotropic, so the frame does not matter) and ε_rot ~ N(0, σ_rot²) (radians), drawn independently per particle
and per step, as the paper does; the noise does not scale with the length of the increment. A step is therefore a
keyframe (`bimfactor.odometry`, which also holds the increments and the odometry noise model the simulator and the
back end share with the localizer).
"""

from __future__ import annotations

import numpy as np

from bimfactor.types import se2_compose, wrap_angle

_MIN_TURN_RATE = 1e-9  # rad/s: below this a velocity command is a straight line


def velocity_increment(v_mps: float, omega_rps: float, dt_s: float) -> np.ndarray:
    """(3,) robot-frame increment of driving at constant (v, ω) for dt: an exact circular arc."""
    dyaw = omega_rps * dt_s
    if abs(omega_rps) < _MIN_TURN_RATE:
        return np.array([v_mps * dt_s, 0.0, 0.0])
    radius = v_mps / omega_rps
    return np.array([radius * np.sin(dyaw), radius * (1.0 - np.cos(dyaw)), float(wrap_angle(dyaw))])


def propagate(
    particles: np.ndarray,
    increment: np.ndarray,
    sigma_trans_m: float,
    sigma_rot_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(M, 3) particles moved by a (3,) robot-frame increment, plus Gaussian noise; returns a new array."""
    particles = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    moved = se2_compose(particles, np.broadcast_to(np.asarray(increment, np.float64), particles.shape))
    noise = rng.standard_normal((len(particles), 3))
    moved[:, :2] += sigma_trans_m * noise[:, :2]
    moved[:, 2] = wrap_angle(moved[:, 2] + sigma_rot_rad * noise[:, 2])
    return moved


def propagate_velocity(
    particles: np.ndarray,
    v_mps: float,
    omega_rps: float,
    dt_s: float,
    sigma_trans_m: float,
    sigma_rot_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(M, 3) particles moved by the control u = (v, ω) over dt (the paper's form of the motion model)."""
    return propagate(particles, velocity_increment(v_mps, omega_rps, dt_s), sigma_trans_m, sigma_rot_rad, rng)
