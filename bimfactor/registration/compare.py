"""The registrar comparison: basins of convergence on simulated keyframes, per-registrar summaries, and speed.

For keyframes with ground truth, the true pose is perturbed by a sweep of initial errors (random
directions, seeded); each registrar runs from every perturbed start, and a run succeeds when it ends
within `success_trans_m` and `success_rot_deg` of the truth.
"""

from __future__ import annotations

import json
import logging
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config, RegistrationConfig
from bimfactor.progress import progress
from bimfactor.registration.gate import degeneracy_ratio, gate_registration
from bimfactor.registration.icp import REGISTRARS, Registrar, evaluate_pose, make_registrar
from bimfactor.registration.scan import frame_scan
from bimfactor.registration.surface import SurfaceModel, build_surface_models
from bimfactor.sim.simulate import build_world, simulate_sequence
from bimfactor.types import Frame, SequenceMeta, wrap_angle

log = logging.getLogger(__name__)

# A keyframe is usable for the comparison when its scan at the true pose has this many points ...
MIN_SCAN_POINTS = 100


@dataclass
class Keyframe:
    """A frame with ground truth, its sequence metadata, and its registration scan (N, 3) in the base frame."""

    frame: Frame
    meta: SequenceMeta
    scan_base: np.ndarray


def select_keyframes(
    prior: BimPrior, model: IfcModel, cfg: Config, surfaces: list[SurfaceModel], n: int, seed: int
) -> list[Keyframe]:
    """`n` keyframes drawn (seeded) from simulated trajectories whose scans the gate would call registrable.

    Frames that see no wall within range, or only one direction of walls (degenerate at the true pose), are
    skipped: no registrar can succeed there, and the gate rejects them (see `gate_registration`).
    """
    rc = cfg.registration
    rng = np.random.default_rng([seed, 0x1CB])
    world = build_world(prior, model, cfg, seed)
    chosen: list[Keyframe] = []
    skipped = 0
    for trajectory_index in range(cfg.evaluation.num_trajectories):
        sim = simulate_sequence(prior, model, cfg, trajectory_index, seed, progress=False, world=world)
        order = rng.permutation(len(sim.frames))
        per_trajectory = 0
        for i in order:
            frame = sim.frames[i]
            if frame.gt_pose is None or per_trajectory >= max(1, -(-n // 3)):
                continue
            surface = surfaces[frame.gt_storey or 0]
            scan = frame_scan(frame, sim.meta, rc)
            ok = len(scan) >= MIN_SCAN_POINTS
            if ok:
                ev = evaluate_pose(scan, surface, frame.gt_pose, rc)
                ok = ev.fitness >= rc.min_fitness and degeneracy_ratio(ev.information) >= rc.min_degeneracy_ratio
            if not ok:
                skipped += 1
                continue
            chosen.append(Keyframe(frame, sim.meta, scan))
            per_trajectory += 1
            if len(chosen) == n:
                log.info("%d keyframes chosen (%d frames skipped as unregistrable)", n, skipped)
                return chosen
    log.warning("only %d of %d keyframes are registrable (%d frames skipped)", len(chosen), n, skipped)
    return chosen


def initial_error_sweep(cfg: RegistrationConfig) -> np.ndarray:
    """(P, 2) initial errors (translation m, rotation rad): both 0..max evenly (`compare_registrars` re-pairs them)."""
    p = cfg.compare_perturbations
    trans = np.linspace(0.0, cfg.compare_max_trans_m, p)
    rot = np.deg2rad(np.linspace(0.0, cfg.compare_max_rot_deg, p))
    return np.column_stack([trans, rot])


def perturb(pose: np.ndarray, trans_m: float, rot_rad: float, rng: np.random.Generator) -> np.ndarray:
    """(3,) pose moved by `trans_m` in a random direction and turned by ±`rot_rad`."""
    direction = rng.uniform(-np.pi, np.pi)
    sign = rng.choice([-1.0, 1.0])
    out = np.asarray(pose, dtype=np.float64).copy()
    out[:2] += trans_m * np.array([np.cos(direction), np.sin(direction)])
    out[2] = wrap_angle(out[2] + sign * rot_rad)
    return out


def compare_registrars(
    prior: BimPrior,
    model: IfcModel,
    cfg: Config,
    keyframes: list[Keyframe],
    registrars: dict[str, Registrar],
    initial_errors: np.ndarray,
    seed: int,
    surfaces: list[SurfaceModel] | None = None,
) -> list[dict]:
    """One record per (keyframe, initial error, registrar): start and final errors, success, gate, time.

    `initial_errors` (P, 2) are (translation m, rotation rad) levels; rotations are re-paired per keyframe.
    """
    rc = cfg.registration
    surfaces = surfaces if surfaces is not None else build_surface_models(model, rc, seed)
    building = Path(prior.source_file).stem
    rng = np.random.default_rng([seed, 0xC0DE])
    records = []
    for k, key in enumerate(progress(keyframes, desc=f"registering {building}", unit="keyframe")):
        surface = surfaces[key.frame.gt_storey or 0]
        gt = key.frame.gt_pose
        # A fresh pairing of translation and rotation levels per keyframe, so the two marginals are not confounded.
        errors = np.column_stack([initial_errors[:, 0], rng.permutation(initial_errors[:, 1])])
        for trans_m, rot_rad in errors:
            init = perturb(gt, float(trans_m), float(rot_rad), rng)
            for name, registrar in registrars.items():
                result = registrar.register(key.scan_base, surface, init)
                trans_err = float(np.hypot(*(result.pose[:2] - gt[:2])))
                rot_err = float(abs(np.rad2deg(wrap_angle(result.pose[2] - gt[2]))))
                decision = gate_registration(result, init, rc)
                records.append(
                    {
                        "building": building,
                        "keyframe": k,
                        "frame_index": key.frame.index,
                        "registrar": name,
                        "init_trans_m": float(trans_m),
                        "init_rot_deg": float(np.rad2deg(rot_rad)),
                        "final_trans_m": trans_err,
                        "final_rot_deg": rot_err,
                        "success": trans_err < rc.success_trans_m and rot_err < rc.success_rot_deg,
                        "accepted": decision.accepted,
                        "fitness": result.fitness,
                        "inlier_rmse_m": result.inlier_rmse,
                        "degeneracy_ratio": decision.degeneracy_ratio,
                        "converged": result.converged,
                        "time_ms": result.time_ms,
                        "scan_points": len(key.scan_base),
                    }
                )
    return records


def summarize(records: list[dict]) -> list[dict]:
    """Per registrar: success rate, median final errors and time, gate acceptance and the gate's precision."""
    out = []
    for name in dict.fromkeys(r["registrar"] for r in records):
        rows = [r for r in records if r["registrar"] == name]
        accepted = [r for r in rows if r["accepted"]]
        out.append(
            {
                "registrar": name,
                "runs": len(rows),
                "success_rate": sum(r["success"] for r in rows) / len(rows),
                "median_final_trans_m": statistics.median(r["final_trans_m"] for r in rows),
                "median_final_rot_deg": statistics.median(r["final_rot_deg"] for r in rows),
                "median_time_ms": statistics.median(r["time_ms"] for r in rows),
                "p90_time_ms": float(np.percentile([r["time_ms"] for r in rows], 90)),
                "accepted_rate": len(accepted) / len(rows),
                "accepted_success_rate": (sum(r["success"] for r in accepted) / len(accepted)) if accepted else None,
            }
        )
    return out


def _success_by(records: list[dict], name: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    rows = [r for r in records if r["registrar"] == name]
    levels = np.unique(np.round([r[key] for r in rows], 6))
    rates = [np.mean([r["success"] for r in rows if abs(r[key] - level) < 1e-5]) for level in levels]
    return levels, np.asarray(rates)


def plot_basins(records: list[dict], path: str | Path, title: str = "") -> Path:
    """PNG: success rate vs initial translation error and vs initial rotation error, one line per registrar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bimfactor.evaluation.plots import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for name in dict.fromkeys(r["registrar"] for r in records):
        for ax, key in zip(axes, ("init_trans_m", "init_rot_deg"), strict=True):
            levels, rates = _success_by(records, name, key)
            ax.plot(levels, rates, marker="o", label=name)
    axes[0].set_xlabel("initial translation error [m]")
    axes[1].set_xlabel("initial rotation error [deg]")
    axes[0].set_ylabel("success rate (< 5 cm and < 1°)")
    for ax in axes:
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[1].legend(loc="lower left", fontsize=8)
    fig.suptitle(title or "basin of convergence")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120, tight=False)


def benchmark_registration(
    prior: BimPrior,
    model: IfcModel,
    cfg: Config,
    method: str | None = None,
    n_keyframes: int = 10,
    repeats: int = 5,
    trans_m: float = 0.3,
    rot_deg: float = 5.0,
) -> dict:
    """Median and p90 ms of one registration (default voxel, registrar `method`) from 0.3 m / 5° perturbed starts.

    Scan building and the surface's one-off KD-tree are timed separately.
    """
    rc = cfg.registration
    t0 = time.perf_counter()
    surfaces = build_surface_models(model, rc, cfg.seed)
    surface_s = time.perf_counter() - t0
    keyframes = select_keyframes(prior, model, cfg, surfaces, n_keyframes, cfg.seed)
    registrar = make_registrar(rc, method)
    t0 = time.perf_counter()
    for s in surfaces:
        _ = s.nn_tree  # built once per storey
    tree_s = time.perf_counter() - t0
    scan_ms = []
    for key in keyframes:
        t = time.perf_counter()
        frame_scan(key.frame, key.meta, rc)
        scan_ms.append((time.perf_counter() - t) * 1000)
    rng = np.random.default_rng(cfg.seed)
    times, successes = [], []
    for key in keyframes:
        surface = surfaces[key.frame.gt_storey or 0]
        registrar.register(key.scan_base, surface, key.frame.gt_pose)  # warm-up
        for _ in range(repeats):
            init = perturb(key.frame.gt_pose, trans_m, np.deg2rad(rot_deg), rng)
            result = registrar.register(key.scan_base, surface, init)
            times.append(result.time_ms)
            err = result.pose - key.frame.gt_pose
            successes.append(np.hypot(*err[:2]) < rc.success_trans_m and abs(np.rad2deg(wrap_angle(err[2]))) < 1.0)
    return {
        "building": Path(prior.source_file).name,
        "method": registrar.name,
        "scan_voxel_m": rc.scan_voxel_m,
        "keyframes": len(keyframes),
        "runs": len(times),
        "median_ms": statistics.median(times) if times else None,
        "p90_ms": float(np.percentile(times, 90)) if times else None,
        "success_rate": float(np.mean(successes)) if successes else None,
        "median_scan_points": statistics.median(len(k.scan_base) for k in keyframes) if keyframes else None,
        "median_scan_build_ms": statistics.median(scan_ms) if scan_ms else None,
        "surface_build_s": surface_s,
        "kdtree_build_s": tree_s,
        "surface_points": [len(s) for s in surfaces],
    }


def make_registrars(cfg: RegistrationConfig, names: list[str] | None = None) -> dict[str, Registrar]:
    """Registrars by name (default: every one in `REGISTRARS`)."""
    return {name: make_registrar(cfg, name) for name in (names if names is not None else list(REGISTRARS))}


def run_comparison(
    prior_dir: str | Path, out_dir: str | Path, cfg: Config, names: list[str] | None = None
) -> list[dict]:
    """The whole comparison on one prior's building: records.json, summary.json, basins.png, config.yaml.

    Returns the summary (one dict per registrar).
    """
    from bimfactor.io.atomic import write_text_atomic
    from bimfactor.sim.simulate import load_world_inputs

    rc = cfg.registration
    prior, model = load_world_inputs(prior_dir, cfg)
    surfaces = build_surface_models(model, rc, cfg.seed)
    keyframes = select_keyframes(prior, model, cfg, surfaces, rc.compare_keyframes, cfg.seed)
    records = compare_registrars(
        prior, model, cfg, keyframes, make_registrars(rc, names), initial_error_sweep(rc), cfg.seed, surfaces
    )
    summary = summarize(records)
    out = Path(out_dir)
    write_text_atomic(out / "records.json", json.dumps(records, indent=1))
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=1))
    write_text_atomic(out / "config.yaml", cfg.dump_yaml())
    plot_basins(records, out / "basins.png", title=f"basin of convergence: {Path(prior.source_file).name}")
    return summary
