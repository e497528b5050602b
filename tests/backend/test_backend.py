"""The multi-hypothesis back end over particle-filter modes: the true mode wins, a wrong one is pruned, modes merge."""

import numpy as np
import pytest

from bimfactor.backend.posegraph import ModeGraph, MultiHypothesisBackend, semantic_associator
from bimfactor.backend.synthetic import PRECISE_ODOMETRY, loop_scenario, nearest_landmark_associator
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import load_config
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.modes import Mode
from bimfactor.types import Observations, wrap_angle
from tests.localization.handmade import embedding, make_prior, object_id

# The sensor, odometry and BIM the tolerances below are set for: σ_r 15 cm, σ_b 3°, odometry σ 5 % of the motion,
# BIM σ 10 cm (the loop scenario draws its noise from them; the odometry is PRECISE_ODOMETRY).
CFG = load_config().backend.model_copy(
    update={
        "range_sigma_m": 0.15,
        "bearing_sigma_deg": 3.0,
        "landmark_sigma_m": 0.1,
    }
)
CLUSTER_COV = np.diag([0.2, 0.2, np.deg2rad(5.0)]) ** 2
GATE_M = 1.0


def _nearest_landmark_associator(landmark_xy: np.ndarray, observations: Observations):
    """Each observation → the BIM landmark nearest to where the pose puts it, within GATE_M."""
    return nearest_landmark_associator(landmark_xy, observations, GATE_M)


def _rotate_about_origin(pose: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * pose[0] - s * pose[1], s * pose[0] + c * pose[1], wrap_angle(pose[2] + angle)])


def test_the_true_mode_wins_and_a_wrong_mode_is_pruned():
    sc = loop_scenario(np.random.default_rng(0), CFG, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, CFG, PRECISE_ODOMETRY)
    wrong_rotation = np.pi / 3  # maps the landmark ring's inner landmarks onto outer ones: nothing fits
    pruned, best_ids = [], []
    for t in range(len(sc.true_poses)):
        clusters = [
            Mode(sc.true_poses[t], CLUSTER_COV, 0.5),
            Mode(_rotate_about_origin(sc.true_poses[t], wrong_rotation), CLUSTER_COV, 0.5),
        ]
        increment = None if t == 0 else sc.increments[t - 1]
        step = backend.step(
            clusters, increment, sc.observations[t], _nearest_landmark_associator(sc.landmark_xy, sc.observations[t])
        )
        pruned += step.pruned
        best_ids.append(step.best.mode_id)
        assert np.linalg.norm(step.pose[:2] - sc.true_poses[t, :2]) < 0.3
        assert abs(wrap_angle(step.pose[2] - sc.true_poses[t, 2])) < np.deg2rad(5.0)
        assert step.best.normalised_residual < 2.0
    assert best_ids == [0] * len(sc.true_poses)
    assert 1 in pruned
    # The wrong cluster keeps arriving, spawns again and is pruned again: never more than the true mode survives.
    assert [m.mode_id for m in step.modes] == [0]
    assert step.best.probability == pytest.approx(1.0)


def test_modes_whose_graphs_converge_are_merged():
    sc = loop_scenario(np.random.default_rng(1), CFG, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, CFG, PRECISE_ODOMETRY)
    offset = np.array([0.6, 0.0, 0.0])  # beyond merge_distance_m: the clusters are distinct at first
    assert offset[0] > CFG.merge_distance_m
    merged = []
    for t in range(3):
        clusters = [Mode(sc.true_poses[t], CLUSTER_COV, 0.6), Mode(sc.true_poses[t] + offset, CLUSTER_COV, 0.4)]
        increment = None if t == 0 else sc.increments[t - 1]
        step = backend.step(
            clusters, increment, sc.observations[t], _nearest_landmark_associator(sc.landmark_xy, sc.observations[t])
        )
        merged += step.merged
    assert merged and merged[0] == (0, 1)
    assert len(backend.graphs) == 1


def test_semantic_associator_reuses_the_smcl_score():
    prior = make_prior()
    cfg = load_config()
    smcl_cfg = cfg.smcl
    visibility = VisibilityTable.build(prior, cfg.bim.visibility, progress=False)
    likelihood = SemanticLikelihood(prior, visibility, smcl_cfg.semantic)
    pose = np.array([3.0, 1.5, np.pi / 2])  # in room A, facing the chair at (3, 3)
    observations = Observations(
        np.stack([embedding("chair"), embedding("table")]).astype(np.float32),
        np.array([1.5, 2.0]),
        np.array([0.0, 0.3]),
        labels=["chair", "table"],
    )
    associate = semantic_associator(likelihood, PlateLikelihood(prior, smcl_cfg), observations)
    # The table is in the other room, behind the wall: only the chair is matched.
    assert associate(pose, 0) == [(0, object_id(prior, "chair"))]


