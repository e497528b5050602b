"""Gating: accept a registration only when it fits well, moved plausibly, and the scene constrains every direction.

A corridor or a single wall leaves a horizontal direction unconstrained with a perfect fit, so the degeneracy check
reads the translational information, not fitness or RMSE. A scene can also hold several good fits nearby (identical
bays, mirrored rooms): `gate_with_probes` re-registers from probe starts around the result and rejects it when a probe
ends elsewhere with a fit at least as good; with the coarse pose's covariance, the correction must pass a χ² test and
places it rules out do not count as alternatives. docs/registration.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from bimfactor.config import RegistrationConfig
from bimfactor.registration.icp import (
    RegistrationResult,
    evaluate_planar,
    planar_multistart,
    scan_in_world,
    scan_reach,
    thin,
)
from bimfactor.registration.surface import SurfaceModel
from bimfactor.types import wrap_angle

# Probes settle at 10 × the registrars' step tolerance (1 mm, 0.006°): they only tell places 10 cm apart.
PROBE_TOLERANCE = 10.0


@dataclass
class GateDecision:
    """Whether a registration is accepted, and why not; corrections are relative to the initial pose.

    `correction_chi2` is set when the coarse pose's covariance was given; `alternatives` counts the probes
    that found another equally good fit (0 when no probe ran), `probes_ms` is the time they took.
    """

    accepted: bool
    correction_m: float
    correction_deg: float
    degeneracy_ratio: float
    reasons: list[str] = field(default_factory=list)
    correction_chi2: float | None = None
    alternatives: int = 0
    probes_ms: float = 0.0


def translational_information(information: np.ndarray) -> np.ndarray:
    """(2, 2) information on x, y with yaw marginalised out (Schur complement of the (3, 3) matrix)."""
    H = np.asarray(information, dtype=np.float64)
    if H[2, 2] <= 0:
        return H[:2, :2].copy()
    return H[:2, :2] - np.outer(H[:2, 2], H[2, :2]) / H[2, 2]


def degeneracy_ratio(information: np.ndarray) -> float:
    """λmin / λmax of the translational information: ≈ 0 when one horizontal direction is unconstrained."""
    eig = np.linalg.eigvalsh(translational_information(information))
    if not np.all(np.isfinite(eig)) or eig[-1] <= 0:
        return 0.0
    return float(max(eig[0], 0.0) / eig[-1])


def correction(pose: np.ndarray, T_world_base_init: np.ndarray) -> np.ndarray:
    """(3,) world-frame x, y, yaw from the initial pose to `pose` (yaw wrapped)."""
    delta = np.asarray(pose, dtype=np.float64) - np.asarray(T_world_base_init, dtype=np.float64)
    delta[2] = wrap_angle(delta[2])
    return delta


def correction_chi2(pose: np.ndarray, T_world_base_init: np.ndarray, covariance_world: np.ndarray) -> float:
    """χ² of the correction from the initial pose to `pose` under the coarse pose's (3, 3) world-frame covariance."""
    delta = correction(pose, T_world_base_init)
    C = np.asarray(covariance_world, dtype=np.float64)
    if not np.all(np.isfinite(C)):
        return float("inf")
    return float(delta @ np.linalg.pinv(C, hermitian=True) @ delta)


def gate_registration(
    result: RegistrationResult,
    T_world_base_init: np.ndarray,
    cfg: RegistrationConfig,
    covariance_world: np.ndarray | None = None,
) -> GateDecision:
    """Accept `result` only if fitness, inlier RMSE, the correction from the (3,) initial pose and degeneracy pass.

    With the coarse pose's (3, 3) world-frame covariance, the correction's χ² must also stay within
    `cfg.consistency_chi2`.
    """
    delta = correction(result.pose, T_world_base_init)
    correction_m = float(np.hypot(delta[0], delta[1]))
    correction_deg = float(abs(np.rad2deg(delta[2])))
    ratio = degeneracy_ratio(result.information)
    reasons = []
    if result.fitness < cfg.min_fitness:
        reasons.append(f"fitness {result.fitness:.2f} < {cfg.min_fitness:.2f}")
    if not result.inlier_rmse <= cfg.max_rmse_m:
        reasons.append(f"inlier RMSE {result.inlier_rmse:.3f} m > {cfg.max_rmse_m:.3f} m")
    if correction_m > cfg.max_correction_m:
        reasons.append(f"correction {correction_m:.2f} m > {cfg.max_correction_m:.2f} m")
    if correction_deg > cfg.max_correction_deg:
        reasons.append(f"correction {correction_deg:.1f}° > {cfg.max_correction_deg:.1f}°")
    if ratio < cfg.min_degeneracy_ratio:
        reasons.append(f"degenerate: λmin/λmax {ratio:.3f} < {cfg.min_degeneracy_ratio:.3f}")
    chi2 = None
    if covariance_world is not None:
        chi2 = correction_chi2(result.pose, T_world_base_init, covariance_world)
        if not chi2 <= cfg.consistency_chi2:
            reasons.append(f"inconsistent with the coarse pose: χ² {chi2:.1f} > {cfg.consistency_chi2:.1f}")
    return GateDecision(not reasons, correction_m, correction_deg, ratio, reasons, chi2)


