"""The localizer's variants on a simulated drive through the paper-floor building: smcl, smcl+graph and full (the
drive and its runs: tests/conftest.py; their offline refinement: tests/test_refine.py)."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest

from bimfactor.bim.symmetry import Motion
from bimfactor.config import Config, load_config
from bimfactor.errors import ConfigError, InputError
from bimfactor.evaluation import report
from bimfactor.evaluation.metrics import translation_errors_m
from bimfactor.evaluation.report import twin_summary, write_run
from bimfactor.localization.stats import local_mean_yaw, weighted_geometric_median
from bimfactor.pipeline import (
    TWIN_YAW_DEG,
    LocalizationRun,
    Localizer,
    localize_sequence,
    rejection_kind,
)
from bimfactor.sim.simulate import SimResult, simulate_sequence
from bimfactor.types import wrap_angle
from tests.conftest import SEED
from tests.sim.conftest import Building

# The full variant's last-step error may exceed smcl+graph's by at most this (ICP against the walls is cm-accurate).
FULL_TOLERANCE_M = 0.02
ACCEPTED_MAX_ERROR_M = 0.05


def test_the_graph_variant_leaves_the_filter_as_it_is(runs: dict[str, LocalizationRun]) -> None:
    smcl, graph = runs["smcl"], runs["smcl+graph"]
    assert (smcl.variant, graph.variant) == ("smcl", "smcl+graph")
    # The back end only reads the particles: the filter's estimate is the same bit for bit, with ICP too (the demo
    # reports S-MCL from the smcl+graph run's filter track on the strength of this).
    for other in (graph, runs["full"]):
        for name in ("poses", "covariances", "storeys", "rooms"):
            np.testing.assert_array_equal(getattr(other.filter, name), getattr(smcl.filter, name), err_msg=name)
        np.testing.assert_array_equal(other.ess, smcl.ess)
    assert smcl.graph is None and smcl.output is smcl.filter and not smcl.final_modes
    assert all(not modes for modes in smcl.modes)
    assert graph.graph is not None and graph.output is graph.graph
    assert graph.odom_increments.shape == (len(graph.poses) - 1, 3)
    assert np.all(graph.graph.step_ms >= graph.filter.step_ms)


def _check_reported_covariance(run: LocalizationRun, i: int, mode) -> None:
    """The reported covariance is the whole belief's about the reported pose: the reported mode's share of it,
    plus the rivals'."""
    modes = run.modes[i]
    clustered = min(sum(m.particle_weight for m in modes), 1.0)
    own = clustered * mode.probability * mode.covariance
    assert np.all(np.linalg.eigvalsh(run.covariances[i] - own) > -1e-12)
    if clustered > 0.999 and mode.probability > 0.999:
        np.testing.assert_allclose(run.covariances[i], mode.covariance, rtol=0.01, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(run.covariances[i]) > 0)


def test_the_graph_output_is_the_mode_at_the_belief_median(runs: dict[str, LocalizationRun]) -> None:
    """Default `localization.output: belief_median`: each step reports a mode's graph pose, or, with no mode near
    the particles' median, a position of its own; once converged, the most probable mode."""
    run = runs["smcl+graph"]
    assert run.graph is not None
    with_modes = [i for i, modes in enumerate(run.modes) if modes]
    assert len(with_modes) > len(run.modes) // 2
    reported_modes = 0
    for i, modes in enumerate(run.modes):
        probabilities = [m.probability for m in modes]
        assert probabilities == sorted(probabilities, reverse=True)
        assert not modes or sum(probabilities) == pytest.approx(1.0)
        reported = [m for m in modes if np.array_equal(m.pose, run.poses[i])]
        if reported:
            reported_modes += 1
            _check_reported_covariance(run, i, reported[0])
        else:  # the median itself (`test_the_median_output_is_the_belief_median_with_its_local_heading`)
            assert np.all(np.linalg.eigvalsh(run.covariances[i]) > 0)
        if run.converged[i] and modes and modes[0].probability > 0.99:
            np.testing.assert_array_equal(run.poses[i], modes[0].pose)
    assert reported_modes >= len(with_modes) // 2
    assert run.final_modes and run.final_modes[0].mode_id == run.modes[-1][0].mode_id


