"""The particle filter's loop: initialization, prediction with off-map down-weighting, the measurement update,
resampling, the estimate, and one step of all of them."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.navigation import PORTAL_REACH_M
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config, SmclConfig, updated
from bimfactor.errors import InputError
from bimfactor.evaluation.speed import benchmark_step
from bimfactor.localization.filter import SemanticMCL, StepResult
from bimfactor.localization.measurements import FrameData
from bimfactor.types import Observations, wrap_angle
from tests.localization.handmade import make_prior, observe


def noise_free(cfg: SmclConfig) -> SmclConfig:
    return updated(cfg, {"motion.sigma_trans_m": 0.0, "motion.sigma_rot_deg": 0.0})


def test_initialize_spreads_particles_over_navigable_space_of_all_storeys(smcl_cfg: SmclConfig, test_config: Config):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    mcl = SemanticMCL(prior, table, smcl_cfg, np.random.default_rng(0), num_particles=4000)
    mcl.initialize()
    assert mcl.on_navigable(mcl.particles, mcl.storeys).all()
    assert abs((mcl.storeys == 1).mean() - 0.5) < 0.04  # identical storeys: half each
    assert mcl.particles[:, 2].min() >= -np.pi and mcl.particles[:, 2].max() < np.pi
    assert np.std(mcl.particles[:, 2]) == pytest.approx(2 * np.pi / np.sqrt(12), rel=0.05)  # uniform yaw
    np.testing.assert_allclose(mcl.weights.sum(), 1.0)
    mcl.initialize(storeys=[1])
    assert np.all(mcl.storeys == 1)
    with pytest.raises(InputError, match=r"storeys \[2, 5\] do not exist: the prior has storeys 0 … 1$"):
        mcl.initialize(storeys=[1, 5, 2])


def test_initialize_around_a_pose_guess_draws_a_gaussian_on_navigable_space(smcl_cfg: SmclConfig, test_config: Config):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    mcl = SemanticMCL(prior, table, smcl_cfg, np.random.default_rng(0), num_particles=4000)
    guess = np.array([3.0, 3.0, np.pi - 0.05])  # the yaw draws straddle ±π
    mcl.initialize_around(guess, 1, 0.3, np.deg2rad(10.0))
    assert mcl.num_particles == 4000 and np.all(mcl.storeys == 1)
    assert mcl.on_navigable(mcl.particles, mcl.storeys).all()
    np.testing.assert_allclose(mcl.particles[:, :2].mean(axis=0), guess[:2], atol=0.03)
    np.testing.assert_allclose(mcl.particles[:, :2].std(axis=0), 0.3, rtol=0.05)
    turn = wrap_angle(mcl.particles[:, 2] - guess[2])
    assert abs(turn.mean()) < np.deg2rad(0.5) and turn.std() == pytest.approx(np.deg2rad(10.0), rel=0.05)
    assert mcl.particles[:, 2].min() >= -np.pi and mcl.particles[:, 2].max() < np.pi
    np.testing.assert_allclose(mcl.weights, 1 / 4000)

    mcl.initialize_around(np.array([0.5, 3.0, 0.0]), 0, 0.5, 0.1)  # 0.5 m from the west wall: draws into it redrawn
    assert mcl.on_navigable(mcl.particles, mcl.storeys).all() and mcl.particles[:, 0].mean() > 0.6

    with pytest.raises(InputError, match="storey 2 does not exist"):
        mcl.initialize_around(guess, 2, 0.5, 0.1)
    with pytest.raises(InputError, match=r"initial pose \(100.00 m, 100.00 m\) on storey 0: no navigable space"):
        mcl.initialize_around(np.array([100.0, 100.0, 0.0]), 0, 0.5, 0.1)


def test_particles_leaving_navigable_space_are_down_weighted(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, noise_free(smcl_cfg), np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[2.0, 3.0, 0.0], [5.0, 3.0, 0.0]])
    mcl.storeys = np.zeros(2, np.int64)
    mcl.predict(np.array([1.05, 0.0, 0.0]))  # the second particle ends inside the dividing wall
    np.testing.assert_allclose(mcl.particles[:, 0], [3.05, 6.05])
    assert mcl.weights[1] / mcl.weights[0] == pytest.approx(smcl_cfg.motion.off_map_weight)


def test_update_multiplies_by_the_likelihood_and_normalises(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])  # sees the chair / looks away from it
    mcl.storeys = np.zeros(2, np.int64)
    mcl.update(FrameData(observe(("chair", 1.0, 0.0))))  # score 1 and 0
    ratio = np.exp(1.0 / smcl_cfg.semantic.temperature)
    np.testing.assert_allclose(mcl.weights, [ratio / (1 + ratio), 1 / (1 + ratio)])
    before = mcl.weights.copy()
    nothing = mcl.update(FrameData(Observations(np.zeros((0, 5), np.float32), np.zeros(0), np.zeros(0))))
    np.testing.assert_array_equal(mcl.weights, before)
    assert nothing.terms == {} and nothing.log_evidence is None


def test_the_update_reports_the_frames_predictive_likelihood(box_prior, box_visibility, smcl_cfg):
    # ln p(z | belief) = ln Σ w_i p(z | x_i) over the weights before the update: with scores 1 and 0 and weights
    # 0.25 and 0.75 it is ln(0.25 e^(1/T) + 0.75); the challenger compares two filters by it.
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])
    mcl.storeys = np.zeros(2, np.int64)
    mcl.weights = np.array([0.25, 0.75])
    update = mcl.update(FrameData(observe(("chair", 1.0, 0.0))))
    assert update.log_evidence == pytest.approx(np.log(0.25 * np.exp(1.0 / smcl_cfg.semantic.temperature) + 0.75))
    np.testing.assert_array_equal(update.weights, [0.25, 0.75])  # the weights before it
    assert mcl.update(FrameData()).log_evidence is None


def test_all_zero_weights_fall_back_to_uniform(box_prior, box_visibility, smcl_cfg, caplog):
    cfg = updated(noise_free(smcl_cfg), {"motion.off_map_weight": 0.0})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=3)
    mcl.initialize()
    mcl.particles = np.array([[5.0, 3.0, 0.0], [5.0, 2.0, 0.0], [5.0, 4.0, 0.0]])
    mcl.storeys = np.zeros(3, np.int64)
    mcl.predict(np.array([1.05, 0.0, 0.0]))  # all into the wall, weight × 0
    np.testing.assert_allclose(mcl.weights, np.full(3, 1 / 3))
    assert "resetting" in caplog.text
    mcl.update(FrameData(observe(("chair", 1.0, 0.0))))
    assert np.all(np.isfinite(mcl.weights)) and mcl.weights.sum() == pytest.approx(1.0)


def test_resampling_happens_below_the_ess_threshold_and_resets_weights(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=100)
    mcl.initialize()
    assert mcl.resample(FrameData()) == (False, 0)
    mcl.weights = np.zeros(100)
    mcl.weights[[3, 7]] = [0.75, 0.25]
    keep3, keep7 = mcl.particles[3].copy(), mcl.particles[7].copy()
    assert mcl.resample(FrameData()) == (True, 0)
    np.testing.assert_allclose(mcl.weights, np.full(100, 0.01))
    assert (mcl.particles == keep3).all(axis=1).sum() == 75
    assert (mcl.particles == keep7).all(axis=1).sum() == 25


def test_estimate_is_the_weighted_circular_mean_on_the_heaviest_storey(smcl_cfg: SmclConfig, test_config: Config):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    mcl = SemanticMCL(prior, table, smcl_cfg, np.random.default_rng(0), num_particles=4)
    mcl.initialize()
    mcl.particles = np.array(
        [[3.0, 2.0, np.deg2rad(175.0)], [3.2, 2.2, np.deg2rad(-175.0)], [9.0, 3.0, 0.0], [9.0, 3.0, 0.0]]
    )
    mcl.storeys = np.array([1, 1, 0, 0])
    mcl.weights = np.array([0.47, 0.47, 0.03, 0.03])
    est = mcl.estimate()
    assert est.storey == 1 and est.storey_share == pytest.approx(0.94)
    np.testing.assert_allclose(est.pose[:2], [3.1, 2.1])
    assert abs(wrap_angle(est.pose[2] - np.pi)) < 1e-9
    assert est.room_id == 2  # room A of storey 1
    assert est.compact  # std 0.14 m, 5°, 94 % on one storey ...
    assert not est.converged  # ... but no challenger has looked for a look-alike place yet
    paper_flag = updated(smcl_cfg, {"challenger.enabled": False})
    no_challenger = SemanticMCL(prior, table, paper_flag, np.random.default_rng(0), num_particles=4)
    no_challenger.initialize()
    no_challenger.particles, no_challenger.storeys, no_challenger.weights = mcl.particles, mcl.storeys, mcl.weights
    assert no_challenger.estimate().converged  # the paper's flag: compact is converged
    assert est.covariance.shape == (3, 3) and np.allclose(est.covariance, est.covariance.T)
    mcl.weights = np.array([0.4, 0.4, 0.1, 0.1])
    assert not mcl.estimate().compact  # only 80 % of the weight on the estimated storey


def test_observations_decide_the_storey(smcl_cfg: SmclConfig, test_config: Config):
    prior = make_prior(n_storeys=2)  # only storey 1 has a chair beside a table
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    mcl = SemanticMCL(prior, table, smcl_cfg, np.random.default_rng(5), num_particles=2000)
    mcl.initialize()
    # From (4, 3) facing west: the table 1 m ahead, the chair at (2, 3.8) 2.15 m away, 22° to the right.
    seen = observe(("table", 1.0, 0.0), ("chair", np.hypot(2.0, 0.8), np.arctan2(0.8, -2.0) - np.pi))
    result = None
    for _ in range(8):
        result = mcl.step(np.zeros(3), seen)
    assert isinstance(result, StepResult)
    assert result.storey == 1 and result.estimate.storey_share > 0.9
    assert np.hypot(*(result.pose[:2] - [4.0, 3.0])) < 1.0


def test_step_reports_timings_and_ess(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=200)
    result = mcl.step(None, observe(("chair", 1.0, 0.0)))
    assert set(result.timings_ms) == {"predict", "update", "resample", "estimate", "recover"}
    assert 1.0 <= result.ess <= 200.0 and result.n_observations == 1
    assert result.covariance is result.estimate.covariance


def test_filter_needs_initialize_before_predict(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="initialize"):
        mcl.predict(np.zeros(3))


def test_benchmark_reports_one_row_per_particle_count(box_prior, box_visibility, smcl_cfg):
    rows = benchmark_step(box_prior, box_visibility, smcl_cfg, 6.0, n_particles_list=(50, 200), n_obs=4, repeats=2)
    assert [r["n_particles"] for r in rows] == [50, 200]
    assert all(r["n_obs"] == 4 and r["total_ms_median"] > 0 for r in rows)


def _with_portals(test_config: Config) -> tuple:
    """The two-room box on two storeys with a lift in the west room's south-west corner, stopping at both, and a
    stair rising from the east room's south wall (storey 0) to its north wall (storey 1)."""
    from bimfactor.bim.prior import Portal, PortalEnd

    prior = make_prior(n_storeys=2)
    lift_box = (0.2, 0.2, 1.0, 1.0)
    prior.portals = [
        Portal(0, "lift", "lift", "IfcTransportElement", [PortalEnd(0, lift_box), PortalEnd(1, lift_box)]),
        Portal(
            1, "stair", "stair", "IfcStairFlight", [PortalEnd(0, (9, 0.2, 10, 0.5)), PortalEnd(1, (9, 5.5, 10, 5.8))]
        ),
    ]
    return prior, VisibilityTable.build(prior, test_config.bim.visibility, progress=False)


