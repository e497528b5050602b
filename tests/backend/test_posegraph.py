"""Per-mode pose graphs on a synthetic loop: ISAM2 and batch LM accuracy, robust kernels, covariance honesty."""

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from bimfactor.backend.factors import (
    Landmarks,
    bearing_range_noise,
    covariance_body_to_world,
    covariance_world_to_body,
    landmark_factors,
    landmark_prior_factor,
    odometry_factor,
    pose_prior_factor,
)
from bimfactor.backend.posegraph import (
    ModeGraph,
    MultiHypothesisBackend,
    _without_degenerate_bearings,
    batch_refine,
    floored_covariance,
)
from bimfactor.backend.synthetic import PRECISE_ODOMETRY, LoopScenario, loop_scenario
from bimfactor.config import load_config
from bimfactor.localization.measurements.semantic import polar_coordinates
from bimfactor.localization.modes import Mode
from bimfactor.types import Observations, se2_compose, wrap_angle

DEFAULT = load_config()
BASE, WHEEL_ODOMETRY = DEFAULT.backend, DEFAULT.odometry
# A precise sensor, odometry (PRECISE_ODOMETRY) and BIM for the accuracy tests (σ_r 5 cm, σ_b 1°, BIM σ 2 cm;
# truth = BIM).
PRECISE = BASE.model_copy(
    update={
        "range_sigma_m": 0.05,
        "bearing_sigma_deg": 1.0,
        "landmark_sigma_m": 0.02,
        "odom_robust_kernel": "none",  # its noise is the model's own, without slips
    }
)
FIRST_COV = np.diag([0.1, 0.1, np.deg2rad(2.0)]) ** 2
CHI2_3DOF_95 = 7.815
WRONG_MATCH_STEP = 10