def test_the_median_output_is_the_belief_median_with_its_local_heading(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str], fixed_value
) -> None:
    """Where no mode is near the belief's median, the output is the median of the weights an estimate may use,
    with the mean heading of the particles around it."""
    # A 5 cm radius (2 m by default) leaves the modes' graph poses outside it on most steps.
    fixed_value("localization.output_mode_radius_m", 0.05)
    overrides = [*config_overrides, "localization.variant=smcl+graph"]
    cfg = load_config(None, overrides)
    localizer = Localizer(paper_floor.prior, drive.meta, cfg, SEED, text_embedder=text_embedder)
    radius = cfg.localization.output_mode_radius_m
    medians = local = 0
    for frame in drive.frames[:12]:
        out = localizer.step(frame)
        if out.graph is not None and any(np.array_equal(m.pose, out.pose) for m in out.graph.modes):
            continue
        medians += 1
        mcl = localizer.filter
        on = mcl.storeys == out.storey
        weights = mcl.estimation_weights()[on]
        median = weighted_geometric_median(mcl.particles[on, :2], weights)
        np.testing.assert_allclose(out.pose[:2], median)
        yaw = local_mean_yaw(mcl.particles[on], weights, median, radius)
        assert out.pose[2] == (out.filtered.pose[2] if yaw is None else yaw)
        local += yaw is not None
    assert medians >= 6 and local >= 6


def test_on_a_twin_storey_each_step_reports_the_twin_pose_and_the_belief_there(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str], runs: dict
) -> None:
    """The paper floor has no twin storey: nothing is reported. Given one (storey 0 carried 0.5 m along x onto
    itself, as if the floor were a repeated bay), every step's twin pose is the output pose carried by the motion and
    its share is the filter's estimation weight within the output radius and TWIN_YAW_DEG of that pose."""
    assert runs["smcl"].twin_poses is None and runs["smcl"].twin_share is None
    shift = Motion(0.0, np.array([0.5, 0.0]), 43, 43)
    cfg = load_config(None, [*config_overrides, "localization.variant=smcl+graph"])
    localizer = Localizer(paper_floor.prior, drive.meta, cfg, SEED, text_embedder=text_embedder, twins={0: shift})
    shares = []
    for frame in drive.frames[:12]:
        out = localizer.step(frame)
        assert out.twin_pose is not None
        np.testing.assert_allclose(out.twin_pose, out.pose + np.array([0.5, 0.0, 0.0]))
        mcl = localizer.filter
        weights = mcl.estimation_weights()
        offset = np.hypot(*(mcl.particles[:, :2] - out.twin_pose[:2]).T)
        turn = np.abs(wrap_angle(mcl.particles[:, 2] - out.twin_pose[2]))
        near = (
            (mcl.storeys == 0) & (offset <= cfg.localization.output_mode_radius_m) & (turn <= np.deg2rad(TWIN_YAW_DEG))
        )
        assert out.twin_share == pytest.approx(weights[near].sum() / weights.sum())
        shares.append(out.twin_share)
    # Converged, the belief lies around the estimate: within 2 m of a pose 0.5 m away from it.
    assert all(0.0 <= share <= 1.0 for share in shares) and shares[-1] > 0.5


