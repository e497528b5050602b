"""Statistics of a weighted particle set: effective sample size, circular means, pose moments and the like."""

from __future__ import annotations

import numpy as np

from bimfactor.types import wrap_angle


def effective_sample_size(weights: np.ndarray) -> float:
    """ESS = 1 / Σ w² of (M,) normalised weights."""
    w = np.asarray(weights, np.float64)
    return float(1.0 / np.dot(w, w))


def circular_mean(angles: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted circular mean of (N,) angles in [-π, π): atan2(Σ w sin θ, Σ w cos θ)."""
    angles = np.asarray(angles, np.float64)
    w = np.ones_like(angles) if weights is None else np.asarray(weights, np.float64)
    return float(wrap_angle(np.arctan2(np.dot(w, np.sin(angles)), np.dot(w, np.cos(angles)))))


def weighted_pose_stats(poses: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) weighted mean (circular in yaw) and (3, 3) covariance of (N, 3) poses; yaw residuals wrapped."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    mean = np.empty(3)
    mean[:2] = w @ poses[:, :2]
    mean[2] = circular_mean(poses[:, 2], w)
    return mean, _second_moment(poses, mean, w)


def weighted_geometric_median(
    points: np.ndarray, weights: np.ndarray, tol_m: float = 0.01, max_iterations: int = 50
) -> np.ndarray:
    """(2,) weighted geometric median of (N, 2) points: the position minimising Σ w ‖p − x‖, i.e. the expected
    Euclidean error under the weighted set (Weiszfeld's iteration from the weighted mean, until it moves < tol_m).

    Unlike the mean, it stays inside a cluster that holds most of the weight instead of being pulled towards
    distant minorities, and between clusters of similar weight it is no farther from the truth on average."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    w = np.asarray(weights, np.float64)
    x = w @ points / w.sum()
    for _ in range(max_iterations):
        inverse = w / np.maximum(np.hypot(*(points - x).T), 1e-6)
        moved = inverse @ points / inverse.sum()
        done = np.hypot(*(moved - x)) < tol_m
        x = moved
        if done:
            break
    return x


def local_mean_yaw(poses: np.ndarray, weights: np.ndarray, center_xy: np.ndarray, radius_m: float) -> float | None:
    """Weighted circular mean yaw of the (N, 3) poses within `radius_m` of `center_xy`; None when none holds weight.

    A position reported between or inside clusters takes the heading of the particles there, not the belief's
    global mean heading, which rival places facing elsewhere pull away."""
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    near = np.hypot(*(poses[:, :2] - np.asarray(center_xy, np.float64)).T) <= radius_m
    w = np.where(near, np.asarray(weights, np.float64), 0.0)
    return circular_mean(poses[:, 2], w) if w.sum() > 0 else None


def pose_window(poses: np.ndarray, centre: np.ndarray, radius_m: float, yaw_half_rad: float) -> np.ndarray:
    """(N,) bool: poses within the flat (position radius, wrapped yaw half-width) window around a (3,) centre."""
    near = np.hypot(poses[:, 0] - centre[0], poses[:, 1] - centre[1]) <= radius_m
    return near & (np.abs(wrap_angle(poses[:, 2] - centre[2])) <= yaw_half_rad)


def near_pose(
    poses: np.ndarray, storeys: np.ndarray, pose: np.ndarray, storey: int, radius_m: float, yaw_rad: float
) -> np.ndarray:
    """(M,) bool: which of the (M, 3) poses on their (M,) storeys lie in the `pose_window` of a (3,) pose on
    `storey`."""
    return (np.asarray(storeys) == storey) & pose_window(poses, pose, radius_m, yaw_rad)


def _second_moment(poses: np.ndarray, about: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(3, 3) Σ_k w_k δ_k δ_kᵀ of (K, 3) poses with (K,) normalised weights, δ_k = pose_k − about, yaw wrapped."""
    delta = np.asarray(poses, np.float64).reshape(-1, 3) - np.asarray(about, np.float64)
    delta[:, 2] = wrap_angle(delta[:, 2])
    return (delta * weights[:, None]).T @ delta


def mixture_pose_covariance(
    about: np.ndarray, means: np.ndarray, covariances: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """(3, 3) second moment about the (3,) pose `about` of a mixture of K Gaussians: (K, 3) means, (K, 3, 3)
    covariances, (K,) weights (normalised here); Σ_k w_k (Σ_k + δ_k δ_kᵀ) with δ_k = μ_k − about, yaw wrapped.

    The uncertainty of reporting one component's pose when the belief holds the others too (law of total
    covariance, taken about the reported pose instead of the mixture's mean)."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    within = np.einsum("k,kij->ij", w, np.asarray(covariances, np.float64).reshape(-1, 3, 3))
    return within + _second_moment(means, about, w)
