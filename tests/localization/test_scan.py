"""The scan term: depth → nearest return per bearing bin, scored against the prior's likelihood field."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config, SmclConfig, updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.measurements.scan import DepthPoints, ScanLikelihood, scan_endpoints
from bimfactor.localization.recovery import LostMonitor
from bimfactor.localization.recovery.augmented import AugmentedMCL
from bimfactor.sim.sensors import camera_mount
from bimfactor.types import CameraIntrinsics

W, H = 64, 48


def _camera(cfg: Config) -> tuple[CameraIntrinsics, np.ndarray]:
    return CameraIntrinsics.from_hfov(W, H, cfg.sim.camera.hfov_deg), camera_mount(cfg.sim.camera)


def _endpoints(depth: np.ndarray, cfg: Config) -> np.ndarray:
    """The scan of a depth image from the test camera, up to the top of the grid's obstacle band."""
    intrinsics, T_base_camera = _camera(cfg)
    points = DepthPoints.of(depth, intrinsics, T_base_camera)
    return scan_endpoints(points, cfg.scan, cfg.sensor, cfg.bim.grid.band_max_m)


def test_endpoints_are_the_nearest_surface_per_bearing_bin(test_config: Config) -> None:
    forward = test_config.sim.camera.mount_forward_m
    depth = np.full((H, W), 3.0, np.float32)  # a wall 3 m ahead of the (level) camera
    wall = _endpoints(depth, test_config)
    np.testing.assert_allclose(wall[:, 0], forward + 3.0, atol=1e-9)
    bins = np.floor(np.arctan2(wall[:, 1], wall[:, 0]) / np.deg2rad(test_config.scan.beam_deg))
    assert len(np.unique(bins)) == len(wall)  # one endpoint per bin
    assert 40 <= len(wall) <= 46  # the 90° view in 2° bins (the bearings from the base origin span a bit less)
    # Rows at the camera's height hold a nearer surface: every bin's endpoint moves onto it.
    depth[20:28] = 2.0
    near = _endpoints(depth, test_config)
    np.testing.assert_allclose(near[:, 0], forward + 2.0, atol=1e-9)
    # A nearer surface above the band (the top two rows at 1 m lie 1.20-1.23 m high) is not part of the scan.
    depth[:] = 3.0
    depth[:2] = 1.0
    np.testing.assert_allclose(_endpoints(depth, test_config), wall)


def test_an_endpoint_is_the_median_of_its_nearest_surface_not_its_nearest_noisy_return(test_config: Config) -> None:
    """A wall 5 m ahead seen with the camera's depth noise (σ ≈ 4 cm there): the nearest of a bin's hundreds of
    returns is ~3σ short, the median of the returns within 6σ of it is on the wall; a far wall behind does not
    count."""
    sigma = float(test_config.sensor.depth_noise.sigma_m(5.0))
    surface_m = min(test_config.scan.surface_sigmas * sigma, test_config.scan.surface_m)
    rng = np.random.default_rng(0)
    depth = (5.0 + sigma * rng.standard_normal((H, W))).astype(np.float32)
    depth[:, ::7] = 9.0  # columns of a far wall seen through gaps: beyond the nearest surface
    scan = _endpoints(depth, test_config)
    ranges = scan[:, 0] - test_config.sim.camera.mount_forward_m
    assert abs(np.mean(ranges) - 5.0) < 0.015  # unbiased (the nearest returns: 5 m − ~2.5σ)
    assert np.all(np.abs(ranges - 5.0) < 0.2)  # each a sample of the noise, none on the far wall
    assert surface_m >= 6 * sigma  # the surface holds the whole ±3σ spread of the noise
    nearest = np.delete(depth, np.s_[::7], axis=1).min(axis=0).mean()  # per column, fewer returns than a bin
    assert nearest < 5.0 - 1.5 * sigma


def test_a_low_table_seen_from_above_ends_the_scan_at_its_edge(test_config: Config, fixed_value) -> None:
    """A thin table top 0.1 m below the camera, from 1.0 to 1.8 m ahead, a wall at 3 m: the top's returns lie behind
    its edge, so the nearest surface is only as deep as the noise there (2 cm), not the 0.3 m of a far wall's."""
    cfg = test_config
    mount = cfg.sim.camera.mount_height_m
    w, h = 640, 480  # fine rows: the top spans 14 of them
    intrinsics = CameraIntrinsics.from_hfov(w, h, cfg.sim.camera.hfov_deg)
    rows = np.arange(h, dtype=np.float64)[:, None] - intrinsics.cy
    with np.errstate(divide="ignore"):
        on_top = np.where(rows > 0, (mount - 0.4) * intrinsics.fy / rows, np.inf)  # depth where a row meets z = 0.4
    depth = np.where((on_top >= 1.0) & (on_top <= 1.8), on_top, 3.0) * np.ones((1, w))

    def ahead(c: Config) -> np.ndarray:
        scan = scan_endpoints(
            DepthPoints.of(depth.astype(np.float32), intrinsics, camera_mount(c.sim.camera)), c.scan, c.sensor, 1.2
        )
        return scan[np.abs(scan[:, 1]) < 0.3, 0] - c.sim.camera.mount_forward_m  # the bins straight ahead

    assert len(ahead(cfg)) >= 3
    assert np.all(ahead(cfg) < 1.03)  # on the table's edge
    fixed_value("scan.surface_min_m", 0.3)
    assert np.all(ahead(cfg) > 1.1)  # a fixed 0.3 m surface: the median return lies on the top, inside the table


