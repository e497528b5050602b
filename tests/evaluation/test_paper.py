"""The paper benchmark's report: the average row and its bootstrap interval over runs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bimfactor.config import load_config
from bimfactor.errors import ConfigError
from bimfactor.evaluation.paper import (
    RunResult,
    StepErrors,
    _confidence_intervals,
    _known_storey,
    _pooled,
    check_protocol,
    format_table_one,
    kidnap_route,
    pose_guess,
    scoring_window,
)
from bimfactor.pipeline import FineTrack, Track


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
    for run, start in zip(runs, (0, 2, 2, 4, 9, 3, 30), strict=True):
        run.scored_from = start
    warmed = {
        "variants": ["smcl"],
        "smcl": {"average": _pooled(runs), "per_trajectory": {}},
        "protocol": {"score_from": "filter_converged"},
    }
    assert format_table_one(warmed, "smcl").splitlines()[-1] == (
        "scored from the step the filter first reported itself converged: median step 3 (range 0–30) of the 7 runs"
    )


def test_the_error_after_convergence_pools_the_steps_after_each_runs_convergence() -> None:
    early, late, never = _run(0, 0, 0.1, 1.0), _run(1, 0, 0.1, 1.0), _run(2, 0, 3.0, 0.0)
    early.trans_err_m[:2] = 5.0  # converged from step 2: eight steps of 0.1 m
    late.trans_err_m[:] = 0.9
    late.trans_err_m[8] = 1.5  # converged from step 9: one step of 0.9 m
    early.metrics["steps_to_converge"], late.metrics["steps_to_converge"] = 2, 9
    never.metrics["steps_to_converge"] = None
    average = _pooled([early, late, never])
    assert average["trans_err_conv_m"] == pytest.approx((8 * 0.1 + 0.9) / 9)
    assert average["trans_err_conv_run_mean_m"] == pytest.approx((0.1 + 0.9) / 2)
    assert average["orient_err_conv_deg"] == pytest.approx(1.0)  # 10 × 0.1 m's degrees, the same steps
    assert average["converged_runs"] == 2
    assert _pooled([never])["trans_err_conv_m"] is None


def test_the_first_t_steps_are_scored_beside_the_converged_window_only_when_every_run_has_them() -> None:
    runs = [_run(k, 0, 0.2, 1.0) for k in range(2)]
    assert "from_start" not in _pooled(runs)
    runs[0].from_start = StepErrors(np.full(10, 4.0), np.full(10, 30.0), np.r_[np.zeros(5), np.ones(5)])
    assert "from_start" not in _pooled(runs)
    runs[1].from_start = StepErrors(np.full(10, 2.0), np.full(10, 10.0), np.ones(10))
    average = _pooled(runs)
    assert average["from_start"]["trans_err_m"] == pytest.approx(3.0)
    assert average["from_start"]["orient_err_deg"] == pytest.approx(20.0)
    assert average["from_start"]["room_acc"] == pytest.approx(0.75)
    assert average["trans_err_m"] == pytest.approx(0.2)  # the scored window is unchanged
    report = {"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}}
    assert format_table_one(report, "smcl").splitlines()[-1] == (
        "the same runs from their first frame (the uniform cloud included): 3.00 m, 20.0°, 75.0 %"
    )


def test_the_average_up_to_the_twin_places_is_reported_only_when_every_run_has_it() -> None:
    runs = [_run(k, 0, 3.0, 0.5) for k in range(3)]
    assert "trans_err_up_to_twin_m" not in _pooled(runs)
    for run, up_to_twin in zip(runs, (0.1, 0.2, 0.3), strict=True):
        run.trans_err_twin_m = np.full(10, up_to_twin)
        run.orient_err_twin_deg = np.full(10, 10 * up_to_twin)
    average = _pooled(runs)
    assert average["trans_err_up_to_twin_m"] == pytest.approx(0.2)
    assert average["orient_err_up_to_twin_deg"] == pytest.approx(2.0)
    report = {"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}, "twins": {"1": "a half-turn"}}
    assert format_table_one(report, "smcl").endswith(
        "up to the building's twin places (storeys 1; the motions are results.json's twins): 0.20 m, 2.0°"
    )


def test_scoring_starts_at_the_first_frame_or_where_the_filter_first_reports_itself_converged() -> None:
    flags = np.zeros(40, bool)
    flags[[7, 8, 20]] = True
    assert scoring_window(flags, 10, "start", 30) == slice(0, 10)
    assert scoring_window(flags, 10, "filter_converged", 30) == slice(7, 17)
    assert scoring_window(flags, 10, "filter_converged", 5) == slice(5, 15)  # not converged in time: from the cap
    assert scoring_window(np.ones(40, bool), 10, "filter_converged", 30) == slice(0, 10)
    assert scoring_window(np.zeros(40, bool), 10, "filter_converged", 30) == slice(30, 40)


def test_a_window_of_a_track_keeps_those_steps_of_every_field() -> None:
    steps = 6
    track = Track(
        np.arange(steps * 3.0).reshape(steps, 3), np.zeros((steps, 3, 3)), np.zeros(steps, int), np.arange(steps),
        np.arange(steps, dtype=float),
    )  # fmt: skip
    part = track.window(slice(2, 5))
    assert part.poses.tolist() == track.poses[2:5].tolist() and part.rooms.tolist() == [2, 3, 4]
    assert part.covariances.shape == (3, 3, 3) and part.step_ms.tolist() == [2.0, 3.0, 4.0]
    fine = FineTrack(np.ones(steps, bool), np.arange(steps) % 2 == 0, [[f"r{i}"] for i in range(steps)], np.ones(steps))
    tail = fine.window(slice(4, 6))
    assert tail.reasons == [["r4"], ["r5"]] and tail.accepted.tolist() == [True, False]


def test_a_pose_guess_lies_the_set_distance_and_turn_off_the_truth_in_seeded_directions() -> None:
    truth = np.array([4.0, -2.0, np.deg2rad(175.0)])
    guesses = np.array([pose_guess(truth, 1.0, 20.0, np.random.default_rng(seed)) for seed in range(40)])
    np.testing.assert_allclose(np.hypot(*(guesses[:, :2] - truth[:2]).T), 1.0)
    turns = np.rad2deg(np.angle(np.exp(1j * (guesses[:, 2] - truth[2]))))
    np.testing.assert_allclose(np.abs(turns), 20.0)  # across the ±180° seam too
    assert (turns > 0).any() and (turns < 0).any()
    directions = np.arctan2(guesses[:, 1] - truth[1], guesses[:, 0] - truth[0])
    assert np.ptp(directions) > np.pi  # not one direction for every run
    np.testing.assert_array_equal(pose_guess(truth, 1.0, 20.0, np.random.default_rng(3)), guesses[3])


def test_the_kidnapped_robot_is_carried_to_the_route_three_further_on() -> None:
    assert [kidnap_route(k, 6) for k in range(6)] == [3, 4, 5, 0, 1, 2]
    assert kidnap_route(0, 1) == 0


def test_a_scenario_other_than_the_papers_scores_from_its_own_start() -> None:
    assert load_config(None, ["evaluation.scenario=kidnap"]).evaluation.scenario == "kidnap"
    papers = load_config(None, []).evaluation
    assert papers.score_from == "filter_converged" and papers.scores_from_convergence
    assert papers.warmup_steps == papers.warmup_max_steps > 0
    for scenario in ("guess", "kidnap"):  # the default score_from does not apply: no warm-up, no first-T comparison
        ev = load_config(None, [f"evaluation.scenario={scenario}"]).evaluation
        assert not ev.scores_from_convergence and ev.warmup_steps == 0
    assert load_config(None, ["evaluation.score_from=start"]).evaluation.warmup_steps == 0
    with pytest.raises(ConfigError, match=r"evaluation\.scenario"):
        load_config(None, ["evaluation.scenario=teleport"])
    check_protocol(load_config(None, ["evaluation.scenario=kidnap"]))  # refine smooths each stretch on its own
    with pytest.raises(ConfigError, match="one pose guess for one sequence"):
        check_protocol(load_config(None, ["evaluation.scenario=guess", "smcl.start.pose=[1, 2, 3]"]))


def test_the_kidnap_table_says_how_many_runs_were_tracking_and_how_soon_they_recovered() -> None:
    runs = [_run(k, 0, 0.3, 1.0) for k in range(4)]
    for run, before, recover, relocalized, error in zip(
        runs, (True, True, True, False), (3, 9, None, 5), (1, 1, 0, 0), (0.1, 0.2, 0.3, 4.2), strict=True
    ):
        run.tracking_before = before
        run.trans_err_before_m = error
        run.metrics["steps_to_converge"] = recover
        run.relocalizations = relocalized
    average = _pooled(runs)
    assert average["tracking_before_kidnap_runs"] == 3 and average["steps_to_recover_median"] == 5.0
    assert average["trans_err_before_kidnap_m"] == pytest.approx(1.2)  # equally long runs: the mean of the means
    assert average["converged_runs"] == 3 and average["relocalized_runs"] == 2
    text = format_table_one({"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}}, "smcl")
    assert text.splitlines()[-2:] == [
        "kidnapped: 3 of 4 runs were tracking when carried off (1.20 m on average before it); 3 recovered (within 1 m "
        "and 15° to the end), in a median 5 steps",
        "the filter spread its particles over the building again in 2 runs",
    ]


def test_the_table_says_in_how_many_runs_the_belief_moved_to_a_challenger() -> None:
    runs = [_run(k, 0, 0.3, 1.0) for k in range(3)]
    for run, challenges in zip(runs, (0, 2, 1), strict=True):
        run.challenges = challenges
    average = _pooled(runs)
    assert average["challenged_runs"] == 2
    text = format_table_one({"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}}, "smcl")
    assert text.splitlines()[-1] == "the belief moved to a challenger that explained the frames better in 2 runs"
    assert "tracking_before_kidnap_runs" not in _pooled([_run(0, 0, 0.3, 1.0)])  # other scenarios: no such line


def test_a_known_storey_confines_the_uniform_start_to_the_storey_the_route_starts_on() -> None:
    frames = [SimpleNamespace(gt_storey=2), SimpleNamespace(gt_storey=0)]
    assert _known_storey(load_config(None, ["evaluation.known_storey=true"]), frames).smcl.start.storeys == [2]
    assert _known_storey(load_config(None, []), frames).smcl.start.storeys is None
    with pytest.raises(ConfigError, match=r"evaluation\.known_storey"):
        check_protocol(load_config(None, ["smcl.start.storeys=[1]"]))  # one sequence's storey, not every run's


def test_the_share_of_steps_on_the_true_storey_is_printed_for_a_building_of_several() -> None:
    runs = [_run(k, 0, 1.0, 0.5) for k in range(3)]
    for run, hits in zip(runs, (10, 5, 0), strict=True):
        run.storey_hit = (np.arange(10) < hits).astype(float)
    average = _pooled(runs)
    assert average["storey_acc"] == pytest.approx(0.5)
    report = {"variants": ["smcl"], "smcl": {"average": average, "per_trajectory": {}}, "storeys": 5}
    assert "\non the true storey: 50.0 % of the steps" in format_table_one(report, "smcl")
    assert "true storey" not in format_table_one({**report, "storeys": 1}, "smcl")