def test_a_portal_carries_particles_between_floors(smcl_cfg: SmclConfig, test_config: Config):
    prior, table = _with_portals(test_config)
    mcl = SemanticMCL(prior, table, noise_free(smcl_cfg), np.random.default_rng(0), num_particles=4000)
    at_lift, far = np.array([1.5, 1.5, 0.3]), np.array([4.0, 4.0, 0.0])
    at_foot = np.array([9.5, 1.0, 1.0])
    poses = np.repeat([at_lift, far, at_foot], [2000, 1000, 1000], axis=0)
    start = np.zeros(4000, np.int64)

    # Without an event: a few particles at each portal go through, keeping their place (a stair's climb is in the
    # odometry increment).
    mcl.set_particles(poses, start)
    mcl.predict(np.zeros(3))
    went = mcl.storeys == 1
    assert not went[2000:3000].any()
    for part in (slice(0, 2000), slice(3000, 4000)):
        assert went[part].mean() == pytest.approx(mcl.cfg.motion.portal_share, abs=0.02)
    np.testing.assert_allclose(mcl.particles, poses)
    np.testing.assert_allclose(mcl.weights, 1 / 4000)
    # A step that passes the stair's foot counts, though it starts and ends 1.2 m from it.
    mcl.set_particles(np.repeat([[8.0, 1.2, 0.0]], 4000, axis=0), start)
    mcl.predict(np.array([3.0, 0.0, 0.0]))
    assert (mcl.storeys == 1).mean() == pytest.approx(mcl.cfg.motion.portal_share, abs=0.015)
    # A step across the stair's steps (where no robot on the floor can drive) climbed it, likely.
    mcl.set_particles(np.repeat([[9.5, 1.5, -np.pi / 2]], 4000, axis=0), start)
    mcl.predict(np.array([1.4, 0.0, 0.0]))
    assert (mcl.storeys == 1).mean() == pytest.approx(mcl.cfg.motion.portal_cross_share, abs=0.03)

    # Told the robot went up a floor: every particle at a portal goes; the rest come out of a portal's end on the floor
    # above (on navigable space, within reach of the lift or the stair's head) with a thousandth of their weight.
    mcl.set_particles(poses, start)
    mcl.predict(np.zeros(3), storey_change=1)
    assert np.all(mcl.storeys == 1)
    np.testing.assert_allclose(mcl.particles[:2000], poses[:2000])
    moved = mcl.particles[2000:3000]
    near_lift = np.all((moved[:, :2] >= 0.2 - PORTAL_REACH_M) & (moved[:, :2] <= 1.0 + PORTAL_REACH_M), axis=1)
    near_head = np.all(moved[:, :2] >= (9 - PORTAL_REACH_M, 5.5 - PORTAL_REACH_M), axis=1)
    assert np.all(near_lift | near_head) and near_lift.any() and near_head.any()
    assert mcl.on_navigable(moved, mcl.storeys[2000:3000]).all()
    assert mcl.weights[2000:3000].sum() == pytest.approx(1e-3 * 1000 / (3000 + 1e-3 * 1000))
    # A belief with no particle where the robot rode: it learns from the ride where the robot is, at the portals' ends.
    mcl.set_particles(poses[2000:3000], start[2000:3000])
    mcl.predict(np.zeros(3), storey_change=1)
    assert np.all(mcl.storeys == 1)
    np.testing.assert_allclose(mcl.weights, 1 / 1000)
    # Down from the lowest floor: no particle can, so all keep equal weights.
    mcl.set_particles(poses, start)
    mcl.predict(np.zeros(3), storey_change=-1)
    assert np.all(mcl.storeys == 0)
    np.testing.assert_allclose(mcl.weights, 1 / 4000)