def test_the_run_folder_lists_the_twin_poses_and_says_how_often_the_belief_split(
    paper_floor: Building, runs: dict[str, LocalizationRun], tmp_path
) -> None:
    """steps.csv's twin columns are empty without twins; with them (here given by hand on every other step) they
    hold the twin pose and share, and the summary line counts the steps with ≥ 20 % at the twin."""
    run = runs["smcl"]
    write_run(run, paper_floor.prior, tmp_path / "plain", "", "plain")
    rows = list(csv.DictReader((tmp_path / "plain" / "steps.csv").read_text().splitlines()))
    assert all(row["twin_share"] == "" and row["twin_x"] == "" for row in rows) and twin_summary(run) is None
    n = len(run.poses)
    share = np.where(np.arange(n) % 2 == 0, np.nan, 0.1)
    share[1::4] = 0.3  # steps 1, 5, 9, ...: the belief split
    twin_poses = np.where(np.isnan(share)[:, None], np.nan, run.poses + np.array([1.0, 2.0, 0.0]))
    twin_run = dataclasses.replace(run, twin_poses=twin_poses, twin_share=share)
    write_run(twin_run, paper_floor.prior, tmp_path / "twin", "", "twin")
    rows = list(csv.DictReader((tmp_path / "twin" / "steps.csv").read_text().splitlines()))
    assert [row["twin_share"] == "" for row in rows] == [i % 2 == 0 for i in range(n)]
    assert float(rows[1]["twin_share"]) == 0.3 and float(rows[3]["twin_share"]) == 0.1
    assert float(rows[1]["twin_x"]) == pytest.approx(run.poses[1, 0] + 1.0)
    assert float(rows[1]["twin_y"]) == pytest.approx(run.poses[1, 1] + 2.0)
    summary = twin_summary(twin_run)
    assert summary is not None
    assert f"at {n // 2} of {n} steps" in summary and f"at {len(range(1, n, 4))} steps" in summary


def test_an_initial_pose_guess_starts_the_filter_about_it(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]
) -> None:
    """AMCL's initial pose: M particles about a guess 1 m and 20° off the truth; the run tracks from its first
    step."""
    truth = np.array([f.gt_pose for f in drive.frames[:10]])
    x, y, yaw = truth[0] + [0.6, -0.8, np.deg2rad(20.0)]
    cfg = load_config(None, [*config_overrides, f"smcl.start.pose=[{x}, {y}, {np.degrees(yaw)}]"])
    localizer = Localizer(paper_floor.prior, drive.meta, cfg, SEED, text_embedder=text_embedder)
    start = localizer.filter
    assert start.num_particles == cfg.smcl.num_particles and np.all(start.storeys == 0)
    assert np.hypot(*(start.particles[:, :2].mean(axis=0) - [x, y])) < 0.1
    run = localize_sequence(
        paper_floor.prior, drive.meta, drive.frames[:10], cfg, SEED, text_embedder=text_embedder, show_progress=False
    )
    errors = translation_errors_m(run.poses, truth)
    assert errors.max() < 1.0 and errors[-1] < 0.5, errors


def test_a_kidnapped_robot_is_noticed_and_the_belief_spread_over_the_building_again(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]
) -> None:
    """Tracking from a pose guess, the robot is carried to another route unseen by odometry: at the second frame
    the filter (`smcl.relocalize`) spreads its particles over the building; without it, it keeps the old place. With
    the paper's open-vocabulary eyes, whose objects keep the tracking before the kidnap tight (the lost monitor's
    reaction is what is under test)."""
    from bimfactor.sim.simulate import kidnap

    other = simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 3, 0, progress=False)
    frames = kidnap(drive.frames, other.frames, at=12, resume_at=10)[:16]
    truth = np.array([f.gt_pose for f in frames])
    assert np.hypot(*(truth[12, :2] - truth[11, :2])) > 5.0
    x, y, yaw = truth[0]
    guess = f"smcl.start.pose=[{x}, {y}, {np.degrees(yaw)}]"
    spread = {}
    for relocalize in (True, False):
        relocalizing = f"smcl.relocalize.enabled={str(relocalize).lower()}"
        cfg = load_config(None, [*config_overrides, guess, relocalizing, "perception.sim_preset=paper"])
        run = localize_sequence(
            paper_floor.prior, drive.meta, frames, cfg, SEED, text_embedder=text_embedder, show_progress=False
        )
        assert translation_errors_m(run.poses[:12], truth[:12]).max() < 1.0  # tracking before it
        assert np.nanmedian(run.scan_fit[2:12]) > 0.4 and np.nanmax(run.scan_fit[12:14]) < 0.5 * np.nanmean(
            run.scan_fit[2:12]
        )
        spread[relocalize] = run
    steps = np.flatnonzero(spread[True].relocalized)
    assert steps.tolist() == [13], steps  # the second poor frame
    assert spread[True].lost_frames[13] == 2  # lost since keyframe 12, the first one at the new place
    assert spread[True].segments() == [range(0, 12), range(12, 16)]
    assert (
        spread[True].n_particles[steps[0]] == paper_floor.cfg.smcl.resampler.max_particles
    )  # the whole building again
    assert not spread[False].relocalized.any() and spread[False].segments() == [range(0, 16)]


