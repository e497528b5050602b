"""The active scenario: the closed loop beside the passive route from the same start, reported as `+active`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.symmetry import twin_motions
from bimfactor.config import load_config, updated
from bimfactor.evaluation.active import active_route, active_runs
from bimfactor.evaluation.paper import paper_report, reported_variants, run_seed, simulate_routes
from bimfactor.pipeline import localize_sequence, scan_matcher
from bimfactor.types import wrap_angle


def test_the_active_run_follows_suggestions_and_is_the_passive_run_until_the_first(
    paper_floor_prior: Path, config_overrides: list[str]
) -> None:
    cfg = load_config(None, [*config_overrides, "evaluation.trajectory_length=22", "localization.variant=smcl+graph"])
    prior = BimPrior.load(paper_floor_prior)
    (passive,), _ = simulate_routes(paper_floor_prior, cfg, [(2, 22)])
    run, frames, steer = active_route(paper_floor_prior, cfg, 2, 0, twin_motions(prior), route=passive.frames)
    assert len(frames) == len(run.poses) == 22
    assert steer.first_suggestion is not None and steer.goals  # the belief narrowed to a few places and asked
    first = steer.first_suggestion + 1  # frames up to and including the one the first suggestion came after
    for mine, theirs in zip(frames[:first], passive.frames[:first], strict=True):
        np.testing.assert_allclose(mine.gt_pose, theirs.gt_pose)
        np.testing.assert_allclose(mine.odom_pose, theirs.odom_pose)
        np.testing.assert_array_equal(mine.depth_m, theirs.depth_m)
    # The same route, seeds and sequence: the localizer's estimates up to there are the passive run's, bit for bit.
    alone = localize_sequence(
        prior, passive.meta, passive.frames[:first], cfg, run_seed(cfg.seed, 2, 0), show_progress=False,
        matcher=scan_matcher(prior, cfg), twins=twin_motions(prior),
    )  # fmt: skip
    np.testing.assert_array_equal(run.filter.poses[:first], alone.filter.poses)
    np.testing.assert_array_equal(run.poses[:first], alone.poses)
    # then it drove (or turned) off to the goals: the route's own poses are left
    off = [
        np.hypot(*(mine.gt_pose[:2] - theirs.gt_pose[:2])) + abs(wrap_angle(mine.gt_pose[2] - theirs.gt_pose[2]))
        for mine, theirs in zip(frames[first:], passive.frames[first:], strict=True)
    ]
    assert max(off) > 0.1, off
    # The localizer weighed the route's next keyframes as a candidate while the robot was on the route, not after.
    steer.frames = frames[:first]
    np.testing.assert_array_equal(steer.route_ahead(), [f.odom_pose for f in passive.frames[first:]])
    steer.frames = frames
    assert steer.route_ahead() is None
    steer.frames = frames[: first + int(np.argmax(np.asarray(off) > 1e-6)) + 1]  # the first frame off the route
    assert steer.route_ahead() is None


def test_the_active_scenario_reports_each_variant_and_its_closed_loop(
    paper_floor_prior: Path, config_overrides: list[str]
) -> None:
    cfg = load_config(
        None,
        [*config_overrides, "evaluation.trajectory_length=6", "evaluation.variants=[smcl,smcl+graph]",
         "evaluation.num_trajectories=1", "evaluation.repeats=1",
         "evaluation.scenario=active"],
    )  # fmt: skip
    prior = BimPrior.load(paper_floor_prior)
    twins = twin_motions(prior)
    results = active_runs(paper_floor_prior, cfg, 0, 0, twins)
    assert sorted(r.variant for r in results) == sorted(reported_variants(cfg.evaluation))
    assert reported_variants(cfg.evaluation) == ["smcl", "smcl+graph", "smcl+active", "smcl+graph+active"]
    assert all(len(r.trans_err_m) == 6 and r.outcome is not None for r in results)
    report = paper_report(paper_floor_prior, prior, cfg, twins, results)
    assert {"smcl+graph", "smcl+graph+active"} <= set(report["variants"])
    assert report["smcl+graph+active"]["average"]["runs"] == 1
    assert reported_variants(updated(cfg, {"evaluation.scenario": "global"}).evaluation) == ["smcl", "smcl+graph"]
