"""The offline refinement (`bimfactor.refine`) of the paper-floor drive's graph runs (`runs`, tests/conftest.py)
and of a kidnapped recording: stretches refined on their own, seams searched in hindsight, false alarms joined,
stretches parted offline."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bimfactor.backend.factors import Landmarks
from bimfactor.backend.posegraph import semantic_associator
from bimfactor.backend.refine import refine_mode
from bimfactor.config import Config, load_config
from bimfactor.evaluation import report
from bimfactor.evaluation.metrics import translation_errors_m
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.pipeline import LocalizationRun, localize_sequence, visibility_of
from bimfactor.refine import RefinedRun, _hindsight_segments, _offline_split, refine_run
from bimfactor.sim.simulate import SimResult, simulate_sequence
from tests.conftest import SEED
from tests.sim.conftest import Building

REFINE_TOLERANCE_M = 0.05


@pytest.fixture(scope="module")
def kidnapped(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]
) -> tuple[LocalizationRun, Config]:
    """smcl+graph tracking from a pose guess, carried off after keyframe 11 (30 keyframes), and its config; with the
    paper's open-vocabulary eyes, whose objects keep the tracking before the kidnap tight (the refinement's seams
    are what is under test)."""
    from bimfactor.sim.simulate import kidnap

    other = simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 3, 0, progress=False)
    frames = kidnap(drive.frames, other.frames, at=12, resume_at=11)[:30]  # new place: from route 3's keyframe 12
    x, y, yaw = frames[0].gt_pose
    cfg = load_config(
        None,
        [
            *config_overrides,
            "localization.variant=smcl+graph",
            f"smcl.start.pose=[{x}, {y}, {np.degrees(yaw)}]",
            "perception.sim_preset=paper",
        ],
    )
    run = localize_sequence(
        paper_floor.prior, drive.meta, frames, cfg, SEED, text_embedder=text_embedder, show_progress=False
    )
    return run, cfg


def test_a_kidnapped_recording_is_refined_one_stretch_at_a_time(
    paper_floor: Building, kidnapped: tuple[LocalizationRun, Config], tmp_path
) -> None:
    """Carried off after keyframe 11: each side of the seam is smoothed on its own, the seam found in hindsight."""
    run, cfg = kidnapped
    truth = run.gt_poses
    assert run.relocalized.any()
    refined = refine_run(run, paper_floor.prior, cfg)
    assert [steps.start for steps in refined.segments] == [0, 12] and not refined.offline_seams
    report.write_refined(refined, paper_floor.prior, tmp_path / "refined", cfg.dump_yaml(), title="kidnapped")
    stretches = json.loads((tmp_path / "refined" / "modes.json").read_text())["segments"]
    assert [(s["steps"], s["begins"]) for s in stretches] == [([0, 11], "start"), ([12, 29], "relocalized")]
    first, second = refined.best
    assert first is not None and second is not None and second.start == 12 and second.first_index > 12
    assert len(first.poses) == 12 and len(second.poses) == 18  # each over its own stretch
    assert refined.best_at(11) is first and refined.best_at(12) is second
    errors = translation_errors_m(refined.estimate.poses, truth)
    assert errors.max() < 0.5, errors  # both sides, the keyframes before the new place's mode was born included
    # A change point the monitor put late or early is moved to where the frames say, unless the search is off.
    (k,) = np.flatnonzero(run.relocalized)
    monitor_only = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"refine_seam_window": 0})})
    unconvinced = cfg.model_copy(
        update={"backend": cfg.backend.model_copy(update={"refine_seam_min_log_ratio": 1e6})}
    )  # no gain of likelihood is enough to move it
    for seam in (k, 9):
        lost_frames = np.zeros_like(run.lost_frames)
        lost_frames[k] = k - seam + 1
        misplaced = dataclasses.replace(run, lost_frames=lost_frames)
        assert misplaced.segments()[1].start == seam
        assert [steps.start for steps in refine_run(misplaced, paper_floor.prior, cfg).segments] == [0, 12]
        for kept in (monitor_only, unconvinced):
            assert [steps.start for steps in refine_run(misplaced, paper_floor.prior, kept).segments] == [0, seam]


def test_a_recording_carried_off_unnoticed_is_parted_offline(
    paper_floor: Building, kidnapped: tuple[LocalizationRun, Config], tmp_path
) -> None:
    """The same recording as if the filter had never relocalized (one stretch): the mode born at the new place and
    the old place's mode each explain their side, and refine parts the stretch where they meet."""
    run, cfg = kidnapped
    unnoticed = dataclasses.replace(run, lost_frames=np.zeros_like(run.lost_frames))
    assert unnoticed.segments() == [range(0, 30)]
    refined = refine_run(unnoticed, paper_floor.prior, cfg)
    assert refined.offline_seams == [12] and [steps.start for steps in refined.segments] == [0, 12]
    assert translation_errors_m(refined.estimate.poses, run.gt_poses).max() < 0.5
    report.write_refined(refined, paper_floor.prior, tmp_path / "refined", cfg.dump_yaml(), title="carried off")
    stretches = json.loads((tmp_path / "refined" / "modes.json").read_text())["segments"]
    assert [(s["steps"], s["begins"]) for s in stretches] == [([0, 11], "start"), ([12, 29], "offline")]
    # Without the split, one trajectory is smoothed across the jump, and one side is metres off.
    kept = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"refine_split": False})})
    whole = refine_run(unnoticed, paper_floor.prior, kept)
    assert [steps.start for steps in whole.segments] == [0] and not whole.offline_seams
    assert translation_errors_m(whole.estimate.poses, run.gt_poses).max() > 2.0


