"""Writing runs to disk: a localization run (trajectory as TUM, per-step table, modes, metrics, particle snapshots,
figures) and an offline refinement (refined trajectory, per-step covariances, every refined mode, metrics, figure)."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.evaluation.metrics import TrajectoryMetrics, trajectory_metrics
from bimfactor.evaluation.plots import save_estimate_plot, save_particle_snapshots, save_suggestion_figure
from bimfactor.io.atomic import check_output_dir, output_dir
from bimfactor.io.tum import write_tum_trajectory
from bimfactor.pipeline import LocalizationRun, Track
from bimfactor.refine import RefinedRun
from bimfactor.types import Observations

POSE_COLUMNS = [
    "x", "y", "yaw", "storey", "room", "cov_xx", "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw",
]  # fmt: skip
GT_COLUMNS = ["gt_x", "gt_y", "gt_yaw", "gt_room"]
STEP_COLUMNS = [
    "step", "timestamp_s", *POSE_COLUMNS, "converged", "ess", "n_particles", "n_observations", "texts_read",
    "scan_fit", "relocalized", "challenged", "skipped", "filter_ms",
    "perception_ms", "n_modes", "mode_id", "mode_probability", "graph_ms", "icp_accepted", "icp_ms", "twin_x",
    "twin_y", "twin_yaw", "twin_share", *GT_COLUMNS,
]  # fmt: skip
MODE_COLUMNS = [
    "step", "rank", "mode_id", "probability", "particle_weight", "normalised_residual", "n_matches", *POSE_COLUMNS,
]  # fmt: skip
REFINED_COLUMNS = ["step", "timestamp_s", *POSE_COLUMNS, "n_matches", "segment", "mode_id", "forward_x", "forward_y",
                   "forward_yaw", *GT_COLUMNS]  # fmt: skip


def ensure_run_destination(out_dir: str | Path, inputs: Sequence[str | Path] = ()) -> None:
    """Raise InputError unless a run may be written to `out_dir`: absent, empty, or an earlier bimfactor run folder
    holding nothing else, and none of `inputs` (the prior, the sequence) inside it."""
    check_output_dir(out_dir, "run", inputs=inputs)


def track_metrics(track: Track, gt_poses: np.ndarray | None, gt_rooms: np.ndarray | None) -> TrajectoryMetrics | None:
    """The paper's metrics of one estimator's track, when the sequence has ground truth."""
    if gt_poses is None or gt_rooms is None:
        return None
    return trajectory_metrics(track.poses, gt_poses, track.rooms, gt_rooms, track.covariances, track.step_ms)


def run_metrics(run: LocalizationRun) -> TrajectoryMetrics | None:
    """The paper's metrics of a run's output, when its sequence has ground truth."""
    return track_metrics(run.output, run.gt_poses, run.gt_rooms)


def _num(value: float) -> str:
    return repr(float(value))


def _pose_cells(pose: np.ndarray, storey: int, room: int, cov: np.ndarray) -> list[str | int]:
    """The POSE_COLUMNS cells of one step."""
    return [
        *map(_num, pose), int(storey), int(room), _num(cov[0, 0]), _num(cov[0, 1]), _num(cov[0, 2]),
        _num(cov[1, 1]), _num(cov[1, 2]), _num(cov[2, 2]),
    ]  # fmt: skip


def _gt_cells(gt_poses: np.ndarray | None, gt_rooms: np.ndarray | None, i: int) -> list[str | int]:
    """The GT_COLUMNS cells of step i (empty without ground truth)."""
    gt = map(_num, gt_poses[i]) if gt_poses is not None else ("",) * 3
    return [*gt, int(gt_rooms[i]) if gt_rooms is not None else ""]


def _csv(columns: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(columns)
    writer.writerows(rows)
    return buffer.getvalue()


def _main_storey(storeys: np.ndarray) -> int:
    return int(np.bincount(storeys).argmax()) if len(storeys) else 0


def write_run(
    run: LocalizationRun,
    prior: BimPrior,
    out_dir: str | Path,
    config_yaml: str,
    title: str,
    inputs: Sequence[str | Path] = (),
) -> list[Path]:
    """Write estimate.txt (TUM), steps.csv, modes.csv (graph variants), metrics.json (with ground truth; the full
    variant adds the fine stage's acceptance and rejection counts under "icp"), snapshots.npz, config.yaml and the
    figures. steps.csv's icp_accepted is 1 or 0 where the fine stage ran (variant full, a mode existed), else empty;
    on storeys with a twin (`bim.symmetry`) twin_x, twin_y, twin_yaw are the estimate's twin pose and twin_share the
    belief's weight there, else empty. scan_fit is the belief's predicted scan fit (empty without a scan) and
    relocalized 1 where the filter spread its particles over the building again (`smcl.relocalize`), challenged 1
    where it took the particles of a challenger that explained the frames better (`smcl.challenger`); skipped is why
    the localizer skipped the step's frame ("empty depth", "odometry jump of 1e6 m"; `LocalizationRun.skipped`), empty
    where it used it.
    """
    out_dir = Path(out_dir)
    with output_dir(out_dir, "run", inputs=inputs) as tmp:
        figures = _write_run_files(run, prior, tmp, config_yaml, title)
    return [out_dir / figure.name for figure in figures]


def _write_run_files(run: LocalizationRun, prior: BimPrior, out_dir: Path, config_yaml: str, title: str) -> list[Path]:
    """`write_run`'s files, into the folder that becomes the run folder once all are written; returns the figures."""
    (out_dir / "config.yaml").write_text(config_yaml)
    write_tum_trajectory(out_dir / "estimate.txt", run.timestamps_s, run.poses, comment=f"bimfactor {run.variant}")
    out, fine = run.output, run.fine
    fine_ms = fine.time_ms if fine is not None else np.zeros(len(out.poses))
    graph_ms = out.step_ms - run.filter.step_ms - fine_ms
    rows = []
    skipped = run.skip_reasons
    for i in range(len(out.poses)):
        modes = run.modes[i] if run.graph is not None else None
        best = [modes[0].mode_id, _num(modes[0].probability)] if modes else ["", ""]
        icp = [int(fine.accepted[i]), f"{fine_ms[i]:.3f}"] if fine is not None and fine.ran[i] else ["", ""]
        twin = (
            [*map(_num, run.twin_poses[i]), f"{run.twin_share[i]:.4f}"]
            if run.twin_poses is not None and run.twin_share is not None and not np.isnan(run.twin_share[i])
            else [""] * 4
        )
        rows.append(
            [i, _num(run.timestamps_s[i]), *_pose_cells(out.poses[i], out.storeys[i], out.rooms[i], out.covariances[i]),
             int(run.converged[i]), _num(run.ess[i]), int(run.n_particles[i]), int(run.n_observations[i]),
             _texts_read(run.observations[i]), "" if np.isnan(run.scan_fit[i]) else f"{run.scan_fit[i]:.4f}",
             int(run.relocalized[i]), int(run.challenged[i]), skipped[i],
             f"{run.filter.step_ms[i]:.3f}", f"{run.perception_ms[i]:.3f}", "" if modes is None else len(modes), *best,
             "" if modes is None else f"{graph_ms[i]:.3f}", *icp, *twin,
             *_gt_cells(run.gt_poses, run.gt_rooms, i)]
        )  # fmt: skip
    (out_dir / "steps.csv").write_text(_csv(STEP_COLUMNS, rows))
    if run.graph is not None:
        (out_dir / "modes.csv").write_text(_csv(MODE_COLUMNS, _mode_rows(run, prior)))
    metrics = run_metrics(run)
    if metrics is not None:
        summary = {"variant": run.variant, **metrics.to_dict(), **({"icp": fine.summary()} if fine is not None else {})}
        (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2))
    with (out_dir / "snapshots.npz").open("wb") as fh:
        np.savez_compressed(
            fh,
            **{
                f"step{k}_{name}": arr
                for k, (p, w) in run.snapshots.items()
                for name, arr in (("particles", p), ("weights", w))
            },
        )
    storey = _main_storey(run.storeys)
    figures = [save_estimate_plot(prior, run.poses, run.gt_poses, storey, out_dir / "trajectory.png", title)]
    if run.snapshots:
        figures.append(
            save_particle_snapshots(prior, run.snapshots, run.gt_poses, run.poses, storey, out_dir / "particles.png")
        )
    if run.suggestion is not None:
        (out_dir / "suggestion.json").write_text(json.dumps(run.suggestion.to_dict(), indent=2))
        figures.append(save_suggestion_figure(prior, run.suggestion, out_dir / "suggestion.png", title))
    return figures


