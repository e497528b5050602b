"""Gating: accept a registration only when it fits well, moved plausibly, and the scene constrains every direction.

A featureless corridor (or a single visible wall) leaves one horizontal direction unconstrained: ICP then
"converges" wherever it started along that direction with a perfect fit, so fitness and RMSE cannot catch
it. The degeneracy check looks at the translational information instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bimfactor.config import RegistrationConfig
from bimfactor.registration.icp import RegistrationResult
from bimfactor.types import wrap_angle


@dataclass
class GateDecision:
    """Whether a registration is accepted, and why not; corrections are relative to the initial pose."""

    accepted: bool
    correction_m: float
    correction_deg: float
    degeneracy_ratio: float
    reasons: list[str] = field(default_factory=list)


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


def gate_registration(
    result: RegistrationResult, T_world_base_init: np.ndarray, cfg: RegistrationConfig
) -> GateDecision:
    """Accept `result` only if fitness, inlier RMSE, the correction from the (3,) initial pose and degeneracy pass."""
    init = np.asarray(T_world_base_init, dtype=np.float64)
    correction_m = float(np.hypot(*(result.pose[:2] - init[:2])))
    correction_deg = float(abs(np.rad2deg(wrap_angle(result.pose[2] - init[2]))))
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
    return GateDecision(not reasons, correction_m, correction_deg, ratio, reasons)
