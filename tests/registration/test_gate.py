"""The gate: a corridor's unconstrained axis, poor fits and implausible corrections are rejected."""

from __future__ import annotations

import numpy as np

from bimfactor.config import Config
from bimfactor.registration.gate import degeneracy_ratio, gate_registration, translational_information
from bimfactor.registration.icp import RegistrationResult, make_registrar
from bimfactor.registration.scan import voxel_downsample

from .synthetic import corridor_boxes, scan_from, surface_from_boxes


def test_corridor_offset_along_its_axis_is_rejected_as_degenerate(test_config: Config) -> None:
    surface = surface_from_boxes(corridor_boxes(), 100.0, seed=0)
    true_pose = np.array([20.0, 1.0, 0.0])  # mid-corridor, looking along it; both ends are > 6 m away
    scan = voxel_downsample(scan_from(surface_from_boxes(corridor_boxes(), 400.0, seed=1), true_pose), 0.1)
    init = true_pose + np.array([0.5, 0.05, np.deg2rad(2.0)])  # wrong by 0.5 m along the corridor
    rc = test_config.registration
    result = make_registrar(rc).register(scan, surface, init)
    # ICP fits the walls perfectly — across the corridor and in heading — but cannot tell where along it.
    assert abs(result.pose[1] - true_pose[1]) < 0.01 and abs(result.pose[2]) < np.deg2rad(0.2)
    assert abs(result.pose[0] - true_pose[0]) > 0.4
    assert result.fitness > 0.99 and result.inlier_rmse < 0.01
    info_xy = translational_information(result.information)
    assert info_xy[0, 0] < 1e-6 * info_xy[1, 1]  # nothing constrains x
    decision = gate_registration(result, init, rc)
    assert not decision.accepted
    assert decision.degeneracy_ratio < 1e-6
    assert [r for r in decision.reasons if r.startswith("degenerate")] and len(decision.reasons) == 1


def _result(pose, fitness=1.0, rmse=0.01, information=None) -> RegistrationResult:
    info = np.diag([1e4, 1e4, 1e5]) if information is None else information
    pose = np.asarray(pose, float)
    return RegistrationResult("test", pose, np.eye(4), fitness, rmse, 500, info, 5, 1.0, True)


def test_gate_thresholds(test_config: Config) -> None:
    rc = test_config.registration
    init = np.array([1.0, 2.0, 0.0])
    assert gate_registration(_result(init + np.array([0.1, 0.0, 0.01])), init, rc).accepted
    far = gate_registration(_result(init + np.array([rc.max_correction_m + 0.1, 0.0, 0.0])), init, rc)
    assert not far.accepted and far.reasons[0].startswith("correction")
    turned = gate_registration(_result(init + np.array([0, 0, np.deg2rad(rc.max_correction_deg + 1)])), init, rc)
    assert not turned.accepted and abs(turned.correction_deg - rc.max_correction_deg - 1) < 1e-9
    assert not gate_registration(_result(init, fitness=rc.min_fitness - 0.01), init, rc).accepted
    assert not gate_registration(_result(init, rmse=rc.max_rmse_m * 1.1), init, rc).accepted
    assert not gate_registration(_result(init, rmse=float("inf")), init, rc).accepted


def test_degeneracy_ratio_marginalises_yaw() -> None:
    # x and y equally informative, but x strongly coupled with yaw: marginally x is barely constrained.
    H = np.array([[100.0, 0.0, 99.0], [0.0, 100.0, 0.0], [99.0, 0.0, 100.0]])
    assert degeneracy_ratio(H) < 0.03
    assert degeneracy_ratio(np.diag([100.0, 100.0, 1.0])) == 1.0
    assert degeneracy_ratio(np.zeros((3, 3))) == 0.0
