"""The paper benchmark's report: the average row and its bootstrap interval over runs."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.evaluation.paper import RunResult, _confidence_intervals, _pooled, format_table_one


def _run(trajectory: int, repeat: int, trans: float, room: float) -> RunResult:
    steps = 10
    return RunResult(
        "smcl",
        trajectory,
        repeat,
        np.full(steps, trans),
        np.full(steps, 10 * trans),
        np.full(steps, room),
        np.ones(steps, bool),
        np.ones(steps),
        {"steps_to_converge": 0, "trans_err_conv_m": trans, "orient_err_conv_deg": 10 * trans},
    )


def test_the_average_carries_a_bootstrap_interval_over_runs_and_the_table_prints_it() -> None:
    runs = [_run(k, r, 0.2, 1.0) for k in range(3) for r in range(2)] + [_run(3, 0, 6.2, 0.0)]
    average = {**_pooled(runs), **_confidence_intervals(runs)}
    lo, hi = average["trans_err_ci95_m"]
    assert lo == pytest.approx(0.2) and lo < average["trans_err_m"] < hi  # one wrong run of seven: wide above
    assert average["room_acc_ci95"][0] < average["room_acc"] <= average["room_acc_ci95"][1] == pytest.approx(1.0)
    report = {"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}}
    line = format_table_one(report, "smcl").splitlines()[-1]
    assert line.startswith("95 % interval of the average (bootstrap over the 7 runs): 0.20–")
    assert _confidence_intervals(runs[:1]) == {}  # one run has no interval, and the table has no such line
    single = {"variants": ["smcl"], "smcl": {"average": _pooled(runs[:1]), "per_trajectory": {}}}
    assert format_table_one(single, "smcl").splitlines()[-1].startswith("Avg.")