TWIN_NOTICE_SHARE = 0.2
"""`twin_summary` counts the steps whose belief holds at least this much weight at the estimate's twin."""


def twin_summary(run: LocalizationRun) -> str | None:
    """One line on the building's twin places (None without any): how many steps were on a storey with a twin, where
    what the robot sees is the same from the estimate and its twin pose unless it sees what only one place has, and
    at how many of them the belief held at least `TWIN_NOTICE_SHARE` at the twin."""
    if run.twin_share is None:
        return None
    on_twin_storey = ~np.isnan(run.twin_share)
    split = int(np.sum(run.twin_share[on_twin_storey] >= TWIN_NOTICE_SHARE))
    return (
        f"twin places: at {int(on_twin_storey.sum())} of {len(run.twin_share)} steps the estimate was on a storey "
        "that a rigid motion carries onto itself (objects and walls), so its twin pose explains the frames as well; "
        f"the belief held ≥ {100 * TWIN_NOTICE_SHARE:.0f} % there at {split} steps (steps.csv: twin_x, twin_y, "
        "twin_yaw, twin_share)"
    )


def _texts_read(observations: Observations) -> str:
    """The door-plate text read at a step, '|'-separated ('' when none)."""
    return "|".join(observations.texts.texts) if observations.n_texts else ""