def _errors(poses: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """RMS position error (m) and RMS yaw error (deg) of (T, 3) poses."""
    err = poses - truth
    err[:, 2] = wrap_angle(err[:, 2])
    return float(np.sqrt((err[:, :2] ** 2).sum(axis=1).mean())), float(np.rad2deg(np.sqrt((err[:, 2] ** 2).mean())))


def _run_isam(sc: LoopScenario, cfg, associations=None) -> ModeGraph:
    associations = sc.associations if associations is None else associations
    graph = ModeGraph(0, 0, sc.true_poses[0], FIRST_COV, sc.landmark_xy, cfg, PRECISE_ODOMETRY)
    for t in range(len(sc.true_poses)):
        graph.add_keyframe(t, sc.observations[t], associations[t], None if t == 0 else sc.increments[t - 1])
    return graph


def _run_batch(sc: LoopScenario, cfg, associations=None):
    associations = sc.associations if associations is None else associations
    return batch_refine(
        sc.true_poses[0], FIRST_COV, sc.increments, sc.observations, associations, sc.landmark_xy, cfg, PRECISE_ODOMETRY
    )


def _wrong_associations(sc: LoopScenario) -> tuple[list, float]:
    """The true associations with one observation matched to a landmark ≈ 3 m from its true one."""
    associations = [list(a) for a in sc.associations]
    k, true_j = associations[WRONG_MATCH_STEP][0]
    gaps = np.linalg.norm(sc.landmark_xy - sc.landmark_xy[true_j], axis=1)
    wrong_j = int(np.argmin(np.abs(gaps - 3.0)))
    associations[WRONG_MATCH_STEP][0] = (k, wrong_j)
    return associations, float(gaps[wrong_j])


def test_covariance_frame_round_trip():
    cov = np.array([[0.04, 0.01, 0.001], [0.01, 0.01, 0.0], [0.001, 0.0, 0.002]])
    body = covariance_world_to_body(cov, 0.7)
    np.testing.assert_allclose(covariance_body_to_world(body, 0.7), cov, atol=1e-12)
    # At heading 90° the body x axis points along world y: a world-x uncertainty is a body-y one.
    np.testing.assert_allclose(
        covariance_world_to_body(np.diag([1.0, 0.0, 0.0]), np.pi / 2), np.diag([0, 1.0, 0]), atol=1e-12
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("relinearize_skip", [1, 10])
def test_isam2_converges_to_the_true_loop(seed, relinearize_skip):
    cfg = PRECISE.model_copy(update={"relinearize_skip": relinearize_skip})
    sc = loop_scenario(np.random.default_rng(seed), cfg, PRECISE_ODOMETRY)
    graph = _run_isam(sc, cfg)
    assert graph.isam.params().relinearizeSkip == relinearize_skip
    trans_rms_m, yaw_rms_deg = _errors(graph.trajectory(), sc.true_poses)
    assert trans_rms_m < 0.05
    assert yaw_rms_deg < 1.0
    # The online (filtered) estimate of the last pose beats dead reckoning, which drifts.
    dead = sc.true_poses[0]
    for inc in sc.increments:
        dead = se2_compose(dead, inc)
    online_err_m = np.linalg.norm(graph.pose[:2] - sc.true_poses[-1, :2])
    assert online_err_m < 0.1
    assert online_err_m < np.linalg.norm(dead[:2] - sc.true_poses[-1, :2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_batch_lm_converges_and_agrees_with_isam2(seed):
    sc = loop_scenario(np.random.default_rng(seed), PRECISE, PRECISE_ODOMETRY)
    result = _run_batch(sc, PRECISE)
    trans_rms_m, yaw_rms_deg = _errors(result.poses, sc.true_poses)
    assert trans_rms_m < 0.05
    assert yaw_rms_deg < 1.0
    assert result.error_after < result.error_before
    assert result.covariances.shape == (20, 3, 3)
    assert np.all(np.linalg.eigvalsh(result.covariances) > 0)
    # ISAM2's smoothed trajectory is near the same optimum (one relinearization per keyframe: not all the way).
    gap = _run_isam(sc, PRECISE).trajectory()[:, :2] - result.poses[:, :2]
    assert np.sqrt((gap**2).sum(axis=1).mean()) < 0.02


@pytest.mark.parametrize("kernel", ["cauchy", "huber"])
def test_robust_kernel_down_weights_a_wrong_match_that_drags_the_plain_graph(kernel):
    sc = loop_scenario(np.random.default_rng(1), PRECISE, PRECISE_ODOMETRY)
    wrong, gap_m = _wrong_associations(sc)
    assert 2.5 < gap_m < 4.0
    k = {"cauchy": 2.385, "huber": 1.345}[kernel]
    robust = PRECISE.model_copy(update={"robust_kernel": kernel, "robust_k": k})
    plain = PRECISE.model_copy(update={"robust_kernel": "none"})
    for run in (lambda s, c, a=None: _run_isam(s, c, a).trajectory(), lambda s, c, a=None: _run_batch(s, c, a).poses):
        shift_robust = np.abs(run(sc, robust, wrong) - run(sc, robust))[:, :2].max()
        shift_plain = np.abs(run(sc, plain, wrong) - run(sc, plain))[:, :2].max()
        assert shift_robust < 0.06
        assert shift_plain > 0.3


def _max_yaw_error_deg(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.rad2deg(np.abs(wrap_angle(poses[:, 2] - truth[:, 2])).max()))


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_odometry_lets_the_landmarks_overrule_a_turn_the_wheels_measured_short(kernel):
    """An 18° turn measured as 4.5° (a slip): ~10σ of the odometry model evaluated at the measured increment."""
    sc = loop_scenario(np.random.default_rng(2), PRECISE, PRECISE_ODOMETRY)
    plain = PRECISE  # no kernel on the odometry
    clean = _run_batch(sc, plain).poses
    sc.increments[9][2] -= np.deg2rad(13.5)
    k = {"cauchy": 2.385, "huber": 1.345}[kernel]
    robust = PRECISE.model_copy(update={"odom_robust_kernel": kernel, "odom_robust_k": k})
    assert _max_yaw_error_deg(_run_batch(sc, plain).poses, sc.true_poses) > 4.0
    refined = _run_batch(sc, robust).poses
    assert _max_yaw_error_deg(refined, sc.true_poses) < 1.0
    assert _max_yaw_error_deg(refined, sc.true_poses) < _max_yaw_error_deg(clean, sc.true_poses) + 0.5
    # Online too, though ISAM2 relinearizes only every tenth keyframe.
    online_plain = _max_yaw_error_deg(_run_isam(sc, plain).trajectory(), sc.true_poses)
    online_robust = _max_yaw_error_deg(_run_isam(sc, robust).trajectory(), sc.true_poses)
    assert online_robust < online_plain - 2.0


def test_covariance_is_honest_on_the_synthetic_loop():
    """The true pose lies inside the online estimate's 95 % ellipse on roughly 95 % of the steps."""
    inside, total = 0, 0
    for seed in range(6):
        sc = loop_scenario(np.random.default_rng(100 + seed), BASE, WHEEL_ODOMETRY, as_built=True)
        graph = ModeGraph(0, 0, sc.true_poses[0], FIRST_COV, sc.landmark_xy, BASE, WHEEL_ODOMETRY)
        for t in range(len(sc.true_poses)):
            graph.add_keyframe(t, sc.observations[t], sc.associations[t], None if t == 0 else sc.increments[t - 1])
            err = sc.true_poses[t] - graph.pose
            err[2] = wrap_angle(err[2])
            inside += int(err @ np.linalg.solve(graph.covariance, err) <= CHI2_3DOF_95)
            total += 1
    assert 0.8 <= inside / total <= 1.0


def test_reassociation_swaps_the_factors_when_the_estimate_moves():
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    graph = ModeGraph(0, 0, sc.true_poses[0], FIRST_COV, sc.landmark_xy, PRECISE, PRECISE_ODOMETRY)
    graph.add_keyframe(0, sc.observations[0], sc.associations[0])
    graph.add_keyframe(1, sc.observations[1], sc.associations[1], sc.increments[0])
    calls = []

    def associate(pose, storey):
        calls.append(pose)
        return sc.associations[1]

    # Close to where it associated: nothing is re-run.
    assert not graph.reassociate(sc.observations[1], associate, graph.pose)
    assert calls == []
    # Far from where it associated: the callback runs; same matches, so nothing is swapped.
    far = graph.pose + np.array([1.0, 0.0, 0.0])
    assert not graph.reassociate(sc.observations[1], associate, far)
    assert len(calls) == 1
    # Different matches: the keyframe's landmark factors are replaced.
    n_before = graph.isam.getFactorsUnsafe().nrFactors()
    assert graph.reassociate(sc.observations[1], lambda p, s: sc.associations[1][:2], far)
    assert graph.associations[1] == sc.associations[1][:2]
    assert graph.isam.getFactorsUnsafe().nrFactors() == n_before - (len(sc.associations[1]) - 2)


def test_a_cluster_on_a_line_in_x_and_yaw_still_starts_a_graph():
    """Particles resampled from a few ancestors and turned lie on a line in x–yaw: both variances are above the
    floor, yet the cluster's covariance is singular. Raising only the diagonal left it so and ISAM2 found the mode's
    first keyframe indeterminate; the floor holds in every direction."""
    sigma = np.array([BASE.prior_min_sigma_m, BASE.prior_min_sigma_m, np.deg2rad(BASE.prior_min_sigma_deg)])
    along = np.array([0.44, 0.07, -0.2])  # x and yaw move together (σ 0.44 m and 11.5°, above the floor)
    singular = np.outer(along, along)
    floored = floored_covariance(singular, BASE)
    assert np.linalg.eigvalsh(floored / np.outer(sigma, sigma)).min() == pytest.approx(1.0)
    np.testing.assert_allclose(floored @ np.linalg.solve(floored, along), along)  # the cluster's own spread stays
    assert floored[0, 0] >= singular[0, 0] and floored[2, 2] >= singular[2, 2]
    diagonal = np.diag([0.5, 0.01, 0.001])
    np.testing.assert_allclose(floored_covariance(diagonal, BASE), np.diag(np.maximum(np.diag(diagonal), sigma**2)))
    graph = ModeGraph(0, 0, np.array([1.0, 2.0, 0.3]), singular, np.array([[50.0, 50.0]]), BASE, WHEEL_ODOMETRY)
    graph.add_keyframe(0, Observations(np.zeros((0, 4), np.float32), np.zeros(0), np.zeros(0)), [])
    np.testing.assert_allclose(graph.pose, [1.0, 2.0, 0.3], atol=1e-9)
    assert np.linalg.eigvalsh(graph.covariance).min() > 0


def test_pose_factor_pulls_the_estimate():
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    graph = _run_isam(sc, PRECISE)
    target = graph.pose + np.array([0.3, 0.0, 0.0])
    graph.add_pose_factor(19, target, np.diag([1e6, 1e6, 1e6]))
    np.testing.assert_allclose(graph.pose, target, atol=0.01)
    assert np.sqrt(graph.covariance[0, 0]) < 0.01


def test_batch_covariances_fall_back_to_the_motion_graph_when_the_marginals_fail(monkeypatch, caplog):
    """GTSAM may find the full graph's marginals indeterminate at the optimum: the run keeps its optimised poses and
    reports the prior-and-odometry covariances, which are wider than the full graph's, with a warning."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    normal = _run_batch(sc, PRECISE)
    import bimfactor.backend.posegraph as posegraph

    real_marginals, calls = posegraph.gtsam.Marginals, []

    def failing_first(graph, values):
        calls.append(graph.size())
        if len(calls) == 1:
            raise RuntimeError("Indeterminant linear system detected while working near variable x0.")
        return real_marginals(graph, values)

    monkeypatch.setattr(posegraph.gtsam, "Marginals", failing_first)
    with caplog.at_level("WARNING", logger="bimfactor.backend.posegraph"):
        fallback = _run_batch(sc, PRECISE)
    assert len(calls) == 2 and calls[1] < calls[0]  # the second, smaller graph: prior and odometry only
    np.testing.assert_allclose(fallback.poses, normal.poses)
    wider = np.trace(fallback.covariances[:, :2, :2], axis1=1, axis2=2) > np.trace(
        normal.covariances[:, :2, :2], axis1=1, axis2=2
    )
    assert wider[1:].all()  # the landmarks tighten every pose but the prior's
    assert "pose marginals failed" in caplog.text


def test_marginals_leave_out_a_bearing_whose_landmark_sits_on_the_pose():
    """A landmark parked on its pose (range 10 µm) makes the bearing's Jacobian explode and GTSAM's marginals
    indeterminate; without that one factor they exist, and the pose keeps a real (not collapsed) uncertainty."""
    cfg = BASE
    sc = loop_scenario(np.random.default_rng(0), cfg, WHEEL_ODOMETRY)
    landmarks = Landmarks.of(sc.landmark_xy)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(pose_prior_factor(0, sc.true_poses[0], FIRST_COV))
    for t, pose in enumerate(sc.true_poses):
        values.insert(X(t), gtsam.Pose2(*pose))
        if t:
            graph.add(odometry_factor(t, sc.increments[t - 1], cfg, WHEEL_ODOMETRY))
        for factor in landmark_factors(t, sc.observations[t], sc.associations[t], bearing_range_noise(cfg)):
            graph.add(factor)
    for j, xy in enumerate(sc.landmark_xy):
        graph.add(landmark_prior_factor(j, landmarks, cfg))
        values.insert(L(j), xy.copy())
    _, parked = sc.associations[5][0]
    values.update(L(parked), sc.true_poses[5, :2] + 1e-5)
    with pytest.raises(RuntimeError, match="Indetermina"):
        gtsam.Marginals(graph, values).marginalCovariance(X(5))
    kept = _without_degenerate_bearings(graph, values)
    assert kept.size() == graph.size() - 1
    covariance = gtsam.Marginals(kept, values).marginalCovariance(X(5))
    assert np.all(np.isfinite(covariance)) and np.linalg.eigvalsh(covariance)[0] > 1e-4


def test_a_scan_measurement_enters_the_mode_graph_with_its_keyframe_and_is_kept_apart():
    """`pose_factor_fn` measures each mode's keyframe pose from its prediction: a tight measurement at the truth
    pulls a mode born off the truth onto it, and the history keeps it as a scan factor, not a fine one."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, PRECISE, PRECISE_ODOMETRY)
    information = np.diag([1 / 0.01**2, 1 / 0.01**2, 1 / np.deg2rad(0.2) ** 2])
    asked = []

    def measure(pose, storey):
        asked.append(pose.copy())
        t = len(asked) - 1
        return (sc.true_poses[t], information) if t % 2 == 0 else None  # every other keyframe

    born_off = np.array([0.4, -0.3, np.deg2rad(8.0)])
    for t in range(5):
        clusters = [Mode(sc.true_poses[t] + born_off, np.diag([0.3, 0.3, np.deg2rad(10.0)]) ** 2, 1.0)]
        increment = None if t == 0 else sc.increments[t - 1]
        step = backend.step(clusters, increment, sc.observations[t], lambda p, s: [], None, measure)
    np.testing.assert_allclose(asked[0], sc.true_poses[0] + born_off)  # measured from the mode's own prediction
    history = backend.histories()[0]
    assert [i for i, _, _ in history.scan_factors] == [0, 2, 4] and history.pose_factors == []
    assert np.linalg.norm(step.pose[:2] - sc.true_poses[4, :2]) < 0.03
    assert abs(wrap_angle(step.pose[2] - sc.true_poses[4, 2])) < np.deg2rad(0.5)


@pytest.mark.parametrize("first_match", [1, 6])
def test_a_scan_match_beyond_the_window_starts_the_mode_graph_again_at_it(first_match: int):
    """A mode born 1.2 m off the truth: its scans are not matched before keyframe `first_match`, whose match lies
    beyond the ± `scan_factor.window_m` window about the prediction (the matcher searched again about the window's
    edge).
    The graph disagrees with the walls there, so it starts again at that match; matches inside the window then enter
    it as scan factors. The history before the restart is kept as a refine candidate when it is long enough
    (`refine_retired_min_keyframes`), as a pruned mode's is."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, PRECISE, PRECISE_ODOMETRY)
    information = np.diag([1 / 0.01**2, 1 / 0.01**2, 1 / np.deg2rad(0.2) ** 2])
    born_off = np.array([1.2, 0.0, np.deg2rad(5.0)])
    assert born_off[0] > PRECISE.scan_factor.window_m
    assert 1 < PRECISE.refine_retired_min_keyframes <= 6
    asked = []
    T = first_match + 4
    for t in range(T):
        clusters = [Mode(sc.true_poses[0] + born_off, np.diag([0.3, 0.3, np.deg2rad(10.0)]) ** 2, 1.0)]

        def measure(pose, storey, t=t):
            asked.append(pose - sc.true_poses[t])
            return None if t < first_match else (sc.true_poses[t], information)

        increment = None if t == 0 else sc.increments[t - 1]
        backend.step(clusters if t == 0 else [], increment, sc.observations[t], lambda p, s: [], None, measure)
    off = np.hypot(*np.array(asked)[:, :2].T)
    assert off[first_match] > 1.0 and np.all(off[first_match + 1 :] < 0.2)
    (history,) = backend.histories()
    assert history.first_index == first_match and len(history.poses) == T - first_match
    np.testing.assert_allclose(history.prior_pose, sc.true_poses[first_match])
    assert [i for i, _, _ in history.scan_factors] == list(range(first_match + 1, T))
    assert np.linalg.norm(history.poses[-1, :2] - sc.true_poses[T - 1, :2]) < 0.03
    if first_match < PRECISE.refine_retired_min_keyframes:
        assert backend.retired == []
    else:
        (before,) = backend.retired
        assert before.mode_id == history.mode_id and before.first_index == 0 and len(before.poses) == first_match
        assert np.all(np.hypot(*(before.poses[:, :2] - sc.true_poses[:first_match, :2]).T) > 0.5)  # as it was


def test_a_long_objects_landmark_gives_way_along_its_footprint():
    """A node on the near end of a 3 m table, 1.4 m from its centre, seen from six keyframes: as a point landmark
    the table drags the poses towards its centre; with its footprint in the landmark prior it barely does."""
    truth = np.array([[x, 0.0, 0.0] for x in np.arange(0.0, 3.0, 0.5)])
    seen = np.array([[6.6, 2.0]])  # the table's footprint: x 6.5–9.5, y 1.8–2.2

    def final_error(landmarks) -> float:
        graph = ModeGraph(0, 0, truth[0], np.diag([0.3, 0.3, np.deg2rad(5.0)]) ** 2, landmarks, BASE, WHEEL_ODOMETRY)
        for t, pose in enumerate(truth):
            d, alpha = polar_coordinates(pose, seen)
            obs = Observations(np.zeros((1, 4), np.float32), d, alpha, ["table"])
            graph.add_keyframe(t, obs, [(0, 0)], None if t == 0 else np.array([0.5, 0.0, 0.0]))
        return float(np.hypot(*(graph.pose[:2] - truth[-1, :2])))

    point = final_error(np.array([[8.0, 2.0]]))
    footprint = final_error(Landmarks(np.array([[8.0, 2.0]]), np.array([[3.0, 0.4]])))
    assert point > 0.5
    assert footprint < 0.25