def test_a_stretch_is_parted_where_two_modes_each_explain_their_own_side_by_far_best() -> None:
    """`_offline_split` on per-keyframe fits: steps 10 … 39, carried off before step 24."""
    from types import SimpleNamespace

    steps, cfg = range(10, 40), load_config().backend
    before = np.r_[np.full(14, 2.0), np.full(16, -3.0)]  # the old place's mode: right up to step 23
    after = np.r_[np.full(14, -3.0), np.full(16, 2.0)]  # the new place's, born at 25, tracked back across the jump
    old, new = SimpleNamespace(first_index=11), SimpleNamespace(first_index=25)
    assert _offline_split(steps, [new, old], [after, before], cfg) == 24  # 70 nats over the best single mode
    assert _offline_split(steps, [new, old], [after, before], cfg.model_copy(update={"refine_split_min_keyframes": 15}))
    assert (
        _offline_split(steps, [new, old], [after, before], cfg.model_copy(update={"refine_split_min_keyframes": 16}))
        is None
    )
    born_early = SimpleNamespace(first_index=20)  # the later part begins at its mode's birth at the latest
    assert _offline_split(steps, [born_early, old], [after, before], cfg) == 20
    # A wrong mode that fits the first 25 keyframes a little better than the true one (0.5 per keyframe, 12.5 in all)
    # does not part the stretch; with no per-keyframe bar it would.
    true, wrong = np.full(30, 1.0), np.r_[np.full(25, 1.5), np.zeros(5)]
    early, late = SimpleNamespace(first_index=10), SimpleNamespace(first_index=36)
    assert _offline_split(steps, [late, early], [true, wrong], cfg) is None
    lax = cfg.model_copy(update={"refine_split_min_keyframe_log_ratio": 0.0})
    assert _offline_split(steps, [late, early], [true, wrong], lax) == 35
    assert _offline_split(steps, [late], [true], lax) is None  # one mode: nothing to part


def test_two_seams_searched_in_one_pass_each_stay_within_the_stretches_their_fits_cover() -> None:
    """A robot standing still at x = 0, 10, 20 (steps 0–7, 8–12, 13–29), its stretches parted late at 10 and 15:
    both seams move back, the second within the stretch its earlier fit was refined over (from step 10), even
    after the first seam has moved before it."""
    from types import SimpleNamespace

    T, truth = 30, np.r_[np.zeros(8), np.full(5, 10.0), np.full(17, 20.0)]
    segments = [range(0, 10), range(10, 15), range(15, 30)]
    best = [SimpleNamespace(poses=np.tile([x, 0.0, 0.0], (len(steps), 1)), start=steps.start, storey=0)
            for x, steps in zip((0.0, 10.0, 20.0), segments, strict=True)]  # fmt: skip
    run = SimpleNamespace(timestamps_s=np.arange(T, dtype=float), odom_increments=np.zeros((T - 1, 3)))

    def frame_fits(poses: np.ndarray, storey: int, steps: range) -> np.ndarray:
        assert len(poses) == len(steps)
        return -np.abs(poses[:, 0] - truth[steps.start : steps.stop])

    cfg = load_config().backend.model_copy(update={"refine_seam_window": 10, "refine_seam_min_log_ratio": 1.0})
    moved = _hindsight_segments(segments, [None, None], best, run, None, frame_fits, cfg)
    assert [steps.start for steps in moved] == [0, 8, 13]


