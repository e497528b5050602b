"""The paper's metrics (Eq. 5) and convergence, against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.symmetry import Motion
from bimfactor.evaluation.metrics import (
    ellipse_coverage,
    errors_up_to_twin,
    inside_ellipse,
    orientation_errors_deg,
    run_bootstrap_ci,
    steps_to_converge,
    trajectory_metrics,
    translation_errors_m,
)


def test_errors_per_step() -> None:
    truth = np.array([[0.0, 0.0, np.deg2rad(179.0)], [1.0, 1.0, 0.0]])
    estimate = np.array([[3.0, 4.0, np.deg2rad(-179.0)], [1.0, 1.0, np.deg2rad(10.0)]])
    np.testing.assert_allclose(translation_errors_m(estimate, truth), [5.0, 0.0])
    np.testing.assert_allclose(orientation_errors_deg(estimate, truth), [2.0, 10.0])  # wrapped across ±180°


@pytest.mark.parametrize(
    ("trans", "orient", "expected"),
    [
        ([5, 3, 0.5, 0.4, 0.2], [90, 40, 10, 5, 1], 2),
        ([0.5, 0.4], [1, 1], 0),
        ([0.5, 2.0, 0.5], [1, 1, 1], 2),
        ([0.5, 0.5, 2.0], [1, 1, 1], None),
        ([0.5, 0.5], [1, 20], None),
    ],
)
def test_steps_to_converge(trans: list, orient: list, expected: int | None) -> None:
    assert steps_to_converge(np.asarray(trans, float), np.asarray(orient, float)) == expected


def test_ellipse_coverage_counts_points_inside_the_95_percent_ellipse() -> None:
    cov = np.tile(np.diag([1.0, 1.0, 0.1]), (3, 1, 1))
    estimates = np.zeros((3, 3))
    truth = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [0.0, 2.4, 0.0]])  # m² = 2, 8, 5.76; χ²₂(0.95) = 5.99
    assert ellipse_coverage(estimates, cov, truth) == pytest.approx(2 / 3)
    np.testing.assert_array_equal(inside_ellipse(estimates, cov, truth), [True, False, True])
    np.testing.assert_array_equal(inside_ellipse(estimates, cov, truth, p=0.99), [True, True, True])  # χ²₂(0.99) = 9.21


def test_trajectory_metrics_mean_and_std_over_steps() -> None:
    truth = np.zeros((4, 3))
    estimates = np.array([[2.0, 0, 0], [0.5, 0, 0], [0.5, 0, 0], [0.0, 0, 0]])
    m = trajectory_metrics(
        estimates, truth, np.array([1, 2, 2, 2]), np.array([2, 2, 2, 2]), np.tile(np.eye(3), (4, 1, 1)), np.ones(4)
    )
    assert m.trans_err_m == pytest.approx(0.75) and m.trans_err_std_m == pytest.approx(np.std([2, 0.5, 0.5, 0]))
    assert m.room_acc == pytest.approx(0.75) and m.room_acc_std == pytest.approx(np.std([0, 1, 1, 1]))
    assert m.steps_to_converge == 1 and m.trans_err_conv_m == pytest.approx(1 / 3)
    assert m.step_ms_median == 1.0


def test_run_bootstrap_interval_resamples_whole_runs() -> None:
    same = [np.full(50, 0.3) for _ in range(6)]
    assert run_bootstrap_ci(same) == pytest.approx((0.3, 0.3))  # identical runs: no spread of the average
    # Nine settled runs and one locked onto a wrong place for its 50 steps: the interval is wide and asymmetric
    # about the pooled mean 1.17 m (a resample holds that run 0, 1, 2... times).
    runs = [np.full(50, 0.1) for _ in range(9)] + [np.full(50, 10.8)]
    lo, hi = run_bootstrap_ci(runs)
    pooled = np.concatenate(runs).mean()
    assert lo < pooled < hi and lo == pytest.approx(0.1) and hi > 2.0
    assert run_bootstrap_ci(runs) == (lo, hi)  # deterministic
    assert run_bootstrap_ci(runs, level=0.5)[1] < hi
    with pytest.raises(ValueError, match="at least one run"):
        run_bootstrap_ci([])


def test_errors_up_to_twin_score_the_nearer_of_the_truth_and_its_twin_on_twin_storeys_only() -> None:
    half_turn = Motion(np.pi, np.array([12.0, 4.0]), 10, 10)  # about (6, 2)
    truth = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.5], [1.0, 1.0, 0.0]])
    estimates = np.array(
        [
            [1.1, 1.0, 0.1],  # near the truth
            [11.0, 3.2, np.pi],  # on the twin: 0.2 m, facing as the twin does
            [9.0, 2.0, 0.5],  # between the two, nearer the twin (1.0 m off it, turned by π against it)
            [11.0, 3.0, np.pi],  # the twin's pose, but on a storey without a twin
        ]
    )
    storeys = np.array([1, 1, 1, 0])
    trans, orient = errors_up_to_twin(estimates, truth, storeys, {1: half_turn})
    assert trans == pytest.approx([0.1, 0.2, 1.0, np.hypot(10.0, 2.0)])
    assert orient == pytest.approx([np.rad2deg(0.1), 0.0, 180.0, 180.0])
    assert np.all(trans <= translation_errors_m(estimates, truth))
