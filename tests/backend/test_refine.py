"""Offline refinement on the synthetic loop: a late mode smoothed over the whole sequence, hindsight re-association."""

import numpy as np
import pytest

from bimfactor.backend.posegraph import ModeGraph, ModeHistory, batch_refine, dead_reckoning
from bimfactor.backend.refine import refine_mode
from bimfactor.backend.synthetic import PRECISE_ODOMETRY, LoopScenario, loop_scenario, nearest_landmark_associator
from bimfactor.config import load_config
from bimfactor.types import se2_between, wrap_angle

# A precise sensor, odometry (PRECISE_ODOMETRY) and BIM (σ_r 5 cm, σ_b 1°, BIM σ 2 cm; truth = BIM), as in the
# pose-graph tests.
PRECISE = load_config().backend.model_copy(
    update={
        "range_sigma_m": 0.05,
        "bearing_sigma_deg": 1.0,
        "landmark_sigma_m": 0.02,
        "odom_robust_kernel": "none",  # its noise is the model's own, without slips
    }
)
BIRTH_COV = np.diag([0.3, 0.3, np.deg2rad(10.0)]) ** 2
BIRTH_OFFSET = np.array([0.25, -0.2, np.deg2rad(6.0)])  # the cluster mean a mode is born at is off the truth
BORN_AT = 8
WRONG_STEP = 14


def _rms_m(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(((poses[:, :2] - truth[:, :2]) ** 2).sum(axis=1).mean()))


def _late_mode(sc: LoopScenario, cfg, associations=None, until: int | None = None) -> ModeHistory:
    """A mode born at keyframe BORN_AT (off the truth) and run online to the end of the loop (or pruned at
    keyframe `until`)."""
    associations = sc.associations if associations is None else associations
    graph = ModeGraph(
        3, BORN_AT, sc.true_poses[BORN_AT] + BIRTH_OFFSET, BIRTH_COV, sc.landmark_xy, cfg, PRECISE_ODOMETRY
    )
    for t in range(BORN_AT, len(sc.true_poses) if until is None else until):
        graph.add_keyframe(t, sc.observations[t], associations[t], None if t == BORN_AT else sc.increments[t - 1])
    return graph.history(probability=0.8)


def _associators(sc: LoopScenario) -> list:
    return [nearest_landmark_associator(sc.landmark_xy, obs) for obs in sc.observations]


def test_dead_reckoning_chains_forwards_and_backwards_from_the_anchor():
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    anchor = np.array([1.0, -2.0, 0.4])
    poses = dead_reckoning(anchor, 5, sc.increments)
    assert poses.shape == (len(sc.true_poses), 3)
    np.testing.assert_allclose(poses[5], anchor)
    steps = se2_between(poses[:-1], poses[1:])
    steps[:, 2] = wrap_angle(steps[:, 2] - sc.increments[:, 2])
    np.testing.assert_allclose(steps[:, :2], sc.increments[:, :2], atol=1e-9)
    np.testing.assert_allclose(steps[:, 2], 0.0, atol=1e-9)


def test_batch_refine_takes_its_prior_on_any_keyframe():
    sc = loop_scenario(np.random.default_rng(1), PRECISE, PRECISE_ODOMETRY)
    result = batch_refine(
        sc.true_poses[10], BIRTH_COV, sc.increments, sc.observations, sc.associations, sc.landmark_xy,
        PRECISE, PRECISE_ODOMETRY, prior_index=10,
    )  # fmt: skip
    assert _rms_m(result.poses, sc.true_poses) < 0.05
    with pytest.raises(ValueError, match="outside"):
        batch_refine(
            sc.true_poses[0], BIRTH_COV, sc.increments, sc.observations, sc.associations, sc.landmark_xy,
            PRECISE, PRECISE_ODOMETRY, prior_index=len(sc.true_poses),
        )  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_late_mode_is_smoothed_over_the_whole_sequence(seed):
    sc = loop_scenario(np.random.default_rng(seed), PRECISE, PRECISE_ODOMETRY)
    mode = _late_mode(sc, PRECISE)
    assert len(mode.poses) == len(sc.true_poses) - BORN_AT
    refined = refine_mode(
        mode, sc.increments, sc.observations, _associators(sc), sc.landmark_xy, PRECISE, PRECISE_ODOMETRY
    )
    assert refined.poses.shape == (len(sc.true_poses), 3)
    assert (refined.mode_id, refined.first_index, refined.probability) == (3, BORN_AT, 0.8)
    # The keyframes before the mode existed are placed by hindsight, as well as the ones after.
    assert _rms_m(refined.poses[:BORN_AT], sc.true_poses[:BORN_AT]) < 0.05
    assert _rms_m(refined.poses, sc.true_poses) < 0.05
    # From the birth on, the same evidence as the online graph's plus the keyframes before: as good, within 5 %.
    assert _rms_m(refined.poses[BORN_AT:], sc.true_poses[BORN_AT:]) <= 1.05 * _rms_m(
        mode.poses, sc.true_poses[BORN_AT:]
    )
    assert refined.batch.error_after <= refined.batch.error_before
    assert np.all(np.linalg.eigvalsh(refined.covariances) > 0)
    # Keyframes before the birth got their matches from the associator: the true ones here.
    assert [set(a) for a in refined.associations[:BORN_AT]] == [set(a) for a in sc.associations[:BORN_AT]]


