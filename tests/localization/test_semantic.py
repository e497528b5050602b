"""The semantic term of the measurement model (the paper's, Eqs. 1-4): each score term against hand-computed
values, the assignment against brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from bimfactor.config import SmclConfig, updated
from bimfactor.localization.measurements.semantic import (
    SemanticLikelihood,
    assignment_sums,
    bearing_similarity,
    distance_similarity,
    likelihood_from_score,
    pair_score,
    polar_coordinates,
    semantic_similarity,
)
from bimfactor.types import Observations
from tests.localization.handmade import object_id, observe


def test_polar_coordinates_are_counter_clockwise_from_the_heading():
    pose = np.array([1.0, 2.0, np.pi / 2])  # at (1, 2), facing +y
    d, alpha = polar_coordinates(pose, np.array([[1.0, 5.0], [0.0, 2.0], [2.0, 2.0], [1.0, 0.0]]))
    np.testing.assert_allclose(d, [3.0, 1.0, 1.0, 2.0])
    np.testing.assert_allclose(alpha, [0.0, np.pi / 2, -np.pi / 2, -np.pi], atol=1e-12)  # ahead, left, right, behind


def test_semantic_similarity_is_the_cosine_of_unit_embeddings():
    a = np.array([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0]], np.float32)
    b = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    np.testing.assert_allclose(semantic_similarity(a, b), [[0.0, 1.0], [0.8, 0.6]], atol=1e-7)


def test_distance_and_bearing_terms():
    assert distance_similarity(3.0, 1.8, 1.2) == pytest.approx(np.exp(-1.0))
    assert distance_similarity(1.8, 3.0, 1.2) == pytest.approx(np.exp(-1.0))
    assert distance_similarity(2.0, 2.0, 1.2) == pytest.approx(1.0)
    assert bearing_similarity(np.pi / 2, 0.0, 5.0) == pytest.approx(np.exp(-5.0))
    assert bearing_similarity(np.pi, -np.pi, 5.0) == pytest.approx(1.0)  # the same direction across ±π
    assert bearing_similarity(0.3, 0.1, 5.0) == pytest.approx(np.exp(5.0 * (np.cos(0.2) - 1.0)))


def test_pair_score_is_the_product_and_screens_by_the_semantic_threshold(smcl_cfg: SmclConfig):
    expected = 0.9 * np.exp(-0.5 / 1.2) * np.exp(5.0 * (np.cos(0.2) - 1.0))
    semantic = smcl_cfg.semantic
    assert pair_score(0.9, 2.0, 1.5, 0.2, 0.0, semantic) == pytest.approx(expected)
    assert pair_score(semantic.threshold - 0.01, 2.0, 2.0, 0.0, 0.0, semantic) == 0.0


def test_likelihood_is_exp_score_over_temperature():
    assert likelihood_from_score(0.5, 0.25) == pytest.approx(np.exp(2.0))
    assert likelihood_from_score(0.0, 0.15) == pytest.approx(1.0)


def test_pair_scores_of_one_particle_match_hand_computed_values(box_prior, box_visibility, smcl_cfg):
    scorer = SemanticLikelihood(box_prior, box_visibility, updated(smcl_cfg.semantic, {"footprint_match": False}))
    particle = np.array([[4.0, 3.0, np.pi]])  # facing west: the chair is 1 m straight ahead
    obs = observe(("chair", 1.5, 0.2), ("cabinet", 3.0, -0.5))
    phi, ids = scorer.pair_scores(particle, np.array([0]), obs)
    chair, cabinet = object_id(box_prior, "chair"), object_id(box_prior, "cabinet")
    assert set(ids[0][ids[0] >= 0]) == {chair, cabinet}
    col = {int(i): c for c, i in enumerate(ids[0]) if i >= 0}
    cab_d, cab_a = np.hypot(3.0, 2.0), np.arctan2(2.0, -3.0) - np.pi  # cabinet at (1, 5)
    expected_chair = np.exp(-0.5 / 1.2) * np.exp(5.0 * (np.cos(0.2) - 1.0))
    expected_cabinet = np.exp(-abs(3.0 - cab_d) / 1.2) * np.exp(5.0 * (np.cos(-0.5 - cab_a) - 1.0))
    assert phi[0, 0, col[chair]] == pytest.approx(expected_chair, rel=1e-6)
    assert phi[0, 1, col[cabinet]] == pytest.approx(expected_cabinet, rel=1e-6)
    assert phi[0, 0, col[cabinet]] == 0.0 and phi[0, 1, col[chair]] == 0.0  # different labels: screened out
    score = scorer.scores(particle, np.array([0]), obs)
    assert score[0] == pytest.approx((expected_chair + expected_cabinet) / 2, rel=1e-6)


def test_an_unmatched_observation_counts_zero_in_the_mean(box_prior, box_visibility, smcl_cfg):
    scorer = SemanticLikelihood(box_prior, box_visibility, smcl_cfg.semantic)
    particle = np.array([[4.0, 3.0, np.pi]])
    exact = observe(("chair", 1.0, 0.0))
    with_unexplained = observe(("chair", 1.0, 0.0), ("table", 2.0, 0.0))  # the table is behind the wall
    assert scorer.scores(particle, np.array([0]), exact)[0] == pytest.approx(1.0)
    assert scorer.scores(particle, np.array([0]), with_unexplained)[0] == pytest.approx(0.5)


def test_the_count_exponent_scales_the_mean_score_from_the_papers_mean_to_the_sum(box_prior, box_visibility, smcl_cfg):
    particle, storey = np.array([[4.0, 3.0, np.pi]]), np.array([0])
    # Facing west from (4, 3): the chair 1 m ahead, the cabinet at (1, 5) √13 m away and 33.7° to the right.
    both = observe(("chair", 1.0, 0.0), ("cabinet", np.sqrt(13.0), np.arctan2(2.0, -3.0) - np.pi))
    half = observe(("chair", 1.0, 0.0), ("table", 2.0, 0.0))  # the table is behind the wall: scores 0
    for gamma, scale in ((1.0, 1.0), (0.5, np.sqrt(2.0)), (0.0, 2.0)):
        cfg = updated(smcl_cfg.semantic, {"count_exponent": gamma})
        scorer = SemanticLikelihood(box_prior, box_visibility, cfg)
        assert scorer.scores(particle, storey, both)[0] == pytest.approx(1.0, abs=1e-3)  # the mean, whatever γ
        assert scorer.count_scale(2) == pytest.approx(scale)
        np.testing.assert_allclose(scorer.log_likelihood(particle, storey, both), scale / cfg.temperature, rtol=1e-3)
        np.testing.assert_allclose(scorer.log_likelihood(particle, storey, half), scale * 0.5 / cfg.temperature)
        assert scorer.count_scale(1) == 1.0  # one observation weighs the same either way


def test_candidates_outside_the_field_of_view_do_not_score(box_prior, box_visibility, smcl_cfg):
    scorer = SemanticLikelihood(box_prior, box_visibility, smcl_cfg.semantic)
    facing_east = np.array([[4.0, 3.0, 0.0]])  # the chair is behind the robot
    assert scorer.scores(facing_east, np.array([0]), observe(("chair", 1.0, 0.0)))[0] == 0.0


def test_no_observations_score_zero_for_every_particle(box_prior, box_visibility, smcl_cfg):
    scorer = SemanticLikelihood(box_prior, box_visibility, smcl_cfg.semantic)
    empty = Observations(np.zeros((0, 5), np.float32), np.zeros(0), np.zeros(0))
    np.testing.assert_array_equal(scorer.scores(np.zeros((4, 3)), np.zeros(4, int), empty), np.zeros(4))


def brute_force(phi: np.ndarray) -> float:
    """Best sum over every one-to-one assignment of a (K, C) matrix (rows or columns may stay unmatched)."""
    K, C = phi.shape
    if K <= C:
        return max(sum(phi[k, cols[k]] for k in range(K)) for cols in itertools.permutations(range(C), K))
    return max(sum(phi[rows[c], c] for c in range(C)) for rows in itertools.permutations(range(K), C))


@pytest.mark.parametrize("seed", range(6))
def test_assignment_equals_brute_force_on_random_small_cases(seed: int):
    rng = np.random.default_rng(seed)
    for _ in range(60):
        K, C = (int(v) for v in rng.integers(1, 6, 2))
        density = rng.uniform(0.15, 1.0)
        phi = rng.random((25, K, C)) * (rng.random((25, K, C)) < density)
        if rng.random() < 0.3:
            phi = np.round(phi * 3) / 3  # ties
        totals, _ = assignment_sums(phi.astype(np.float32))
        expected = [brute_force(p.astype(np.float32).astype(np.float64)) for p in phi]
        np.testing.assert_allclose(totals, expected, rtol=1e-6, atol=1e-6)


def test_assignment_shortcuts_and_solver_paths():
    distinct = np.array([[[0.9, 0.1], [0.2, 0.8]]])  # row maxima in different columns: no solver call
    totals, calls = assignment_sums(distinct)
    assert totals[0] == pytest.approx(1.7) and calls == 0
    contested = np.array([[[0.9, 0.8, 0.0], [0.85, 0.1, 0.0], [0.7, 0.6, 0.5]]])  # 3 × 3: Hungarian solver
    totals, calls = assignment_sums(contested)
    assert totals[0] == pytest.approx(brute_force(contested[0])) and calls == 1
    one_column = np.array([[[0.4], [0.6], [0.0]]])
    assert assignment_sums(one_column)[0][0] == pytest.approx(0.6)


def test_a_partly_seen_object_is_a_candidate_at_the_edge_of_the_view(box_prior, box_visibility, smcl_cfg):
    # The table (1.2 × 0.8 m, centre (9, 3)) seen from (8.2, 2.2) facing north: its centre is 45° + 0.5° to the
    # right, outside the 90° FOV, but most of its footprint is inside.
    particle = np.array([[8.2, 2.2, np.deg2rad(90.5)]])
    obs = observe(("table", 1.1, -np.deg2rad(40.0)))
    paper = updated(smcl_cfg.semantic, {"footprint_match": False})
    centre_only = SemanticLikelihood(box_prior, box_visibility, updated(paper, {"fov_extent": False}))
    assert centre_only.scores(particle, np.array([0]), obs)[0] == 0.0
    extent = SemanticLikelihood(box_prior, box_visibility, paper)
    d = np.hypot(0.8, 0.8)
    # The expected bearing is the centre's clipped to the FOV edge (−45°).
    expected = np.exp(-abs(1.1 - d) / 1.2) * np.exp(5.0 * (np.cos(np.deg2rad(5.0)) - 1.0))
    assert extent.scores(particle, np.array([0]), obs)[0] == pytest.approx(expected, rel=1e-5)


def test_footprint_match_expects_a_node_at_the_nearest_point_of_its_object(box_prior, box_visibility, smcl_cfg):
    # The table's footprint is x 8.4–9.6, y 2.6–3.4. From (6, 3) facing east its centre is 3 m ahead.
    cfg = updated(smcl_cfg.semantic, {"similarity": "cosine"})  # one-hot embeddings: φ_sem = 1 for the label
    particle = np.array([[6.0, 3.0, 0.0]])
    on_near_end = observe(("table", 2.6, 0.0))  # (8.6, 3): on the footprint, 0.4 m from its near edge
    beyond = observe(("table", 1.9, 0.0))  # (7.9, 3): 0.5 m short of the near edge (8.4, 3)
    footprint = SemanticLikelihood(box_prior, box_visibility, cfg)
    centre = SemanticLikelihood(box_prior, box_visibility, updated(cfg, {"footprint_match": False}))
    assert footprint.scores(particle, np.array([0]), on_near_end)[0] == pytest.approx(1.0)
    assert centre.scores(particle, np.array([0]), on_near_end)[0] == pytest.approx(np.exp(-0.4 / 1.2))
    assert footprint.scores(particle, np.array([0]), beyond)[0] == pytest.approx(np.exp(-0.5 / 1.2))
    # Off the axis: the nearest footprint point of (8.0, 3.9) is the corner (8.4, 3.4), at its own bearing.
    obs = observe(("table", np.hypot(2.0, 0.9), np.arctan2(0.9, 2.0)))
    d, a = np.hypot(2.4, 0.4), np.arctan2(0.4, 2.4)
    expected = np.exp(-abs(np.hypot(2.0, 0.9) - d) / 1.2) * np.exp(5.0 * (np.cos(np.arctan2(0.9, 2.0) - a) - 1.0))
    assert footprint.scores(particle, np.array([0]), obs)[0] == pytest.approx(expected, rel=1e-6)


def test_softmax_semantic_term_is_the_class_probability_over_the_prior_labels(
    box_prior, box_visibility, smcl_cfg, fixed_value
):
    fixed_value("smcl.semantic.softmax_temperature", 0.5)
    cfg = updated(smcl_cfg.semantic, {"similarity": "softmax"})
    scorer = SemanticLikelihood(box_prior, box_visibility, cfg)
    mixed = np.array([[0.8, 0.6, 0.0, 0.0, 0.0]], np.float32)  # 0.8 chair + 0.6 table in the one-hot label space
    obs = Observations(mixed, np.array([1.0]), np.array([0.0]), labels=["chair"])
    sem = scorer.semantic(obs)[0]
    logits = np.array([0.8, 0.6, 0.0, 0.0, 0.0]) / 0.5  # chair, table, window, cabinet, bookshelf
    p = np.exp(logits) / np.exp(logits).sum()
    assert sem[object_id(box_prior, "chair")] == pytest.approx(p[0], rel=1e-5)
    assert sem[object_id(box_prior, "table")] == pytest.approx(p[1], rel=1e-5)
    assert sem[object_id(box_prior, "bookshelf")] == pytest.approx(p[4], rel=1e-5)
    cosine_cfg = updated(smcl_cfg.semantic, {"similarity": "cosine"})
    cosine = SemanticLikelihood(box_prior, box_visibility, cosine_cfg).semantic(obs)[0]
    assert cosine[object_id(box_prior, "chair")] == pytest.approx(0.8)