def _refined(paper_floor: Building, run: LocalizationRun, config_overrides: list[str]) -> tuple[RefinedRun, Config]:
    """The offline refinement of a run, with the run's variant's config."""
    cfg = load_config(None, [*config_overrides, f"localization.variant={run.variant}"])
    return refine_run(run, paper_floor.prior, cfg), cfg


def test_refine_improves_or_matches_the_forward_pass(
    paper_floor: Building, runs: dict[str, LocalizationRun], config_overrides: list[str]
) -> None:
    run = runs["smcl+graph"]
    refined, _ = _refined(paper_floor, run, config_overrides)
    # Candidates: the surviving modes and the long-lived pruned ones, best fit to the whole sequence first.
    candidates = [*run.final_modes, *run.retired_modes]
    assert refined.modes and sorted(m.mode_id for m in refined.modes) == sorted(m.mode_id for m in candidates)
    assert all(len(m.poses) >= load_config().backend.refine_retired_min_keyframes for m in run.retired_modes)
    assert len(refined.fits) == len(refined.modes) and refined.fits == sorted(refined.fits, reverse=True)
    estimate = refined.estimate
    assert estimate.poses.shape == run.poses.shape and estimate.covariances.shape == run.covariances.shape
    np.testing.assert_array_equal(estimate.poses, refined.modes[0].poses)
    forward_m = translation_errors_m(run.poses, run.gt_poses).mean()
    refined_m = translation_errors_m(estimate.poses, run.gt_poses).mean()
    assert refined_m <= forward_m + REFINE_TOLERANCE_M
    assert all(m.batch.error_after <= m.batch.error_before for m in refined.modes)
    assert np.all(estimate.step_ms > run.graph.step_ms)


def test_a_relocalization_the_frames_do_not_bear_out_is_joined_again(
    paper_floor: Building, runs: dict[str, LocalizationRun], config_overrides: list[str]
) -> None:
    """A false alarm of the lost monitor at keyframe 30 of an uneventful drive: refine sees no mode give way to
    another there and refines the drive as one stretch, as if the monitor had never fired."""
    run = runs["smcl+graph"]
    assert not run.relocalized.any()
    lost_frames = np.zeros_like(run.lost_frames)
    lost_frames[31] = 2  # relocalized at 31, lost since 30
    false_alarm = dataclasses.replace(run, lost_frames=lost_frames)
    assert false_alarm.segments() == [range(0, 30), range(30, 50)]
    refined, cfg = _refined(paper_floor, false_alarm, config_overrides)
    assert refined.segments == [range(0, 50)] and not refined.offline_seams
    np.testing.assert_array_equal(
        refined.estimate.poses, _refined(paper_floor, run, config_overrides)[0].estimate.poses
    )
    kept = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"refine_join": False})})
    assert refine_run(false_alarm, paper_floor.prior, kept).segments == [range(0, 30), range(30, 50)]


def test_refine_needs_a_graph_run(paper_floor: Building, runs: dict[str, LocalizationRun], test_config) -> None:
    with pytest.raises(ValueError, match="pose-graph variant"):
        refine_run(runs["smcl"], paper_floor.prior, test_config)


def test_refine_of_a_full_pass_keeps_its_icp_factors(
    paper_floor: Building, runs: dict[str, LocalizationRun], config_overrides: list[str]
) -> None:
    run = runs["full"]
    refined, cfg = _refined(paper_floor, run, config_overrides)
    assert refined.modes and refined.modes[0].mode_id == run.final_modes[0].mode_id
    # A mode's pose factors enter its batch graph: a tight one 0.5 m off the smoothed pose pins that keyframe.
    mode = run.final_modes[0]
    last = len(run.poses) - 1
    target = mode.poses[-1] + np.array([0.5, 0.0, 0.0])
    pinned = dataclasses.replace(mode, pose_factors=[(last, target, np.diag([1e6, 1e6, 1e6]))])
    likelihood = SemanticLikelihood(paper_floor.prior, visibility_of(paper_floor.prior, cfg), cfg.smcl.semantic)
    plates = PlateLikelihood(paper_floor.prior, cfg.smcl)
    associate_fns = [semantic_associator(likelihood, plates, obs) for obs in run.observations]
    landmarks = Landmarks.from_prior(paper_floor.prior)
    out = refine_mode(
        pinned, run.odom_increments, run.observations, associate_fns, landmarks, cfg.backend, cfg.odometry
    )
    np.testing.assert_allclose(out.poses[last], target, atol=0.01)
