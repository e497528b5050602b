"""Twin places: rigid motions that carry a storey's objects onto others of their label."""

from __future__ import annotations

import numpy as np

from bimfactor.bim.symmetry import Motion, _rotation, symmetries


def test_building_symmetry_finds_the_half_turn_between_twin_flats_and_none_in_an_irregular_layout() -> None:
    flat = np.array([[1.0, 1.0], [3.0, 1.5], [2.0, 4.0], [0.5, 3.0], [3.5, 3.5]])
    labels = ["bed", "table", "sofa", "chair", "chair"]
    centre = np.array([6.0, 2.0])
    twin = 2 * centre - flat  # the second flat: the first turned by 180° about `centre`
    points = np.vstack([flat, twin, [[12.0, 9.0]]])  # and one object only one flat has
    best = symmetries(points, labels + labels + ["plant"])[0]
    assert abs(abs(best.theta_rad) - np.pi) < np.deg2rad(1.0)
    fixed = np.linalg.solve(np.eye(2) - _rotation(best.theta_rad), best.translation)
    assert np.allclose(fixed, centre, atol=0.05)
    assert best.matched == 10 and best.total == 11
    assert "rotation by 180° about (6.00, 2.00) m: 10 of 11 objects" in best.describe()

    # The twin flat built 5 cm off here and there: the two-object hypotheses' angles are off by degrees, the
    # refit to every matched pair is not.
    rng = np.random.default_rng(0)
    noisy = np.vstack([flat, twin + rng.uniform(-0.05, 0.05, twin.shape), [[12.0, 9.0]]])
    refit = symmetries(noisy, labels + labels + ["plant"])[0]
    assert abs(abs(refit.theta_rad) - np.pi) < np.deg2rad(0.15)  # the best pair alone: 0.27°
    assert refit.matched == 10

    irregular = symmetries(flat, labels)
    assert all(motion.matched <= 2 for motion in irregular)  # at most the two chairs swap


def test_a_motion_carries_poses_to_their_twins_and_turns_their_heading() -> None:
    half_turn = Motion(np.pi, np.array([12.0, 4.0]), 10, 11)  # about (6, 2)
    twins = half_turn.apply(np.array([[1.0, 1.0, 0.0], [6.0, 2.0, 3.0]]))
    assert np.allclose(twins[:, :2], [[11.0, 3.0], [6.0, 2.0]])
    assert np.allclose(np.cos(twins[:, 2]), np.cos([np.pi, 3.0 + np.pi]))
    assert np.all(np.abs(twins[:, 2]) <= np.pi)
