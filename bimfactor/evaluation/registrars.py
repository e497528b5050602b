"""The registrar comparison: basins of convergence on simulated keyframes, per-registrar summaries, and speed.

Each registrar runs from the true pose perturbed by a seeded sweep of start errors and succeeds within
`success_trans_m` and `success_rot_deg`; every run is gated without the ambiguity probes, with them, and with them
plus a calibrated coarse covariance (`calibrated_covariance`), to measure what each check adds.
"""

from __future__ import annotations

import json
import logging
import statistics
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.surfaces import wall_meshes
from bimfactor.config import Config, RegistrationConfig, SensorConfig
from bimfactor.errors import InputError
from bimfactor.progress import progress
from bimfactor.registration.gate import degeneracy_ratio, gate_with_probes
from bimfactor.registration.icp import Registrar, available_registrars, evaluate_pose, make_registrar
from bimfactor.registration.scan import MIN_SCAN_POINTS, frame_scan
from bimfactor.registration.surface import SurfaceModel, build_surface_models
from bimfactor.sim.simulate import build_world, simulate_sequence
from bimfactor.types import Frame, SequenceMeta, wrap_angle

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A frame with ground truth, its sequence metadata, and its registration scan (N, 3) in the base frame."""

    frame: Frame
    meta: SequenceMeta
    scan_base: np.ndarray


def registrable_scan(
    frame: Frame, meta: SequenceMeta, surfaces: list[SurfaceModel], cfg: RegistrationConfig, sensor: SensorConfig
) -> np.ndarray | None:
    """The frame's (N, 3) scan when the gate would call it registrable at the frame's true pose, else None.

    Frames that see no wall within range, or only one direction of walls (degenerate at the true pose), are
    unregistrable: no registrar can succeed there, and the gate rejects them (see `gate_registration`).
    """
    if frame.gt_pose is None or not 0 <= (frame.gt_storey or 0) < len(surfaces):
        return None
    scan = frame_scan(frame, meta, cfg, sensor)
    if len(scan) < MIN_SCAN_POINTS:
        return None
    ev = evaluate_pose(scan, surfaces[frame.gt_storey or 0], frame.gt_pose, cfg)
    ok = ev.fitness >= cfg.min_fitness and degeneracy_ratio(ev.information) >= cfg.min_degeneracy_ratio
    return scan if ok else None


def pick_keyframes(
    sources: Iterable[tuple[Sequence[Frame], SequenceMeta]],
    surfaces: list[SurfaceModel],
    cfg: RegistrationConfig,
    sensor: SensorConfig,
    n: int,
    per_source: int,
    rng: np.random.Generator,
) -> list[Keyframe]:
    """Up to `n` registrable keyframes, at most `per_source` from each (frames, meta) source, in a seeded order."""
    chosen: list[Keyframe] = []
    skipped = 0
    for frames, meta in sources:
        taken = 0
        for i in rng.permutation(len(frames)):
            if taken >= per_source:
                break
            frame = frames[int(i)]
            scan = registrable_scan(frame, meta, surfaces, cfg, sensor)
            if scan is None:
                skipped += 1
                continue
            chosen.append(Keyframe(frame, meta, scan))
            taken += 1
            if len(chosen) == n:
                log.info("%d keyframes chosen (%d frames skipped as unregistrable)", n, skipped)
                return chosen
    log.warning("only %d of %d keyframes are registrable (%d frames skipped)", len(chosen), n, skipped)
    return chosen


def select_keyframes(
    prior: BimPrior, model: IfcModel, cfg: Config, surfaces: list[SurfaceModel], n: int, seed: int
) -> list[Keyframe]:
    """`n` keyframes drawn (seeded) from simulated trajectories whose scans the gate would call registrable."""
    world = build_world(prior, model, cfg, seed)

    def trajectories() -> Iterator[tuple[list[Frame], SequenceMeta]]:
        for trajectory_index in range(cfg.evaluation.num_trajectories):
            sim = simulate_sequence(prior, model, cfg, trajectory_index, seed, progress=False, world=world)
            yield sim.frames, sim.meta

    rng = np.random.default_rng([seed, 0x1CB])
    return pick_keyframes(trajectories(), surfaces, cfg.registration, cfg.sensor, n, max(1, -(-n // 3)), rng)


def sequence_keyframes(
    sequence_dir: str | Path, surfaces: list[SurfaceModel], cfg: Config, n: int, seed: int
) -> list[Keyframe]:
    """`n` registrable keyframes with ground truth from a sequence folder, or from each sequence folder inside it
    (`bimfactor simulate --all` writes k0/ ... k5/), spread evenly over the sequences."""
    from bimfactor.io.sequence import META_FILE, read_sequence

    folder = Path(sequence_dir)
    folders = [folder] if (folder / META_FILE).is_file() else sorted(p.parent for p in folder.glob(f"*/{META_FILE}"))
    if not folders:
        raise InputError(f"{folder}: neither a sequence folder nor a folder of sequence folders")
    sequences = [read_sequence(f) for f in folders]
    if all(s.ground_truth() is None for s in sequences):
        raise InputError(f"{folder}: no frame has ground truth; the comparison needs it")
    rng = np.random.default_rng([seed, 0x1CB])
    per_source = max(1, -(-n // len(sequences)))
    return pick_keyframes(((s, s.meta) for s in sequences), surfaces, cfg.registration, cfg.sensor, n, per_source, rng)


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


def calibrated_covariance(trans_m: float, rot_rad: float, cfg: RegistrationConfig) -> np.ndarray:
    """(3, 3) world-frame covariance of a calibrated coarse pose whose error is `trans_m` and `rot_rad`.

    σ per horizontal axis is trans_m / √2 (the RMS of an error of that length in a random direction), σ_yaw is
    rot_rad; floored at the success thresholds, so an exact start still has a usable covariance.
    """
    sigma_m = max(trans_m / np.sqrt(2.0), cfg.success_trans_m)
    sigma_rad = max(rot_rad, np.deg2rad(cfg.success_rot_deg))
    return np.diag([sigma_m**2, sigma_m**2, sigma_rad**2])


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
    surfaces = surfaces if surfaces is not None else build_surface_models(wall_meshes(model), rc, seed)
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
                decision = gate_with_probes(key.scan_base, surface, result, init, rc)
                coarse = calibrated_covariance(float(trans_m), float(rot_rad), rc)
                decision_coarse = gate_with_probes(key.scan_base, surface, result, init, rc, coarse)
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
                        # The gate without the ambiguity probes: what they add is measured by the difference.
                        "accepted_without_probes": decision.accepted or decision.alternatives > 0,
                        "reasons": decision.reasons,
                        "accepted_coarse": decision_coarse.accepted,
                        "reasons_coarse": decision_coarse.reasons,
                        "fitness": result.fitness,
                        "inlier_rmse_m": result.inlier_rmse,
                        "degeneracy_ratio": decision.degeneracy_ratio,
                        "converged": result.converged,
                        "time_ms": result.time_ms,
                        "probes_ms": decision.probes_ms,
                        "scan_points": len(key.scan_base),
                    }
                )
    return records


def _success_share(rows: list[dict]) -> float | None:
    return sum(r["success"] for r in rows) / len(rows) if rows else None


def summarize(records: list[dict]) -> list[dict]:
    """Per registrar: success rate, median final errors and time, gate acceptance and the gate's precision.

    The gate's precision (share of accepted runs that succeeded) is given with and without the ambiguity probes.
    """
    out = []
    for name in dict.fromkeys(r["registrar"] for r in records):
        rows = [r for r in records if r["registrar"] == name]
        accepted = [r for r in rows if r["accepted"]]
        basic = [r for r in rows if r["accepted_without_probes"]]
        coarse = [r for r in rows if r["accepted_coarse"]]
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
                "accepted_success_rate": _success_share(accepted),
                "accepted_wrong": len(accepted) - sum(r["success"] for r in accepted),
                "accepted_without_probes_rate": len(basic) / len(rows),
                "accepted_without_probes_success_rate": _success_share(basic),
                "accepted_without_probes_wrong": len(basic) - sum(r["success"] for r in basic),
                "accepted_coarse_rate": len(coarse) / len(rows),
                "accepted_coarse_success_rate": _success_share(coarse),
                "accepted_coarse_wrong": len(coarse) - sum(r["success"] for r in coarse),
                "median_probes_ms": statistics.median(r["probes_ms"] for r in basic) if basic else None,
            }
        )
    return out


def format_summary_table(summary: list[dict]) -> str:
    """A Markdown table of `summarize`'s rows: success, median final error and time, and the gate's wrong
    acceptances without the probes → with them → with a calibrated coarse covariance."""
    lines = [
        "| registrar | success | median final error | median time | accepted "
        "| accepted but wrong (no probes → probes → coarse) |",
        "|---|---|---|---|---|---|",
    ]
    for s in summary:
        lines.append(
            f"| {s['registrar']} | {100 * s['success_rate']:.0f} % "
            f"| {100 * s['median_final_trans_m']:.1f} cm, {s['median_final_rot_deg']:.2f}° "
            f"| {s['median_time_ms']:.0f} ms | {100 * s['accepted_rate']:.0f} % "
            f"| {s['accepted_without_probes_wrong']} → {s['accepted_wrong']} → {s['accepted_coarse_wrong']} |"
        )
    return "\n".join(lines)


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
    from bimfactor.io.preview import missing_glyphs_quiet

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
    with missing_glyphs_quiet():
        fig.tight_layout()
    return save_figure(fig, path, dpi=120, tight=False)


def make_registrars(cfg: RegistrationConfig, names: list[str] | None = None) -> dict[str, Registrar]:
    """Registrars by name (default: every one that can run here, see `available_registrars`)."""
    return {name: make_registrar(cfg, name) for name in (names if names is not None else available_registrars())}


def run_comparison(
    prior_dir: str | Path,
    out_dir: str | Path,
    cfg: Config,
    names: list[str] | None = None,
    sequence_dir: str | Path | None = None,
) -> list[dict]:
    """The whole comparison on one prior's building: records.json, summary.json, basins.png, config.yaml.

    Keyframes come from `sequence_dir` (a sequence with ground truth, or a folder of them) when given, else
    from the building's simulated standard trajectories. Returns the summary (one dict per registrar).
    """
    from bimfactor.io.atomic import write_text_atomic
    from bimfactor.sim.simulate import load_world_inputs

    rc = cfg.registration
    prior, model = load_world_inputs(prior_dir, cfg)
    surfaces = build_surface_models(wall_meshes(model), rc, cfg.seed)
    if sequence_dir is None:
        keyframes = select_keyframes(prior, model, cfg, surfaces, rc.compare_keyframes, cfg.seed)
    else:
        keyframes = sequence_keyframes(sequence_dir, surfaces, cfg, rc.compare_keyframes, cfg.seed)
    if not keyframes:
        raise InputError("no registrable keyframe: every frame sees too little wall, or only one direction of it")
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
