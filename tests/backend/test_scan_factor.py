"""Correlative scan matching against the likelihood field of the BIM's faces (backend.scan_factor)."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.backend.scan_factor import CorrelativeMatcher
from bimfactor.bim.field import LikelihoodField, face_distances
from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config, ScanFactorConfig
from bimfactor.types import wrap_angle
from tests.localization.handmade import make_prior


@pytest.fixture(scope="module")
def box() -> BimPrior:
    """Two rooms split by a 0.2 m wall at x ∈ [6.0, 6.2]; the box is x ∈ [0, 12], y ∈ [0, 6] with 0.2 m walls."""
    return make_prior(with_door=False)


@pytest.fixture(scope="module")
def cfg(test_config: Config) -> ScanFactorConfig:
    return test_config.backend.scan_factor


def cast_scan(prior: BimPrior, pose: np.ndarray, fov_deg: float = 90.0, beam_deg: float = 2.0) -> np.ndarray:
    """(N, 2) base-frame endpoints of rays marched through the grid's walls from a pose (2 mm steps)."""
    grid, walls = prior.grid, prior.storeys[0].structure
    points = []
    for bearing in np.deg2rad(np.arange(-fov_deg / 2, fov_deg / 2 + 1e-9, beam_deg)):
        direction = np.array([np.cos(pose[2] + bearing), np.sin(pose[2] + bearing)])
        for r in np.arange(0.3, 8.0, 0.002):
            row, col = grid.world_to_cell(pose[:2] + r * direction)[0]
            if walls[row, col]:
                points.append([r * np.cos(bearing), r * np.sin(bearing)])
                break
    return np.array(points)


def pose_error(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(found[:2] - truth[:2]))), float(np.rad2deg(abs(wrap_angle(found[2] - truth[2]))))


def test_a_corner_is_matched_from_an_offset_start_to_centimetres_with_an_honest_covariance(box, cfg):
    truth = np.array([4.0, 4.0, np.deg2rad(30.0)])  # sees the divider and the north wall: a corner
    scan = cast_scan(box, truth)
    start = truth + np.array([0.3, -0.25, np.deg2rad(6.0)])
    match = CorrelativeMatcher(box, cfg).match(start, 0, scan)
    assert match.accepted, match.reason
    dxy, dyaw = pose_error(match.pose, truth)
    assert dxy < 0.04 and dyaw < 0.5
    delta = match.pose - truth
    delta[2] = wrap_angle(delta[2])
    assert delta @ np.linalg.solve(match.covariance, delta) < 11.34  # χ²(3) at 99 %
    assert np.sqrt(np.linalg.eigvalsh(match.covariance[:2, :2])).max() < 0.1
    assert match.inliers >= len(scan) - 2


def test_a_single_wall_gives_a_long_covariance_along_it(box, cfg):
    truth = np.array([4.0, 3.0, 0.0])  # faces the divider (x = 6) square on: y is unconstrained
    scan = cast_scan(box, truth, fov_deg=30.0)
    match = CorrelativeMatcher(box, cfg).match(truth + np.array([0.1, 0.2, 0.0]), 0, scan)
    assert match.accepted, match.reason
    sx, sy = np.sqrt(np.diag(match.covariance)[:2])
    assert abs(match.pose[0] - truth[0]) < 0.04
    assert sy > 3 * sx and sy > 0.2  # the whole window's spread along the wall


def test_a_scan_is_not_matched_through_a_wall(box, cfg):
    """From room A the divider's west face is seen; a start 0.25 m east puts the scan on its east face, 0.2 m further,
    where the rays would have crossed the wall: the match returns to the west face."""
    truth = np.array([3.0, 3.0, 0.0])
    scan = cast_scan(box, truth, fov_deg=40.0)
    match = CorrelativeMatcher(box, cfg).match(truth + np.array([0.25, 0.0, 0.0]), 0, scan)
    assert match.accepted, match.reason
    assert abs(match.pose[0] - truth[0]) < 0.04
    seen_through = LikelihoodField(box, cfg.sigma_m, face_distances(box))
    east_face = truth + np.array([0.2 + 0.05, 0.0, 0.0])
    assert seen_through.values(east_face[None], 0, scan).mean() > 0.75 * 255  # without the ray check, about as good
    assert seen_through.values(east_face[None], 0, scan, cfg.clear_before_m).mean() < 50