def _mode_rows(run: LocalizationRun, prior: BimPrior) -> list[list[object]]:
    """One MODE_COLUMNS row per mode per step, most probable first."""
    rows: list[list[object]] = []
    for i, modes in enumerate(run.modes):
        for rank, m in enumerate(modes):
            room = int(prior.room_at(m.pose[None, :2], m.storey)[0])
            rows.append(
                [i, rank, m.mode_id, _num(m.probability), _num(m.particle_weight), _num(m.normalised_residual),
                 m.n_matches, *_pose_cells(m.pose, m.storey, room, m.covariance)]
            )  # fmt: skip
    return rows


def _mode_file(rank: int, mode_id: int) -> str:
    """The trajectory file of the refined mode listed `rank`-th (from 0, best fit first) in modes.json: one mode id
    can name two candidates (a graph restarted at a scan match far from its prediction leaves its earlier graph as a
    candidate too), and a mode can be refined over two stretches."""
    return f"modes/{rank:02d}_mode_{mode_id}.txt"


def write_refined(
    refined: RefinedRun,
    prior: BimPrior,
    out_dir: str | Path,
    config_yaml: str,
    title: str,
    inputs: Sequence[str | Path] = (),
) -> list[Path]:
    """Write a refinement run as one folder, atomically: estimate.txt (refined, TUM), forward.txt (the forward
    pass, TUM), steps.csv (refined pose and covariance per step, with the stretch it lies on and the refined mode
    that reports it, empty where the forward pass's estimate stands), modes.json (the stretches, each with how it
    begins: at the start, where the filter relocalized or where refine parted a stretch offline; and every refined
    mode by stretch, best fit first, with its fit and forward probability: at the end, or when pruned) and
    modes/NN_mode_<id>.txt (each mode's refined trajectory over its stretch, NN its rank in modes.json),
    metrics.json (with ground truth: the refined metrics and the forward pass's), config.yaml, trajectory.png.
    """
    out_dir = Path(out_dir)
    ensure_run_destination(out_dir, inputs)
    run, est = refined.forward, refined.estimate
    segment_of = np.zeros(len(est.poses), np.int64)
    for index, steps in enumerate(refined.segments):
        segment_of[steps.start : steps.stop] = index
    rows = []
    for i in range(len(est.poses)):
        mode = refined.best_at(i)
        rows.append(
            [i, _num(run.timestamps_s[i]), *_pose_cells(est.poses[i], est.storeys[i], est.rooms[i], est.covariances[i]),
             "" if mode is None else len(mode.associations[i - mode.start]), segment_of[i],
             "" if mode is None else mode.mode_id, *map(_num, run.poses[i]), *_gt_cells(run.gt_poses, run.gt_rooms, i)]
        )  # fmt: skip
    alive = {m.mode_id for m in run.final_modes}
    modes = [
        {
            "mode_id": m.mode_id,
            "segment": m.segment,
            "steps": [m.start, m.start + len(m.poses) - 1],
            "storey": m.storey,
            "measurement_fit": fit,
            "alive_at_end": m.mode_id in alive,
            "probability": m.probability,
            "first_step": m.first_index,
            "error_before": m.batch.error_before,
            "error_after": m.batch.error_after,
            "iterations": m.batch.iterations,
            "reassociation_rounds": m.rounds,
            "matches": sum(len(a) for a in m.associations),
            "trajectory": _mode_file(rank, m.mode_id),
        }
        for rank, (m, fit) in enumerate(zip(refined.modes, refined.fits, strict=True))
    ]
    with output_dir(out_dir, "run", inputs=inputs) as tmp:
        (tmp / "config.yaml").write_text(config_yaml)
        write_tum_trajectory(tmp / "estimate.txt", run.timestamps_s, est.poses, comment="bimfactor refine")
        write_tum_trajectory(tmp / "forward.txt", run.timestamps_s, run.poses, comment=f"bimfactor {run.variant}")
        for rank, m in enumerate(refined.modes):
            stamps = run.timestamps_s[m.start : m.start + len(m.poses)]
            write_tum_trajectory(tmp / _mode_file(rank, m.mode_id), stamps, m.poses)
        (tmp / "steps.csv").write_text(_csv(REFINED_COLUMNS, rows))
        segments = [
            {
                "steps": [steps.start, steps.stop - 1],
                "best_mode": None if mode is None else mode.mode_id,
                "begins": begins,
            }
            for steps, mode, begins in zip(refined.segments, refined.best, refined.begins, strict=True)
        ]
        summary = {"refine_ms": refined.refine_ms, "segments": segments, "modes": modes}
        (tmp / "modes.json").write_text(json.dumps(summary, indent=2))
        metrics = track_metrics(est, run.gt_poses, run.gt_rooms)
        forward = run_metrics(run)
        if metrics is not None and forward is not None:
            (tmp / "metrics.json").write_text(
                json.dumps({"variant": "refine", **metrics.to_dict(), "forward": forward.to_dict()}, indent=2)
            )
        save_estimate_plot(
            prior,
            est.poses,
            run.gt_poses,
            _main_storey(est.storeys),
            tmp / "trajectory.png",
            title,
            others={f"forward ({run.variant})": run.poses},
        )
    return [out_dir / "trajectory.png"]