def test_no_return_gives_an_empty_scan(test_config: Config) -> None:
    empty = _endpoints(np.full((H, W), np.nan, np.float32), test_config)
    assert empty.shape == (0, 2)


def _divider_scan() -> np.ndarray:
    """What a robot at (3, 3) facing +x sees of the box prior's dividing wall (face at x = 6): base-frame points."""
    return np.column_stack([np.full(11, 3.0), np.linspace(-1.0, 1.0, 11)])


def test_scan_score_peaks_at_the_pose_that_put_the_walls_where_they_are(box_prior: BimPrior, smcl_cfg: SmclConfig):
    field = ScanLikelihood(box_prior, smcl_cfg.scan)
    poses = np.array(
        [
            [3.0, 3.0, 0.0],  # truth: every endpoint on the divider's face
            [3.5, 3.0, 0.0],  # 0.5 m east: endpoints past the 0.2 m wall, in room B
            [3.0, 3.0, np.deg2rad(30.0)],  # turned: endpoints in room A's free space
            [40.0, 3.0, 0.0],  # off the grid
        ]
    )
    scores = field.scores(poses, np.zeros(4, np.int64), _divider_scan())
    assert scores[0] > 0.95
    sigma = smcl_cfg.scan.sigma_m
    # Endpoints at x = 6.5 fall in the cell centred at 6.525; the wall's last cell is centred at 6.175.
    assert scores[1] == pytest.approx(np.exp(-0.5 * (0.35 / sigma) ** 2), abs=0.5 / 255)  # the field in 1/255 steps
    assert scores[2] < 0.5 * scores[0]
    assert scores[3] == 0.0
    np.testing.assert_array_equal(field.scores(poses, np.zeros(4, np.int64), np.zeros((0, 2))), np.zeros(4))
    np.testing.assert_allclose(
        field.log_likelihood(poses, np.zeros(4, np.int64), _divider_scan()), scores / smcl_cfg.scan.temperature
    )


def test_field_lookups_are_those_of_each_endpoint_placed_one_at_a_time(smcl_cfg: SmclConfig):
    """The batched lookup (one matrix product for all poses) against placing every endpoint by hand, on two storeys
    and with endpoints off the grid on every side (they score 0)."""
    from bimfactor.bim.field import LikelihoodField
    from tests.localization.handmade import make_prior

    prior = make_prior(n_storeys=2)
    field = LikelihoodField(prior, smcl_cfg.scan.sigma_m)
    grid = prior.grid
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(-2.0, 14.0, 40), rng.uniform(-2.0, 9.0, 40), rng.uniform(-np.pi, np.pi, 40)])
    storeys = rng.integers(0, 2, 40)
    endpoints = rng.uniform(-8.0, 8.0, (25, 2))
    values = field.values(poses, storeys, endpoints)
    expected = np.zeros_like(values)
    distance = np.stack([layers.clearance_m for layers in prior.storeys])
    for m, ((x, y, yaw), storey) in enumerate(zip(poses, storeys, strict=True)):
        for n, (px, py) in enumerate(endpoints):
            wx, wy = x + np.cos(yaw) * px - np.sin(yaw) * py, y + np.sin(yaw) * px + np.cos(yaw) * py
            col, row = (
                int(np.floor((wx - grid.origin_x) / grid.resolution_m)),
                int(np.floor((wy - grid.origin_y) / grid.resolution_m)),
            )
            if 0 <= row < grid.rows and 0 <= col < grid.cols:
                expected[m, n] = np.rint(
                    255.0 * np.exp(-0.5 * (distance[storey, row, col] / smcl_cfg.scan.sigma_m) ** 2)
                )
    assert (expected == 0).any() and (expected > 0).any()
    np.testing.assert_array_equal(values, expected)


def _two_particles(prior: BimPrior, visibility: VisibilityTable, cfg: SmclConfig) -> SemanticMCL:
    mcl = SemanticMCL(prior, visibility, cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[3.0, 3.0, 0.0], [3.5, 3.0, 0.0]])
    mcl.storeys = np.zeros(2, np.int64)
    return mcl