def test_a_scan_counts_at_most_the_effective_endpoints(box, cfg):
    """Up to `effective_endpoints` endpoints each count once; more share that many: a 40-endpoint scan weighs
    what 20 of its endpoints would, and a 5-endpoint scan is not weighed as if it were 20."""
    matcher = CorrelativeMatcher(box, cfg)
    n_eff = int(cfg.effective_endpoints)
    rng = np.random.default_rng(3)
    values = rng.integers(0, 256, size=(4, 2 * n_eff), dtype=np.uint8)
    plain = np.log(values.astype(np.float32) / np.float32(255.0) + np.float32(cfg.outlier)).sum(axis=1)
    few, _ = matcher.log_likelihood(values[:, :5])
    np.testing.assert_allclose(few, np.log(values[:, :5] / 255.0 + cfg.outlier).sum(axis=1), rtol=1e-5)
    many, on_wall = matcher.log_likelihood(values)
    np.testing.assert_allclose(many, plain / 2.0, rtol=1e-5)
    np.testing.assert_array_equal(on_wall, (values >= 128).sum(axis=1))


def test_matches_are_rejected_with_the_reason(box, cfg):
    matcher = CorrelativeMatcher(box, cfg)
    truth = np.array([4.0, 4.0, np.deg2rad(30.0)])
    scan = cast_scan(box, truth)
    few = matcher.match(truth, 0, scan[:5])
    assert not few.accepted and "5 endpoints" in few.reason
    nothing = matcher.match(truth, 0, scan + np.array([0.0, 30.0]))  # 30 m off to the side: off the grid
    assert not nothing.accepted and "on the BIM" in nothing.reason
    wall = np.array([4.0, 3.0, 0.0])  # the divider square on, from 1 m further back: the optimum is outside ± 0.5 m
    far = matcher.match(wall - np.array([1.0, 0.0, 0.0]), 0, cast_scan(box, wall, fov_deg=30.0), recentre=0)
    assert not far.accepted and "edge" in far.reason  # not searched again about the edge
    np.testing.assert_array_equal(far.pose, wall - np.array([1.0, 0.0, 0.0]))


def test_an_optimum_beyond_the_window_is_found_by_searching_again_about_the_edge(box, cfg):
    """The corner seen from 1.1 m and 30° off the start: each search of the ± 0.5 m / ± 18° window ends on its
    edge, and the matcher searches again about that edge pose, `recentre` times at most (`scan_recentre`)."""
    assert cfg.window_m < 1.1 and cfg.window_deg < 30.0
    truth = np.array([4.0, 4.0, np.deg2rad(30.0)])
    scan = cast_scan(box, truth)
    start = truth + np.array([-0.8, -0.75, np.deg2rad(-30.0)])
    once = CorrelativeMatcher(box, cfg.model_copy(update={"recentre": 0}))
    assert once.match(start, 0, scan).reason == "optimum on the window edge"
    again = CorrelativeMatcher(box, cfg.model_copy(update={"recentre": 2}))
    assert again.match(start, 0, scan, recentre=0).reason == "optimum on the window edge"
    match = again.match(start, 0, scan)
    assert match.accepted, match.reason
    dxy, dyaw = pose_error(match.pose, truth)
    assert dxy < 0.04 and dyaw < 0.5


def test_the_factor_function_returns_body_frame_information_of_accepted_matches(box, cfg):
    matcher = CorrelativeMatcher(box, cfg)
    truth = np.array([4.0, 4.0, np.deg2rad(30.0)])
    measure = matcher.factor_fn(cast_scan(box, truth))
    pose, information = measure(truth + np.array([0.1, 0.1, 0.02]), 0)
    match = matcher.match(truth + np.array([0.1, 0.1, 0.02]), 0, cast_scan(box, truth))
    np.testing.assert_allclose(pose, match.pose)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # body → world
    np.testing.assert_allclose(np.linalg.inv(information), R.T @ match.covariance @ R, atol=1e-12)
    assert matcher.factor_fn(cast_scan(box, truth)[:5])(truth, 0) is None


def test_the_factor_function_matches_each_start_pose_once(box, cfg, monkeypatch):
    matcher = CorrelativeMatcher(box, cfg)
    truth = np.array([4.0, 4.0, np.deg2rad(30.0)])
    calls = []
    match = matcher.match
    monkeypatch.setattr(matcher, "match", lambda *args: calls.append(args) or match(*args))
    measure = matcher.factor_fn(cast_scan(box, truth))
    start = truth + np.array([0.1, 0.1, 0.02])
    pose, information = measure(start, 0)
    pose[:] = 0.0  # what a caller does with the result does not reach the next one
    again, information_again = measure(start.copy(), 0)
    assert len(calls) == 1
    np.testing.assert_allclose(again[:2], truth[:2], atol=0.05)
    np.testing.assert_array_equal(information_again, information)
    measure(start + np.array([1e-6, 0.0, 0.0]), 0)  # another start pose is matched anew
    assert len(calls) == 2