def _both_ways(center: np.ndarray, axes: np.ndarray, steps_m: np.ndarray, step_rad: float | None) -> list[np.ndarray]:
    """Starts `center` ± step along each translational axis with a step, and ± `step_rad` in yaw (if given)."""
    offsets = [
        np.array([*(sign * step * axis), 0.0]) for axis, step in zip(axes, steps_m, strict=True) for sign in (1, -1)
    ]
    if step_rad is not None:
        offsets += [np.array([0.0, 0.0, sign * step_rad]) for sign in (1.0, -1.0)]
    return [np.asarray(center, dtype=np.float64) + offset for offset in offsets]


def probe_starts(
    result: RegistrationResult,
    cfg: RegistrationConfig,
    T_world_base_init: np.ndarray | None = None,
    covariance_world: np.ndarray | None = None,
) -> np.ndarray:
    """(P, 3) probe starts: `result.pose` ± `ambiguity_probe_m` along each eigenvector of its translational information
    (the least constrained first) and ± `ambiguity_probe_deg` in yaw; given the coarse covariance, also the initial
    pose ± the coarse σ along each axis whose σ exceeds the probe step (identical bays farther apart than a probe).
    """
    info_xy = translational_information(result.information)
    axes = np.linalg.eigh(info_xy)[1].T if np.all(np.isfinite(info_xy)) else np.eye(2)
    step_rad = float(np.deg2rad(cfg.ambiguity_probe_deg))
    starts = _both_ways(result.pose, axes, np.full(2, cfg.ambiguity_probe_m), step_rad)
    if covariance_world is not None and T_world_base_init is not None:
        C = np.asarray(covariance_world, dtype=np.float64)
        if np.all(np.isfinite(C)):
            sigma_m = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", axes, C[:2, :2], axes), 0.0))
            wide = sigma_m > cfg.ambiguity_probe_m
            sigma_rad = float(np.sqrt(max(C[2, 2], 0.0)))
            starts += _both_ways(
                T_world_base_init, axes[wide], sigma_m[wide], sigma_rad if sigma_rad > step_rad else None
            )
    out = np.asarray(starts)
    out[:, 2] = wrap_angle(out[:, 2])
    return out


@dataclass(frozen=True)
class Fit:
    """A planar pose with its fit: fitness (share of scan points matched) and point-to-plane inlier RMSE."""

    pose: np.ndarray
    fitness: float
    inlier_rmse: float


def elsewhere(pose: np.ndarray, reference_pose: np.ndarray, cfg: RegistrationConfig) -> bool:
    """Whether a (3,) pose is another place than `reference_pose`: farther than the ambiguity separation."""
    delta = correction(pose, reference_pose)
    return bool(
        np.hypot(delta[0], delta[1]) > cfg.ambiguity_separation_m
        or abs(np.rad2deg(delta[2])) > cfg.ambiguity_separation_deg
    )


def is_alternative(probe: Fit | RegistrationResult, result: Fit | RegistrationResult, cfg: RegistrationConfig) -> bool:
    """Whether a probe's registration ended at another place with a fit at least as good as `result`'s."""
    as_good = (
        probe.fitness >= result.fitness - cfg.ambiguity_fitness_margin
        and probe.inlier_rmse <= result.inlier_rmse * cfg.ambiguity_rmse_ratio
    )
    return elsewhere(probe.pose, result.pose, cfg) and as_good