def test_a_mode_whose_graph_fails_restarts_from_its_cluster_and_the_run_goes_on(monkeypatch, caplog):
    """GTSAM raising inside one mode's update (an indeterminate system) restarts that mode's graph from its particle
    cluster at the keyframe, with a warning; the mode keeps its id and the estimate stays on the truth."""
    sc = loop_scenario(np.random.default_rng(0), CFG, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, CFG, PRECISE_ODOMETRY)
    real_add_keyframe, failing_step = ModeGraph.add_keyframe, 8

    def add_keyframe(self, i, *args, **kwargs):
        if i == failing_step and self.first_index < failing_step:
            raise RuntimeError("\nIndeterminant linear system detected while working near variable x8.")
        return real_add_keyframe(self, i, *args, **kwargs)

    monkeypatch.setattr(ModeGraph, "add_keyframe", add_keyframe)
    with caplog.at_level("WARNING", logger="bimfactor.backend.posegraph"):
        for t in range(len(sc.true_poses)):
            increment = None if t == 0 else sc.increments[t - 1]
            associate = _nearest_landmark_associator(sc.landmark_xy, sc.observations[t])
            step = backend.step([Mode(sc.true_poses[t], CLUSTER_COV, 1.0)], increment, sc.observations[t], associate)
            assert step.best.mode_id == 0
            assert np.linalg.norm(step.pose[:2] - sc.true_poses[t, :2]) < 0.3
    assert "mode 0: its pose graph failed at keyframe 8 (Indeterminant" in caplog.text
    assert "restarted from its particle cluster" in caplog.text
    assert backend.graphs[0].first_index == failing_step
    assert sorted(backend.graphs[0].poses) == list(range(failing_step, len(sc.true_poses)))


def test_a_fine_registration_that_breaks_a_graph_restarts_it_with_the_fit(monkeypatch, caplog):
    """GTSAM raising on an ICP pose factor restarts that mode's graph at the keyframe, with the fit in it."""
    sc = loop_scenario(np.random.default_rng(0), CFG, PRECISE_ODOMETRY)
    backend = MultiHypothesisBackend(sc.landmark_xy, CFG, PRECISE_ODOMETRY)
    for t in range(6):
        increment = None if t == 0 else sc.increments[t - 1]
        associate = _nearest_landmark_associator(sc.landmark_xy, sc.observations[t])
        backend.step([Mode(sc.true_poses[t], CLUSTER_COV, 1.0)], increment, sc.observations[t], associate)
    real_add_pose_factor, broken = ModeGraph.add_pose_factor, backend.graphs[0]

    def add_pose_factor(self, *args, **kwargs):
        if self is broken:
            raise RuntimeError("\nIndeterminant linear system detected while working near variable x5.")
        return real_add_pose_factor(self, *args, **kwargs)

    monkeypatch.setattr(ModeGraph, "add_pose_factor", add_pose_factor)
    fit = sc.true_poses[5] + np.array([0.05, -0.03, 0.01])
    with caplog.at_level("WARNING", logger="bimfactor.backend.posegraph"):
        pose, covariance = backend.add_pose_factor(0, 5, fit, np.diag([1e4, 1e4, 1e4]))
    assert "mode 0: its pose graph failed at keyframe 5 (Indeterminant" in caplog.text
    assert "restarted at it, on a fine registration" in caplog.text
    graph = backend.graphs[0]
    assert graph is not broken and graph.first_index == 5 and graph.pose_factors[0][0] == 5
    np.testing.assert_allclose(pose, fit, atol=0.02)  # the tight fit holds the restarted graph
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    # The run goes on from the restarted graph.
    associate = _nearest_landmark_associator(sc.landmark_xy, sc.observations[6])
    step = backend.step([Mode(sc.true_poses[6], CLUSTER_COV, 1.0)], sc.increments[5], sc.observations[6], associate)
    assert step.best.mode_id == 0 and np.linalg.norm(step.pose[:2] - sc.true_poses[6, :2]) < 0.3