def test_hindsight_reassociation_replaces_a_wrong_match():
    sc = loop_scenario(np.random.default_rng(1), PRECISE, PRECISE_ODOMETRY)
    plain = PRECISE.model_copy(update={"robust_kernel": "none"})  # the wrong match drags an unprotected graph
    wrong = [list(a) for a in sc.associations]
    k, true_j = wrong[WRONG_STEP][0]
    gaps = np.linalg.norm(sc.landmark_xy - sc.landmark_xy[true_j], axis=1)
    gaps[true_j] = np.inf
    wrong_j = int(np.argmin(gaps))  # the nearest other landmark
    wrong[WRONG_STEP][0] = (k, wrong_j)
    mode = _late_mode(sc, plain, wrong)
    args = (mode, sc.increments, sc.observations, _associators(sc), sc.landmark_xy)
    dragged = refine_mode(*args, plain.model_copy(update={"refine_rounds": 0}), PRECISE_ODOMETRY)
    fixed = refine_mode(*args, plain.model_copy(update={"refine_rounds": 2}), PRECISE_ODOMETRY)
    assert (k, wrong_j) in dragged.associations[WRONG_STEP]
    assert fixed.rounds >= 1
    assert set(fixed.associations[WRONG_STEP]) == set(sc.associations[WRONG_STEP])
    assert _rms_m(fixed.poses, sc.true_poses) < 0.05 < _rms_m(dragged.poses, sc.true_poses)


def test_a_mode_longer_than_the_sequence_is_refused():
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    mode = _late_mode(sc, PRECISE)
    with pytest.raises(ValueError, match="do not lie in"):
        refine_mode(
            mode,
            sc.increments[:-1],
            sc.observations[:-1],
            _associators(sc)[:-1],
            sc.landmark_xy,
            PRECISE,
            PRECISE_ODOMETRY,
        )


def test_scans_are_matched_anew_from_the_hindsight_trajectory_before_the_birth_too():
    """With a scan matcher per keyframe, every keyframe (also before the mode's birth) gets a scan factor measured
    from the refined trajectory, and those factors replace the forward pass's."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    mode = _late_mode(sc, PRECISE)
    mode.scan_factors = [(BORN_AT, sc.true_poses[BORN_AT] + np.array([5.0, 0.0, 0.0]), np.eye(3) * 1e6)]  # ignored
    information = np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / np.deg2rad(0.1) ** 2])
    asked: dict[int, int] = {}

    def matcher(t: int):
        def measure(pose, storey):
            asked[t] = asked.get(t, 0) + 1
            assert np.linalg.norm(pose[:2] - sc.true_poses[t, :2]) < 1.0  # from the hindsight guess, not far off
            return sc.true_poses[t], information

        return measure

    cfg = PRECISE.model_copy(update={"refine_rounds": 1})
    refined = refine_mode(
        mode,
        sc.increments,
        sc.observations,
        _associators(sc),
        sc.landmark_xy,
        cfg,
        PRECISE_ODOMETRY,
        [matcher(t) for t in range(20)],
    )
    assert sorted(asked) == list(range(len(sc.true_poses)))
    # The first optimisation and one re-matching round; before the birth also the backward tracking.
    assert all(n == (3 if t < BORN_AT else 2) for t, n in asked.items())
    assert _rms_m(refined.poses, sc.true_poses) < 0.01
    without_scans = refine_mode(
        mode, sc.increments, sc.observations, _associators(sc), sc.landmark_xy, cfg, PRECISE_ODOMETRY
    )
    assert _rms_m(without_scans.poses, sc.true_poses) > 1.0  # the forward pass's (wrong) scan factor is used


def test_keyframes_before_the_birth_are_tracked_backwards_through_their_scans():
    """Odometry that turns 4° too far per keyframe puts dead reckoning back from the birth metres off; tracked
    backwards, each keyframe's scan is matched from its predecessor's correction and every match lands."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    mode = _late_mode(sc, PRECISE)
    drifting = sc.increments.copy()
    drifting[:, 2] += np.deg2rad(4.0)
    information = np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / np.deg2rad(0.1) ** 2])
    window_m, window_rad = 0.5, np.deg2rad(18.0)  # the correlative matcher's search window

    def matcher(t: int):
        def measure(pose, storey):
            off = pose - sc.true_poses[t]
            if np.hypot(*off[:2]) > window_m or abs(wrap_angle(off[2])) > window_rad:
                return None
            return sc.true_poses[t], information

        return measure

    dead_reckoned = dead_reckoning(mode.poses[0], BORN_AT, drifting)
    assert _rms_m(dead_reckoned[:BORN_AT], sc.true_poses[:BORN_AT]) > 1.0
    unmatched = [lambda pose, storey: [] for _ in range(20)]  # no landmark to pull the early keyframes back
    refined = refine_mode(
        mode,
        drifting,
        sc.observations,
        unmatched,
        sc.landmark_xy,
        PRECISE,
        PRECISE_ODOMETRY,
        [matcher(t) for t in range(20)],
    )
    assert _rms_m(refined.poses[:BORN_AT], sc.true_poses[:BORN_AT]) < 0.05