def test_an_operator_can_start_the_belief_over_from_a_pose_guess_or_the_whole_building(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]
) -> None:
    """`Localizer.reset`: AMCL's initial pose mid-run (the particles about the guess, the back end's modes
    anew) and its global localization (the particles over the whole building)."""
    truth = np.array([f.gt_pose for f in drive.frames])
    x, y, yaw = truth[0]
    cfg = load_config(
        None, [*config_overrides, "localization.variant=smcl+graph", f"smcl.start.pose=[{x}, {y}, {np.degrees(yaw)}]"]
    )
    localizer = Localizer(paper_floor.prior, drive.meta, cfg, SEED, text_embedder=text_embedder)
    for frame in drive.frames[:6]:
        before = localizer.step(frame)
    assert before.graph is not None and before.graph.modes and np.hypot(*(before.pose[:2] - truth[5, :2])) < 0.5
    old_backend = localizer.backend
    guess = truth[6] + [0.3, -0.3, 0.1]
    localizer.reset(guess)
    assert localizer.backend is not old_backend and not localizer.backend.graphs
    offsets = np.hypot(*(localizer.filter.particles[:, :2] - guess[:2]).T)
    assert np.median(offsets) < 0.8 and offsets.max() < 3.0  # σ = 0.5 m about the guess (median radius 0.59 m)
    after = localizer.step(drive.frames[6])
    assert np.hypot(*(after.pose[:2] - truth[6, :2])) < 1.0
    localizer.reset()
    spread = localizer.filter.particles
    assert (
        len(spread) == cfg.smcl.resampler.max_particles and np.ptp(spread[:, 0]) > 40.0 and np.ptp(spread[:, 1]) > 40.0
    )
    with pytest.raises(InputError, match="no navigable space"):
        localizer.reset([1e4, 1e4, 0.0])


def test_a_frame_without_odometry_is_refused(
    paper_floor: Building, drive: SimResult, text_embedder, test_config: Config
) -> None:
    localizer = Localizer(paper_floor.prior, drive.meta, test_config, SEED, text_embedder=text_embedder)
    localizer.step(drive.frames[0])
    blind = dataclasses.replace(drive.frames[1], odom_pose=np.array([1.0, np.nan, 0.0]))
    with pytest.raises(InputError, match=f"frame {blind.index} has no odometry pose"):
        localizer.step(blind)


def test_a_prior_embedded_with_another_model_is_refused(
    paper_floor: Building, drive: SimResult, text_embedder, test_config: Config
) -> None:
    """Observations and BIM objects must share one embedding space; the check needs no model weights."""
    other = dataclasses.replace(paper_floor.prior, embedding_model="clip:ViT-L-14")
    with pytest.raises(ConfigError, match=r"embedded with clip:ViT-L-14, but this run embeds with all-MiniLM-L6-v2"):
        Localizer(other, drive.meta, test_config, SEED, text_embedder=text_embedder)
    with pytest.raises(ConfigError, match="embedded with clip:ViT-L-14"):
        Localizer(other, drive.meta, test_config, SEED)


