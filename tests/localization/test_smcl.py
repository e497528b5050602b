"""The particle filter: initialization, prediction with off-map down-weighting, update, resampling, estimate."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SmclConfig
from bimfactor.errors import InputError
from bimfactor.evaluation.speed import benchmark_step
from bimfactor.localization.likelihood import polar_coordinates
from bimfactor.localization.smcl import (
    SemanticMCL,
    StepResult,
    circular_mean,
    effective_sample_size,
    kld_particle_count,
    local_mean_yaw,
    mixture_pose_covariance,
    near_pose,
    systematic_resample,
    weighted_geometric_median,
    weighted_pose_stats,
)
from bimfactor.types import Observations, wrap_angle
from tests.localization.handmade import make_prior, object_id, observe


def noise_free(cfg: SmclConfig) -> SmclConfig:
    return cfg.model_copy(update={"sigma_trans_m": 0.0, "sigma_rot_deg": 0.0})


# ------------------------------------------------------------------------------------------ pieces


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


def test_systematic_resampling_counts_are_proportional_to_weights():
    weights = np.array([0.1, 0.2, 0.3, 0.4, 0.0])
    for seed in range(5):
        idx = systematic_resample(weights, 1000, np.random.default_rng(seed))
        counts = np.bincount(idx, minlength=5)
        assert np.all(np.abs(counts - 1000 * weights) <= 1)  # low variance: ⌊n·w⌋ or ⌈n·w⌉
    idx = systematic_resample(np.array([0.25, 0.25, 0.5]), 7, np.random.default_rng(0))
    assert np.all(np.diff(idx) >= 0) and len(idx) == 7


# ------------------------------------------------------------------------------------------ the filter


def test_initialize_spreads_particles_over_navigable_space_of_all_storeys(smcl_cfg: SmclConfig):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, smcl_cfg, progress=False)
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


def test_initialize_around_a_pose_guess_draws_a_gaussian_on_navigable_space(smcl_cfg: SmclConfig):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, smcl_cfg, progress=False)
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
    assert mcl.weights[1] / mcl.weights[0] == pytest.approx(smcl_cfg.off_map_weight)


def test_update_multiplies_by_the_likelihood_and_normalises(box_prior, box_visibility, smcl_cfg):
    smcl_cfg = smcl_cfg.model_copy(update={"detection_probability": 0.0})  # the paper's model
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])  # sees the chair / looks away from it
    mcl.storeys = np.zeros(2, np.int64)
    mcl.update(observe(("chair", 1.0, 0.0)))  # score 1 and 0
    ratio = np.exp(1.0 / smcl_cfg.temperature)
    np.testing.assert_allclose(mcl.weights, [ratio / (1 + ratio), 1 / (1 + ratio)])
    before = mcl.weights.copy()
    mcl.update(Observations(np.zeros((0, 5), np.float32), np.zeros(0), np.zeros(0)))
    np.testing.assert_array_equal(mcl.weights, before)


def test_the_update_reports_the_frames_predictive_likelihood(box_prior, box_visibility, smcl_cfg):
    # ln p(z | belief) = ln Σ w_i p(z | x_i) over the weights before the update: with scores 1 and 0 and weights
    # 0.25 and 0.75 it is ln(0.25 e^(1/T) + 0.75); the challenger compares two filters by it.
    smcl_cfg = smcl_cfg.model_copy(update={"detection_probability": 0.0})
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])
    mcl.storeys = np.zeros(2, np.int64)
    mcl.weights = np.array([0.25, 0.75])
    mcl.update(observe(("chair", 1.0, 0.0)))
    assert mcl.log_evidence == pytest.approx(np.log(0.25 * np.exp(1.0 / smcl_cfg.temperature) + 0.75))
    mcl.update(None)
    assert mcl.log_evidence is None


def test_the_challenger_draws_from_its_own_generator(box_prior, box_visibility, smcl_cfg):
    # The belief's own draws are those it makes without a challenger: runs stay comparable until a hand-over.
    poses = []
    for challenger in (False, True):
        cfg = noise_free(smcl_cfg).model_copy(update={"challenger": challenger})
        mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(3), num_particles=300)
        mcl.initialize_around(np.array([4.0, 3.0, np.pi]), 0, 0.2, 0.1)
        for _ in range(6):
            result = mcl.step(np.array([0.0, 0.0, 0.0]), observe(("chair", 1.0, 0.0)))
        assert result.converged and not result.challenged
        assert (mcl.challenger is not None and mcl.challenger.filter._initialized) == challenger  # it ran
        poses.append(mcl.particles.copy())
    np.testing.assert_array_equal(*poses)


def test_a_frame_without_detections_weighs_the_objects_each_particle_should_have_seen(
    box_prior, box_visibility, smcl_cfg
):
    cfg = smcl_cfg.model_copy(update={"detection_probability": 0.4, "detection_range_m": 4.0})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=2)
    mcl.initialize()
    # Facing west from (4, 3) the chair (1 m) and the cabinet (3.6 m) are in view; facing east nothing is.
    mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])
    mcl.storeys = np.zeros(2, np.int64)
    mcl.update(Observations(np.zeros((0, 5), np.float32), np.zeros(0), np.zeros(0)))
    ratio = (1 - 0.4) ** 2
    np.testing.assert_allclose(mcl.weights, [ratio / (1 + ratio), 1 / (1 + ratio)])
    before = mcl.weights.copy()
    mcl.update(None)  # no frame: nothing to weigh by
    np.testing.assert_array_equal(mcl.weights, before)


def test_all_zero_weights_fall_back_to_uniform(box_prior, box_visibility, smcl_cfg, caplog):
    cfg = noise_free(smcl_cfg).model_copy(update={"off_map_weight": 0.0})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=3)
    mcl.initialize()
    mcl.particles = np.array([[5.0, 3.0, 0.0], [5.0, 2.0, 0.0], [5.0, 4.0, 0.0]])
    mcl.storeys = np.zeros(3, np.int64)
    mcl.predict(np.array([1.05, 0.0, 0.0]))  # all into the wall, weight × 0
    np.testing.assert_allclose(mcl.weights, np.full(3, 1 / 3))
    assert "resetting" in caplog.text
    mcl.update(observe(("chair", 1.0, 0.0)))
    assert np.all(np.isfinite(mcl.weights)) and mcl.weights.sum() == pytest.approx(1.0)


def test_resampling_happens_below_the_ess_threshold_and_resets_weights(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=100)
    mcl.initialize()
    assert mcl.resample_if_needed() == (False, 0)
    mcl.weights = np.zeros(100)
    mcl.weights[[3, 7]] = [0.75, 0.25]
    keep3, keep7 = mcl.particles[3].copy(), mcl.particles[7].copy()
    assert mcl.resample_if_needed() == (True, 0)
    np.testing.assert_allclose(mcl.weights, np.full(100, 0.01))
    assert (mcl.particles == keep3).all(axis=1).sum() == 75
    assert (mcl.particles == keep7).all(axis=1).sum() == 25


def test_kld_particle_count_matches_fox_2003():
    # k = 30 bins, ε = 0.05, z = 2.33: 29 / 0.1 · (1 − 2/261 + √(2/261) · 2.33)³
    a = 2.0 / (9.0 * 29)
    assert kld_particle_count(30, 0.05, 2.33) == int(np.ceil(290.0 * (1.0 - a + np.sqrt(a) * 2.33) ** 3))
    counts = kld_particle_count(np.array([1, 2, 10, 100, 1000]), 0.05, 2.33)
    assert counts[0] == 1 and np.all(np.diff(counts) > 0)  # more occupied bins need more particles
    assert kld_particle_count(100, 0.01, 2.33) > kld_particle_count(100, 0.05, 2.33)  # a tighter bound needs more


def test_kld_sampling_starts_wide_and_shrinks_to_m_on_a_converged_cloud(box_prior, box_visibility, smcl_cfg):
    cfg = smcl_cfg.model_copy(
        update={"kld_sampling": True, "num_particles": 200, "max_particles": 3000, "augmented": False}
    )
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0))
    mcl.initialize()
    assert mcl.num_particles == len(mcl.particles) == len(mcl.weights) == 3000
    # A spread belief (the weight on a uniform quarter of the particles) occupies hundreds of bins: it keeps
    # more particles than M …
    mcl.weights = np.where(np.arange(3000) % 4 == 0, 1.0, 1e-9)
    mcl.weights /= mcl.weights.sum()
    assert mcl.resample_if_needed() == (True, 0)
    spread = mcl.num_particles
    assert 200 < spread <= 3000 and len(mcl.particles) == len(mcl.weights) == spread
    np.testing.assert_allclose(mcl.weights, np.full(spread, 1.0 / spread))
    # … a belief on three particles (three bins) needs a handful: the count falls to M.
    mcl.weights = np.zeros(spread)
    mcl.weights[[0, 1, 2]] = 1.0 / 3
    assert mcl.resample_if_needed() == (True, 0)
    assert mcl.num_particles == len(mcl.particles) == 200
    assert len({tuple(p) for p in mcl.particles}) <= 3
    # A count given to the constructor is fixed (benchmarks measure one M).
    fixed = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=500)
    fixed.initialize()
    assert fixed.num_particles == 500


def test_augmented_mcl_injects_random_particles_when_the_short_average_drops(box_prior, box_visibility, smcl_cfg):
    cfg = smcl_cfg.model_copy(update={"augmented": True})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=1000)
    mcl.initialize()
    mcl.w_slow, mcl.w_fast = 1.0, 0.2
    assert mcl.injection_probability() == pytest.approx(0.8)
    resampled, injected = mcl.resample_if_needed()
    assert resampled and abs(injected - 800) < 60
    literal = smcl_cfg.model_copy(update={"augmented": False})
    paper = SemanticMCL(box_prior, box_visibility, literal, np.random.default_rng(0), num_particles=1000)
    paper.initialize()
    paper.w_slow, paper.w_fast = 1.0, 0.2
    assert paper.injection_probability() == 0.0 and paper.resample_if_needed() == (False, 0)


def test_the_recovery_averages_watch_the_mean_score_whatever_the_count_exponent(box_prior, box_visibility, smcl_cfg):
    both = observe(("chair", 1.0, 0.0), ("table", 2.0, 0.0))  # from the first particle: the chair scores 1, the table 0
    averages = []
    for gamma in (1.0, 0.0):
        cfg = smcl_cfg.model_copy(update={"augmented": True, "score_count_exponent": gamma, "scan_likelihood": False})
        mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=2)
        mcl.initialize()
        mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])
        mcl.storeys = np.zeros(2, np.int64)
        mcl.update(both)
        averages.append(mcl.w_fast)
        ratio = np.exp(cfg.temperature**-1 * (0.5 if gamma == 1.0 else 1.0))  # exp(K^(1-γ) · mean / T), mean 0.5
        np.testing.assert_allclose(mcl.weights[0] / mcl.weights[1], ratio, rtol=1e-6)
    # Both started from equal weights: the average of the likelihoods of mean scores 0.5 and 0, on the mean's scale.
    expected = 0.5 * (np.exp(-0.5 / smcl_cfg.temperature) + np.exp(-1.0 / smcl_cfg.temperature))
    np.testing.assert_allclose(averages, expected)


def test_a_reference_score_floors_the_long_term_average(box_prior, box_visibility, smcl_cfg):
    """A filter whose long-term average began at the uniform cloud's (tiny) likelihood never sees its short average
    drop below it; the reference floor makes a poorly explaining filter inject all the same, a well explaining
    one not."""
    temperature = smcl_cfg.temperature
    cfg = smcl_cfg.model_copy(update={"augmented": True, "injection_reference_score": 0.5})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=1000)
    mcl.initialize()
    reference = np.exp((0.5 - 1.0) / temperature)
    mcl.w_slow, mcl.w_fast = 1e-5, 0.25 * reference  # locked where observations score ~0.36: w_fast > w_slow
    assert mcl.injection_probability() == pytest.approx(0.75)
    mcl.w_fast = 2.0 * reference  # observations explained better than the reference: nothing to recover from
    assert mcl.injection_probability() == 0.0
    mcl.w_slow, mcl.w_fast = 10.0 * reference, 5.0 * reference  # above the floor Thrun's rule is unchanged
    assert mcl.injection_probability() == pytest.approx(0.5)
    thrun = smcl_cfg.model_copy(update={"augmented": True, "injection_reference_score": 0.0})
    plain = SemanticMCL(box_prior, box_visibility, thrun, np.random.default_rng(0), num_particles=1000)
    plain.initialize()
    plain.w_slow, plain.w_fast = 1e-5, 0.25 * reference
    assert plain.injection_probability() == 0.0


def test_estimate_is_the_weighted_circular_mean_on_the_heaviest_storey(smcl_cfg: SmclConfig):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, smcl_cfg, progress=False)
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
    assert est.converged  # std 0.14 m, 5°, 94 % on one storey
    assert est.covariance.shape == (3, 3) and np.allclose(est.covariance, est.covariance.T)
    mcl.weights = np.array([0.4, 0.4, 0.1, 0.1])
    assert not mcl.estimate().converged  # only 80 % of the weight on the estimated storey


def test_observations_decide_the_storey(smcl_cfg: SmclConfig):
    prior = make_prior(n_storeys=2)  # only storey 1 has a chair beside a table
    table = VisibilityTable.build(prior, smcl_cfg, progress=False)
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
    challenger = {"challenger"} if smcl_cfg.challenger else set()
    assert set(result.timings_ms) == {"predict", "update", "resample", "estimate"} | challenger
    assert 1.0 <= result.ess <= 200.0 and result.n_observations == 1
    assert result.covariance is result.estimate.covariance


def test_filter_needs_initialize_before_predict(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="initialize"):
        mcl.predict(np.zeros(3))


def test_benchmark_reports_one_row_per_particle_count(box_prior, box_visibility, smcl_cfg):
    rows = benchmark_step(box_prior, box_visibility, smcl_cfg, n_particles_list=(50, 200), n_obs=4, repeats=2)
    assert [r["n_particles"] for r in rows] == [50, 200]
    assert all(r["n_obs"] == 4 and r["total_ms_median"] > 0 for r in rows)


def test_poses_drawn_from_an_observation_explain_it(box_prior, box_visibility, smcl_cfg):
    # One chair seen 1.5 m ahead, 0.3 rad to the left: every drawn pose has the chair there (within the motion
    # noise), stands on navigable space, and lists the chair as visible; the table cannot explain it.
    mcl = SemanticMCL(box_prior, box_visibility, noise_free(smcl_cfg), np.random.default_rng(1), num_particles=10)
    poses, storeys = mcl.sample_from_observations(300, observe(("chair", 1.5, 0.3)))
    assert len(poses) == 300 and (storeys == 0).all()
    chair = np.asarray(box_prior.objects[object_id(box_prior, "chair")].position_m[:2])
    d, alpha = polar_coordinates(poses, chair[None, :])
    np.testing.assert_allclose(d, 1.5, atol=1e-9)
    np.testing.assert_allclose(alpha, 0.3, atol=1e-9)
    assert mcl.on_navigable(poses, storeys).all()
    assert len({round(float(a), 1) for a in np.arctan2(poses[:, 1] - chair[1], poses[:, 0] - chair[0])}) > 20
    unexplained = observe(("bookshelf", 20.0, 0.0))  # nowhere in the building is a bookshelf 20 m away
    assert len(mcl.sample_from_observations(50, unexplained)[0]) == 0


def test_augmented_mcl_can_inject_poses_that_explain_the_observations(box_prior, box_visibility, smcl_cfg):
    cfg = smcl_cfg.model_copy(update={"augmented": True, "injection": "observations"})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=1000)
    mcl.initialize()
    mcl.w_slow, mcl.w_fast = 1.0, 0.0
    obs = observe(("chair", 1.0, 0.0))
    resampled, injected = mcl.resample_if_needed(obs)
    assert resampled and injected == 1000
    assert mcl.likelihood.scores(mcl.particles, mcl.storeys, obs).mean() > 0.5