def _augmented(mcl: SemanticMCL) -> AugmentedMCL:
    return next(r for r in mcl.recoveries.injections if isinstance(r, AugmentedMCL))


def test_the_filter_weighs_by_the_scan_only_when_enabled(
    box_prior: BimPrior, box_visibility: VisibilityTable, smcl_cfg: SmclConfig
):
    cfg = updated(smcl_cfg, {"scan.enabled": True, "augmented.enabled": True})
    mcl = _two_particles(box_prior, box_visibility, cfg)
    mcl.update(FrameData(scan=_divider_scan()))
    expected = ScanLikelihood(box_prior, cfg.scan).log_likelihood(mcl.particles, mcl.storeys, _divider_scan())
    assert np.log(mcl.weights[0] / mcl.weights[1]) == pytest.approx(expected[0] - expected[1])
    augmented = _augmented(mcl)
    assert augmented.w_slow is None and augmented.w_fast is None  # augmented MCL watches the semantic term only
    off = _two_particles(box_prior, box_visibility, updated(cfg, {"scan.enabled": False}))
    off.update(FrameData(scan=_divider_scan()))
    np.testing.assert_array_equal(off.weights, [0.5, 0.5])


def test_injected_particles_stay_out_of_the_estimate_until_weighed(
    box_prior: BimPrior, box_visibility: VisibilityTable, smcl_cfg: SmclConfig
):
    cfg = updated(smcl_cfg, {"augmented.enabled": True, "augmented.injection": "uniform"})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(3), num_particles=200)
    mcl.initialize()
    mcl.particles[:] = [3.0, 3.0, 0.5]
    augmented = _augmented(mcl)
    augmented.w_slow, augmented.w_fast = 1.0, 0.5  # inject about half of the particles
    resampled, injected = mcl.resample(FrameData())
    assert resampled and 50 < injected < 150 and mcl.fresh.sum() == injected
    assert np.abs(mcl.particles[mcl.fresh] - [3.0, 3.0, 0.5]).max() > 1.0  # spread over the box
    np.testing.assert_allclose(mcl.estimate().pose, [3.0, 3.0, 0.5], atol=1e-9)
    # One source for every estimate (the filter's, the modes, the belief median): the injected weigh nothing.
    weights = mcl.estimation_weights()
    assert np.all(weights[mcl.fresh] == 0) and np.array_equal(weights[~mcl.fresh], mcl.weights[~mcl.fresh])
    mcl.update(FrameData(scan=_divider_scan()))  # a measurement weighs them: they count again
    assert not mcl.fresh.any() and np.array_equal(mcl.estimation_weights(), mcl.weights)
    assert np.abs(mcl.estimate().pose - [3.0, 3.0, 0.5]).max() > 1e-6


def test_drawn_poses_are_screened_by_the_frame_scan(
    box_prior: BimPrior, box_visibility: VisibilityTable, smcl_cfg: SmclConfig
):
    """Of 200 drawn poses that put the divider where the scan has it and 200 turned by 30°, the 100 kept are nearly
    all of the first kind; with no scan the first 100 come back as drawn."""
    cfg = updated(smcl_cfg, {"scan.enabled": True})
    sampler = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(5), num_particles=10).sampler
    drawn = np.repeat([[3.0, 3.0, 0.0], [3.0, 3.0, np.deg2rad(30.0)]], 200, axis=0)
    storeys = np.zeros(len(drawn), np.int64)
    kept, kept_storeys = sampler.screen_by_scan(100, drawn, storeys, FrameData(scan=_divider_scan()))
    assert len(kept) == len(kept_storeys) == 100
    assert np.sum(kept[:, 2] == 0.0) >= 85
    assert len(np.unique(kept, axis=0)) == 2  # chosen among the drawn, not moved
    as_drawn, _ = sampler.screen_by_scan(100, drawn, storeys, FrameData())
    np.testing.assert_array_equal(as_drawn, drawn[:100])
    cfg_off = updated(smcl_cfg, {"scan.enabled": False})
    off = SemanticMCL(box_prior, box_visibility, cfg_off, np.random.default_rng(5), num_particles=10).sampler
    np.testing.assert_array_equal(
        off.screen_by_scan(100, drawn, storeys, FrameData(scan=_divider_scan()))[0], drawn[:100]
    )


# ------------------------------------------------------------------------------------------ the kidnapped robot


def _lost_cfg(smcl_cfg: SmclConfig, relocalize: bool = True) -> SmclConfig:
    return updated(
        smcl_cfg,
        {
            "scan.enabled": True,
            "augmented.enabled": False,
            "relocalize.enabled": relocalize,
            "motion.sigma_trans_m": 0.0,
            "motion.sigma_rot_deg": 0.0,
        },
    )


