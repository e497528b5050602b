"""Statistics of weighted particle sets: circular means, pose moments, the geometric median, the ESS."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.localization.stats import (
    circular_mean,
    effective_sample_size,
    local_mean_yaw,
    mixture_pose_covariance,
    near_pose,
    weighted_geometric_median,
    weighted_pose_stats,
)
from bimfactor.types import wrap_angle


def test_circular_mean_across_pi():
    mean = circular_mean(np.deg2rad([179.0, -179.0]))
    assert abs(wrap_angle(mean - np.pi)) < 1e-9  # 180°, not 0°
    assert circular_mean(np.deg2rad([10.0, 30.0]), np.array([3.0, 1.0])) == pytest.approx(
        np.arctan2(
            3 * np.sin(np.deg2rad(10)) + np.sin(np.deg2rad(30)), 3 * np.cos(np.deg2rad(10)) + np.cos(np.deg2rad(30))
        )
    )


def test_pose_covariance_wraps_yaw_residuals():
    poses = np.array([[1.0, 2.0, np.deg2rad(179.0)], [3.0, 2.0, np.deg2rad(-179.0)]])
    mean, cov = weighted_pose_stats(poses, np.array([0.5, 0.5]))
    np.testing.assert_allclose(mean[:2], [2.0, 2.0])
    assert abs(wrap_angle(mean[2] - np.pi)) < 1e-9
    assert cov[0, 0] == pytest.approx(1.0) and cov[1, 1] == pytest.approx(0.0)
    assert np.sqrt(cov[2, 2]) == pytest.approx(np.deg2rad(1.0), rel=1e-6)


def test_mixture_covariance_about_a_component_adds_the_rivals_offsets_with_wrapped_yaw():
    about = np.array([0.0, 0.0, np.deg2rad(179.0)])
    means = np.array([about, [10.0, 0.0, np.deg2rad(-179.0)]])
    covariances = np.array([np.diag([0.01, 0.04, 0.001]), np.diag([0.09, 0.16, 0.002])])
    cov = mixture_pose_covariance(about, means, covariances, np.array([3.0, 1.0]))  # weights normalised: ¾, ¼
    assert cov[0, 0] == pytest.approx(0.75 * 0.01 + 0.25 * (0.09 + 100.0))
    assert cov[1, 1] == pytest.approx(0.75 * 0.04 + 0.25 * 0.16)
    assert cov[2, 2] == pytest.approx(0.75 * 0.001 + 0.25 * (0.002 + np.deg2rad(2.0) ** 2))  # 2°, not 358°
    assert cov[0, 2] == pytest.approx(0.25 * 10.0 * np.deg2rad(2.0))
    # One component: its own covariance.
    np.testing.assert_allclose(mixture_pose_covariance(about, means[:1], covariances[:1], np.ones(1)), covariances[0])


def test_geometric_median_minimises_the_weighted_distance_sum():
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.normal([0.0, 0.0], 0.3, (40, 2)), rng.normal([10.0, 4.0], 0.3, (25, 2))])
    weights = rng.random(len(points))
    median = weighted_geometric_median(points, weights, tol_m=1e-6, max_iterations=500)

    def cost(x: np.ndarray) -> float:
        return float(weights @ np.hypot(*(points - x).T))

    grid = np.stack(np.meshgrid(np.linspace(-1, 11, 121), np.linspace(-1, 5, 61)), axis=-1).reshape(-1, 2)
    assert cost(median) <= min(cost(x) for x in grid) + 1e-6
    mean = weights @ points / weights.sum()
    assert cost(median) < cost(mean)
    # A point holding more than half the weight is the median: the minority cannot pull it away.
    heavy = np.array([[0.0, 0.0], [30.0, 0.0], [0.0, 30.0]])
    np.testing.assert_allclose(weighted_geometric_median(heavy, np.array([0.6, 0.2, 0.2])), [0.0, 0.0], atol=0.01)


def test_local_mean_yaw_takes_the_heading_of_the_particles_near_the_point():
    # 60 % of the weight at the origin facing ±π (across the seam), 40 % 10 m away facing +y.
    poses = np.array([[0.0, 0.0, np.deg2rad(178.0)], [0.3, 0.0, np.deg2rad(-176.0)], [10.0, 0.0, np.pi / 2]])
    weights = np.array([0.3, 0.3, 0.4])
    local = local_mean_yaw(poses, weights, np.array([0.1, 0.0]), radius_m=2.0)
    assert local is not None and abs(wrap_angle(local - np.deg2rad(-179.0))) < 1e-9
    # The global circular mean is pulled far off by the rival place: the reason for a local heading.
    assert abs(wrap_angle(circular_mean(poses[:, 2], weights) - local)) > np.deg2rad(30.0)
    assert local_mean_yaw(poses, weights, np.array([5.0, 5.0]), radius_m=2.0) is None  # nothing near
    assert local_mean_yaw(poses, np.array([0.0, 0.0, 1.0]), np.array([0.1, 0.0]), radius_m=2.0) is None  # no weight


def test_near_pose_takes_radius_heading_across_the_seam_and_storey():
    pose = np.array([1.0, 2.0, np.deg2rad(175.0)])
    poses = np.array(
        [
            [1.5, 2.0, np.deg2rad(-170.0)],  # 0.5 m off, 15° across ±π: near
            [1.0, 3.9, np.deg2rad(175.0)],  # 1.9 m off: near
            [1.0, 4.1, np.deg2rad(175.0)],  # 2.1 m off: too far
            [1.0, 2.0, np.deg2rad(120.0)],  # 55° off: turned away
            [1.0, 2.0, np.deg2rad(175.0)],  # the same pose on another storey
        ]
    )
    storeys = np.array([0, 0, 0, 0, 1])
    near = near_pose(poses, storeys, pose, 0, radius_m=2.0, yaw_rad=np.deg2rad(45.0))
    assert near.tolist() == [True, True, False, False, False]
    assert near_pose(poses, storeys, pose, 1, radius_m=2.0, yaw_rad=np.deg2rad(45.0)).tolist() == [0, 0, 0, 0, 1]


def test_effective_sample_size():
    assert effective_sample_size(np.full(100, 0.01)) == pytest.approx(100.0)
    assert effective_sample_size(np.array([1.0, 0.0, 0.0])) == pytest.approx(1.0)
    assert effective_sample_size(np.array([0.5, 0.5, 0.0, 0.0])) == pytest.approx(2.0)