def test_a_run_folder_is_replaced_whole_or_not_at_all(
    paper_floor: Building, runs: dict[str, LocalizationRun], tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that fails while its folder is written leaves the earlier run as it was, and no partial folder."""
    folder = tmp_path / "run"
    write_run(runs["smcl"], paper_floor.prior, folder, "earlier: true\n", "earlier")
    before = {f.name: f.read_bytes() for f in folder.iterdir()}

    def broken_figure(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(report, "save_estimate_plot", broken_figure)
    with pytest.raises(OSError, match="disk full"):
        write_run(runs["smcl+graph"], paper_floor.prior, folder, "later: true\n", "later")
    assert {f.name: f.read_bytes() for f in folder.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_with_best_mode_output_the_graph_output_is_the_most_probable_mode(
    paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]
) -> None:
    cfg = load_config(None, [*config_overrides, "localization.variant=smcl+graph", "localization.output=best_mode"])
    run = localize_sequence(
        paper_floor.prior, drive.meta, drive.frames[:20], cfg, SEED, text_embedder=text_embedder, show_progress=False
    )
    assert any(run.modes)
    for i, modes in enumerate(run.modes):
        if not modes:  # no cluster heavy enough yet: the filter's estimate stands
            np.testing.assert_array_equal(run.poses[i], run.filter.poses[i])
            continue
        np.testing.assert_array_equal(run.poses[i], modes[0].pose)
        _check_reported_covariance(run, i, modes[0])


def test_full_feeds_accepted_icp_fits_into_the_best_mode(runs: dict[str, LocalizationRun]) -> None:
    graph, full = runs["smcl+graph"], runs["full"]
    assert full.variant == "full" and full.graph is not None and full.fine is not None
    # ICP only feeds the graphs: the filter is the same bit for bit.
    np.testing.assert_array_equal(full.filter.poses, graph.filter.poses)
    fine = full.fine
    has_mode = np.array([bool(modes) for modes in full.modes])
    np.testing.assert_array_equal(fine.ran, has_mode)
    assert fine.accepted.sum() >= 5 and not np.any(fine.accepted & ~fine.ran)
    assert all(not reasons for reasons, ok in zip(fine.reasons, fine.accepted, strict=True) if ok)
    rejected = fine.ran & ~fine.accepted
    assert all(fine.reasons[i] for i in np.flatnonzero(rejected))
    assert sum(fine.rejection_counts().values()) >= int(rejected.sum())
    for i, modes in enumerate(full.modes):
        if modes:  # the output is the best mode after its ICP factor
            np.testing.assert_array_equal(full.poses[i], modes[0].pose)
    assert np.all(full.graph.step_ms >= full.filter.step_ms + fine.time_ms)
    # An accepted fit puts the output on the walls: within a few centimetres of the truth.
    errors_m = translation_errors_m(full.poses, full.gt_poses)
    assert np.all(errors_m[fine.accepted] < ACCEPTED_MAX_ERROR_M)
    final_full_m = errors_m[-1]
    final_graph_m = translation_errors_m(graph.poses, graph.gt_poses)[-1]
    assert final_full_m <= final_graph_m + FULL_TOLERANCE_M


@pytest.mark.parametrize(
    ("reason", "kind"),
    [
        ("fitness 0.71 < 0.90", "fitness"),
        ("inlier RMSE 0.081 m > 0.060 m", "inlier RMSE"),
        ("degenerate: λmin/λmax 0.010 < 0.080", "degenerate"),
        ("ambiguous: 2 probes found as good a fit elsewhere (nearest 0.61 m, 0.3° away)", "ambiguous"),
        ("the start pose is not finite", "the start pose is not finite"),
    ],
)
def test_rejection_kind(reason: str, kind: str) -> None:
    assert rejection_kind(reason) == kind
