"""Writing a localization run to disk: trajectory (TUM), per-step table, metrics, particle snapshots, figures."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.evaluation.metrics import TrajectoryMetrics, trajectory_metrics
from bimfactor.evaluation.plots import save_estimate_plot, save_particle_snapshots
from bimfactor.io.atomic import atomic_path, write_text_atomic
from bimfactor.io.tum import write_tum_trajectory
from bimfactor.pipeline import LocalizationRun

STEP_COLUMNS = [
    "step", "timestamp_s", "x", "y", "yaw", "storey", "room", "cov_xx", "cov_xy", "cov_yy", "cov_yawyaw",
    "converged", "ess", "n_observations", "filter_ms", "perception_ms", "gt_x", "gt_y", "gt_yaw", "gt_room",
]  # fmt: skip


def run_metrics(run: LocalizationRun) -> TrajectoryMetrics | None:
    """The paper's metrics of a run, when its sequence has ground truth."""
    if run.gt_poses is None or run.gt_rooms is None:
        return None
    return trajectory_metrics(run.poses, run.gt_poses, run.rooms, run.gt_rooms, run.covariances, run.filter_ms)


def write_run(run: LocalizationRun, prior: BimPrior, out_dir: str | Path, config_yaml: str, title: str) -> list[Path]:
    """Write estimate.txt (TUM), steps.csv, metrics.json (with ground truth), snapshots.npz, config.yaml, figures."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "config.yaml", config_yaml)
    write_tum_trajectory(out_dir / "estimate.txt", run.timestamps_s, run.poses, comment="bimfactor estimate")
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(STEP_COLUMNS)
    for i in range(len(run.poses)):
        gt = run.gt_poses[i] if run.gt_poses is not None else (np.nan,) * 3
        gt_room = int(run.gt_rooms[i]) if run.gt_rooms is not None else ""
        cov = run.covariances[i]
        writer.writerow(
            [i, repr(float(run.timestamps_s[i])), *map(repr, map(float, run.poses[i])), int(run.storeys[i]),
             int(run.rooms[i]), repr(float(cov[0, 0])), repr(float(cov[0, 1])), repr(float(cov[1, 1])),
             repr(float(cov[2, 2])), int(run.converged[i]), repr(float(run.ess[i])), int(run.n_observations[i]),
             f"{run.filter_ms[i]:.3f}", f"{run.perception_ms[i]:.3f}", *map(repr, map(float, gt)), gt_room]
        )  # fmt: skip
    write_text_atomic(out_dir / "steps.csv", buffer.getvalue())
    metrics = run_metrics(run)
    if metrics is not None:
        write_text_atomic(out_dir / "metrics.json", json.dumps(metrics.to_dict(), indent=2))
    with atomic_path(out_dir / "snapshots.npz") as tmp, tmp.open("wb") as fh:
        np.savez_compressed(
            fh,
            **{
                f"step{k}_{name}": arr
                for k, (p, w) in run.snapshots.items()
                for name, arr in (("particles", p), ("weights", w))
            },
        )
    storey = int(np.bincount(run.storeys).argmax()) if len(run.storeys) else 0
    figures = [save_estimate_plot(prior, run.poses, run.gt_poses, storey, out_dir / "trajectory.png", title)]
    if run.snapshots:
        figures.append(
            save_particle_snapshots(prior, run.snapshots, run.gt_poses, run.poses, storey, out_dir / "particles.png")
        )
    return figures