def probe_ends(
    scan: np.ndarray, surface: SurfaceModel, result_pose: np.ndarray, starts: np.ndarray, cfg: RegistrationConfig
) -> np.ndarray:
    """(P, 3) poses where the planar solver ends from each (P, 3) start (`planar_multistart`). The starts around the
    result share one crop of the storey facing it; each start farther out (the coarse pose's region) gets its own,
    facing that start, as a registration from there would see the surface."""
    center = np.asarray(result_pose, dtype=np.float64)
    offsets = np.hypot(*(starts[:, :2] - center[:2]).T)
    around = offsets <= cfg.ambiguity_probe_m + 1e-9
    groups = [(center[:2], np.flatnonzero(around))] + [(starts[i, :2], np.array([i])) for i in np.flatnonzero(~around)]
    reach = scan_reach(scan) + max(cfg.max_correspondence_m, cfg.final_correspondence_m) + cfg.crop_margin_m
    ends = np.array(starts, dtype=np.float64)
    for xy, members in groups:
        if len(members):
            spread = float(np.max(np.hypot(*(starts[members, :2] - xy).T)))
            local = surface.facing(xy, reach + spread)
            ends[members] = planar_multistart(scan, local, starts[members], surface.elevation_m, cfg, PROBE_TOLERANCE)
    return ends


def fit_at(scan: np.ndarray, surface: SurfaceModel, pose: np.ndarray, cfg: RegistrationConfig) -> Fit:
    """The (N, 3) scan's fit at a (3,) pose, scored as registrations are (`evaluate_planar` at
    `final_correspondence_m` against the storey seen from there)."""
    visible = surface.facing_near(scan_in_world(scan, pose), 1, pose[:2])
    ev = evaluate_planar(scan, visible, pose, surface.elevation_m, cfg.final_correspondence_m, cfg.noise_sigma_m)
    return Fit(np.asarray(pose, dtype=np.float64), ev.fitness, ev.inlier_rmse)


def gate_with_probes(
    scan_base: np.ndarray,
    surface: SurfaceModel,
    result: RegistrationResult,
    T_world_base_init: np.ndarray,
    cfg: RegistrationConfig,
    covariance_world: np.ndarray | None = None,
) -> GateDecision:
    """`gate_registration`, then (when it accepts and `cfg.ambiguity_probes`) the ambiguity check by probes.

    `scan_base` (N, 3) and `surface` are the ones that produced `result`. The planar solver runs from each of
    `probe_starts` on `ambiguity_probe_points` of the scan (`probe_ends`; whichever registrar produced the result,
    the basins are the surface's); a probe that ends at another place with as good a fit as the result's
    (`fit_at`, `is_alternative`) makes the result ambiguous, unless the coarse pose's covariance (when given) rules
    that place out by the χ² test.
    """
    decision = gate_registration(result, T_world_base_init, cfg, covariance_world)
    if not (decision.accepted and cfg.ambiguity_probes):
        return decision
    t0 = time.perf_counter()
    scan = np.asarray(scan_base, dtype=np.float64)
    starts = probe_starts(result, cfg, T_world_base_init, covariance_world)
    ends = probe_ends(thin(scan, cfg.ambiguity_probe_points), surface, result.pose, starts, cfg)
    # Only the ends elsewhere are scored (most probes come back to the result), on the whole scan as the result was:
    # on a few hundred points, RMSEs of a few millimetres differ by chance more than the margin allows.
    ends = [end for end in ends if elsewhere(end, result.pose, cfg)]
    if covariance_world is not None:
        ends = [e for e in ends if correction_chi2(e, T_world_base_init, covariance_world) <= cfg.consistency_chi2]
    fits = (fit_at(scan, surface, end, cfg) for end in ends)
    alternatives = [fit for fit in fits if is_alternative(fit, result, cfg)]
    decision.probes_ms = (time.perf_counter() - t0) * 1000
    decision.alternatives = len(alternatives)
    if alternatives:
        nearest = min(alternatives, key=lambda a: float(np.hypot(*correction(a.pose, result.pose)[:2])))
        delta = correction(nearest.pose, result.pose)
        decision.accepted = False
        decision.reasons.append(
            f"ambiguous: {len(alternatives)} probes found as good a fit elsewhere "
            f"(nearest {np.hypot(delta[0], delta[1]):.2f} m, {abs(np.rad2deg(delta[2])):.1f}° away)"
        )
    return decision