def _tracking_monitor(smcl_cfg: SmclConfig):
    """A monitor armed by ten frames that fit 0.6."""
    monitor = LostMonitor(_lost_cfg(smcl_cfg).relocalize)
    assert not any(monitor.lost(0.6, 40) for _ in range(10))
    assert monitor.frames == 10 and monitor.average == pytest.approx(0.6)
    return monitor


def test_the_lost_monitor_calls_a_sudden_or_a_held_drop_of_the_scan_fit_below_its_average(smcl_cfg: SmclConfig):
    unarmed = LostMonitor(_lost_cfg(smcl_cfg).relocalize)
    assert not any(unarmed.lost(0.6, 40) for _ in range(9))
    assert not unarmed.lost(0.01, 40) and unarmed.cusum == 0.0  # fewer than 1 / α = 10 frames: not armed ...
    assert unarmed.frames == 10 and unarmed.average == pytest.approx(0.541)  # ... so the frame entered the average
    monitor = _tracking_monitor(smcl_cfg)
    assert not monitor.lost(0.001, 40)  # a passer-by filling the view: one frame never says lost
    assert monitor.streak == 1 and monitor.cusum == pytest.approx(1.0 - 0.4)  # S takes at most h − drift a frame
    assert monitor.average == pytest.approx(0.6)  # the poor frame stayed out of the average
    assert not monitor.lost(0.05, 3)  # too few endpoints: counts for nothing
    assert monitor.lost(0.2, 40) == 3  # the second frame in a row under half the average, lost for three frames
    assert monitor.average is None and monitor.frames == 0 and monitor.streak == 0 and monitor.cusum == 0.0
    sudden = _tracking_monitor(smcl_cfg)
    assert [sudden.lost(0.29, 40), sudden.lost(0.29, 40)] == [0, 2]  # S = 2 (ln(0.6 / 0.29) − 0.4) < 1
    held = _tracking_monitor(smcl_cfg)
    fits = [0.3] * 5  # at half the average, not under it: S grows by ln(2) − 0.4 = 0.29 a frame
    assert [held.lost(fit, 40) for fit in fits] == [0, 0, 0, 4, 0]
    late = _tracking_monitor(smcl_cfg)  # a dip paid back, then the held drop: counted from where S left zero again
    assert [late.lost(fit, 40) for fit in (0.3, 0.6, 0.6, 0.3, 0.3, None, 0.3, 0.3)] == [0, 0, 0, 0, 0, 0, 0, 5]
    near = _tracking_monitor(smcl_cfg)
    assert not any(near.lost(0.42, 40) for _ in range(50))  # 0.7 of the average, above e^−0.4: never adds up
    recovers = _tracking_monitor(smcl_cfg)
    assert not any(recovers.lost(fit, 40) for fit in (0.2, 0.6, 0.6, 0.6, 0.6, 0.2, 0.6))  # good frames pay it back
    spread = LostMonitor(_lost_cfg(smcl_cfg).relocalize)
    assert not any(spread.lost(fit, 40) for fit in (0.1,) * 12 + (0.01,) * 4)  # never reached 0.35: never lost
    assert not LostMonitor(_lost_cfg(smcl_cfg).relocalize).lost(None, 0)


def _kidnapped_scan() -> np.ndarray:
    """What the robot sees after being carried off: from (3, 3) facing +x these endpoints lie in free space of room A,
    1–1.5 m from any wall."""
    return np.column_stack([np.full(11, 1.5), np.linspace(-0.5, 0.5, 11)])


def test_a_tracking_filter_that_stops_explaining_the_scans_spreads_over_the_building_again(
    box_prior: BimPrior, box_visibility: VisibilityTable, smcl_cfg: SmclConfig
):
    runs = {}
    for relocalize in (True, False):
        mcl = SemanticMCL(box_prior, box_visibility, _lost_cfg(smcl_cfg, relocalize), np.random.default_rng(1), 300)
        mcl.initialize()
        mcl.particles[:] = [3.0, 3.0, 0.0]  # tracking at the truth
        steps = [mcl.step(None, None, _divider_scan()) for _ in range(10)]
        assert all(s.scan_fit is not None and s.scan_fit > 0.9 for s in steps)
        steps += [mcl.step(None, None, _kidnapped_scan()) for _ in range(2)]
        runs[relocalize] = (steps, mcl.particles.copy())
    steps, particles = runs[True]
    assert [s.relocalized for s in steps] == [False] * 11 + [True]
    assert steps[-1].scan_fit < 0.1  # the fit that showed it: before the particles were spread
    assert np.ptp(particles[:, 0]) > 8.0 and np.ptp(particles[:, 1]) > 4.0  # over both rooms of the box
    steps, particles = runs[False]
    assert not any(s.relocalized for s in steps)
    np.testing.assert_allclose(particles[:, :2], [[3.0, 3.0]] * len(particles))  # the paper's filter stays put