def test_a_mode_pruned_early_is_tracked_forwards_to_the_end_through_its_scans():
    """A mode pruned at keyframe 14 is a refine candidate too: the keyframes after it are predicted by odometry that
    turns 4° too far per keyframe and corrected by their scans' matches, then the whole sequence is smoothed."""
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    pruned_at = 14
    mode = _late_mode(sc, PRECISE, until=pruned_at)
    assert mode.first_index + len(mode.poses) == pruned_at
    T = len(sc.true_poses)
    drifting = sc.increments.copy()
    drifting[:, 2] += np.deg2rad(4.0)
    information = np.diag([1 / 0.005**2, 1 / 0.005**2, 1 / np.deg2rad(0.1) ** 2])

    def matcher(t: int):
        def measure(pose, storey):
            off = pose - sc.true_poses[t]
            if np.hypot(*off[:2]) > 0.5 or abs(wrap_angle(off[2])) > np.deg2rad(18.0):
                return None
            return sc.true_poses[t], information

        return measure

    assert _rms_m(dead_reckoning(mode.poses[-1], pruned_at - 1, drifting)[pruned_at:], sc.true_poses[pruned_at:]) > 0.5
    unmatched = [lambda pose, storey: [] for _ in range(T)]
    refined = refine_mode(
        mode,
        drifting,
        sc.observations,
        unmatched,
        sc.landmark_xy,
        PRECISE,
        PRECISE_ODOMETRY,
        [matcher(t) for t in range(T)],
    )
    assert refined.poses.shape == (T, 3)
    assert _rms_m(refined.poses[pruned_at:], sc.true_poses[pruned_at:]) < 0.05
    assert _rms_m(refined.poses, sc.true_poses) < 0.05
    # Scans that all see the same walls share the map's error: no keyframe is reported tighter than it.
    map_variance = PRECISE.scan_factor.min_sigma_m**2
    assert np.all(refined.covariances[:, 0, 0] > map_variance) and np.all(refined.covariances[:, 1, 1] > map_variance)
    without_scans = refine_mode(
        mode, sc.increments, sc.observations, _associators(sc), sc.landmark_xy, PRECISE, PRECISE_ODOMETRY
    )
    assert np.any(without_scans.covariances[:, 0, 0] < map_variance)


def test_a_mode_within_a_stretch_counts_its_keyframes_from_the_stretch_and_ends_with_it():
    sc = loop_scenario(np.random.default_rng(0), PRECISE, PRECISE_ODOMETRY)
    mode = _late_mode(sc, PRECISE)
    pose = sc.true_poses[12]
    last = len(sc.true_poses) - 1
    mode.scan_factors = [(10, pose, np.eye(3)), (last, pose, np.eye(3))]
    stretch = mode.within(range(5, 15))
    assert stretch.first_index == BORN_AT - 5 and len(stretch.poses) == 15 - BORN_AT
    np.testing.assert_array_equal(stretch.poses, mode.poses[: 15 - BORN_AT])
    assert stretch.associations == mode.associations[: 15 - BORN_AT]
    assert [t for t, *_ in stretch.scan_factors] == [10 - 5]  # the last keyframe lies past the stretch
    whole = mode.within(range(0, len(sc.true_poses)))  # the whole run: the mode as it is
    assert whole.first_index == BORN_AT and len(whole.scan_factors) == 2
    np.testing.assert_array_equal(whole.poses, mode.poses)
    with pytest.raises(ValueError, match="born at keyframe 8"):
        mode.within(range(9, 20))
