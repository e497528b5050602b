"""Diagnostic: how much of the particle filter's belief lies at the true pose, keyframe by keyframe.

Replays the particle filter (the `smcl` variant) on every run of a `bimfactor bench paper` output folder (the same
building, routes, seeds and config) and records after each keyframe the filter's translation error, how many
particles lie within `--radius` metres and `--yaw` degrees of the true pose, and their weight. It prints how much
of the average error the first keyframes hold, how many runs have no particle at the truth after the first frame,
and how many stray more than 2 m after keyframe 10; it writes OUT/belief_at_truth.json (every run, every keyframe)
and OUT/belief_at_truth.png (mean weight at the truth and mean error per keyframe).

It tells the two reasons a filter's average error can be high apart: particles missing at the truth (particle
deprivation: more particles or particles drawn from the observations would help) or particles there that the
frames do not yet favour (ambiguity: only more informative frames help). Run from the repository root:

    .venv/bin/bimfactor bench paper --variant smcl -o runs/bench-paper
    .venv/bin/python tools/belief_at_truth.py runs/bench-paper -o runs/belief
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def replay(bench_dir: str, trajectory: int, repeat: int, radius_m: float, yaw_deg: float) -> dict:
    """One run of the bench: the filter's error, and the particles within the radius and yaw of the truth, per
    keyframe; in a worker process."""
    from bimfactor.config import load_config
    from bimfactor.evaluation.metrics import translation_errors_m
    from bimfactor.evaluation.paper import run_seed, simulate_routes
    from bimfactor.localization.stats import near_pose
    from bimfactor.pipeline import localize_sequence

    cfg = load_config(Path(bench_dir) / "config.yaml")
    cfg = cfg.model_copy(update={"localization": cfg.localization.model_copy(update={"variant": "smcl"})})
    prior_dir = Path(bench_dir) / "prior"
    (sim,), prior = simulate_routes(prior_dir, cfg, [(trajectory, None)])
    steps = range(len(sim.frames))
    run = localize_sequence(
        prior, sim.meta, sim.frames, cfg, run_seed(cfg.seed, trajectory, repeat), steps, show_progress=False
    )
    assert run.gt_poses is not None
    near_count, near_weight = [], []
    for step, truth in zip(steps, run.gt_poses, strict=True):
        particles, weights = run.snapshots[step]
        # Snapshots hold no storeys: every particle is compared as if on the truth's.
        near = near_pose(particles, np.zeros(len(particles), int), truth, 0, radius_m, np.deg2rad(yaw_deg))
        near_count.append(int(near.sum()))
        near_weight.append(float(weights[near].sum() / weights.sum()))
    return {
        "trajectory": trajectory,
        "repeat": repeat,
        "trans_err_m": translation_errors_m(run.filter.poses, run.gt_poses).tolist(),
        "near_count": near_count,
        "near_weight": near_weight,
    }


def summarise(runs: list[dict], stray_after: int = 10, stray_m: float = 2.0) -> dict:
    """The numbers printed: error shares of the first keyframes, runs without a particle at the truth, strays."""
    err = np.asarray([r["trans_err_m"] for r in runs])
    count = np.asarray([r["near_count"] for r in runs])
    weight = np.asarray([r["near_weight"] for r in runs])
    first_near = [int(np.argmax(c > 0)) + 1 if (c > 0).any() else None for c in count]  # keyframes from 1
    strays = (err[:, stray_after:] > stray_m).any(axis=1)
    return {
        "runs": len(runs),
        "trans_err_m": float(err.mean()),
        "share_of_error_steps_1_4": float(err[:, :4].sum() / err.sum()),
        "share_of_error_steps_1_10": float(err[:, :10].sum() / err.sum()),
        "runs_without_particle_at_truth_after_frame_1": int((count[:, 0] == 0).sum()),
        "first_step_with_particle_at_truth": first_near,
        "runs_off_by_2m_after_step_10": int(strays.sum()),
        "share_of_error_of_those_after_step_10": float(err[strays, stray_after:].sum() / err.sum()),
        "mean_weight_at_truth_by_step": weight.mean(axis=0).tolist(),
        "trans_err_by_step_m": err.mean(axis=0).tolist(),
    }


def save_plot(summary: dict, path: Path) -> None:
    from bimfactor.evaluation.plots import plt, save_figure  # pyplot with the file backend the package sets

    steps = np.arange(1, len(summary["trans_err_by_step_m"]) + 1)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.plot(steps, summary["mean_weight_at_truth_by_step"], ".-")
    top.set_ylabel("belief weight at the truth")
    top.set_ylim(0, 1)
    top.set_title(f"Particle filter, mean over {summary['runs']} runs")
    bottom.semilogy(steps, summary["trans_err_by_step_m"], ".-")
    bottom.set_ylabel("translation error [m]")
    bottom.set_xlabel("keyframe")
    for ax in (top, bottom):
        ax.grid(True, which="both", alpha=0.3)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bench_dir", type=Path, help="a `bimfactor bench paper` output folder (prior/, config.yaml)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder to write")
    parser.add_argument("--radius", type=float, default=1.0, help="metres from the true position (default 1)")
    parser.add_argument("--yaw", type=float, default=20.0, help="degrees from the true heading (default 20)")
    args = parser.parse_args(argv)
    if not (args.bench_dir / "config.yaml").is_file() or not (args.bench_dir / "prior").is_dir():
        print(f"error: {args.bench_dir} is not a `bimfactor bench paper` output folder", file=sys.stderr)
        return 2

    from bimfactor.config import load_config
    from bimfactor.io.atomic import write_text_atomic
    from bimfactor.progress import progress

    ev = load_config(args.bench_dir / "config.yaml").evaluation
    jobs = [(k, r) for k in range(ev.num_trajectories) for r in range(ev.repeats)]
    # spawn, as bench paper: a forked child can deadlock on the parent's torch / Open3D locks
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1), mp_context=context) as pool:
        futures = [pool.submit(replay, str(args.bench_dir), k, r, args.radius, args.yaw) for k, r in jobs]
        runs = [future.result() for future in progress(futures, desc="belief at the truth", unit="run")]
    summary = summarise(runs)
    args.output.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.output / "belief_at_truth.json", json.dumps({"summary": summary, "runs": runs}))
    save_plot(summary, args.output / "belief_at_truth.png")
    weight = summary["mean_weight_at_truth_by_step"]
    print(
        f"{summary['runs']} runs, filter error {summary['trans_err_m']:.2f} m: keyframes 1–4 hold "
        f"{100 * summary['share_of_error_steps_1_4']:.0f} % of it, "
        f"1–10 {100 * summary['share_of_error_steps_1_10']:.0f} %\n"
        f"no particle within {args.radius} m / {args.yaw}° of the truth after the first frame: "
        f"{summary['runs_without_particle_at_truth_after_frame_1']} runs (first keyframe with one, per run: "
        f"{summary['first_step_with_particle_at_truth']})\n"
        f"belief weight at the truth, keyframes 1–10: {', '.join(f'{w:.2f}' for w in weight[:10])}\n"
        f"runs more than 2 m off after keyframe 10: {summary['runs_off_by_2m_after_step_10']}; their keyframes "
        f"after 10 hold {100 * summary['share_of_error_of_those_after_step_10']:.0f} % of the error\n"
        f"wrote {args.output / 'belief_at_truth.json'}, {args.output / 'belief_at_truth.png'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
