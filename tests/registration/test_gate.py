"""The gate: a corridor's unconstrained axis, poor fits, implausible corrections and wrong bays are rejected."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import Config
from bimfactor.registration.gate import (
    degeneracy_ratio,
    gate_registration,
    gate_with_probes,
    probe_starts,
    translational_information,
)
from bimfactor.registration.icp import RegistrationResult, make_registrar
from bimfactor.registration.scan import voxel_downsample

from .synthetic import bay_corridor_boxes, corridor_boxes, scan_from, surface_from_boxes


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


def _bay_corridor(bay_m: float):
    """Surface model of a corridor with pilasters every `bay_m`, and a scan from mid-corridor."""
    surface = surface_from_boxes(bay_corridor_boxes(bay_m), 100.0, seed=0)
    true_pose = np.array([19.5, 1.2, 0.0])
    scan = voxel_downsample(scan_from(surface_from_boxes(bay_corridor_boxes(bay_m), 400.0, seed=1), true_pose), 0.1)
    return surface, scan, true_pose


def test_wrong_bay_of_a_symmetric_corridor_is_rejected_as_ambiguous(test_config: Config) -> None:
    rc = test_config.registration
    bay_m = 3.0
    surface, scan, true_pose = _bay_corridor(bay_m)
    registrar = make_registrar(rc)
    init = true_pose + np.array([2.2, 0.1, np.deg2rad(2.0)])  # the coarse pose is 2.2 m off along the corridor
    result = registrar.register(scan, surface, init)
    # ICP settles one bay ahead: well constrained, a good fit, a plausible correction, and wrong by 3 m.
    np.testing.assert_allclose(result.pose, true_pose + np.array([bay_m, 0.0, 0.0]), atol=0.01)
    assert result.fitness > 0.98 and result.inlier_rmse < 0.02
    assert gate_registration(result, init, rc).accepted  # fit, correction and degeneracy cannot tell the bays apart
    # A coarse pose whose σ along the corridor (2 m) matches its error allows both bays; probing that region
    # finds the true bay's fit, as good as the wrong one.
    coarse = np.diag([2.0**2, 0.3**2, np.deg2rad(5.0) ** 2])
    assert gate_registration(result, init, rc, coarse).accepted  # the correction itself is consistent with it
    decision = gate_with_probes(scan, surface, result, init, rc, coarse)
    assert not decision.accepted and decision.alternatives >= 1
    assert len(decision.reasons) == 1 and decision.reasons[0].startswith("ambiguous")
    # A start in the right bay whose coarse pose rules the neighbours out is accepted, probes and all.
    init = true_pose + np.array([0.4, 0.1, np.deg2rad(2.0)])
    result = registrar.register(scan, surface, init)
    assert np.hypot(*(result.pose[:2] - true_pose[:2])) < 0.01
    decision = gate_with_probes(scan, surface, result, init, rc, np.diag([0.3**2, 0.3**2, 0.01]))
    assert decision.accepted and decision.alternatives == 0 and decision.probes_ms > 0


def test_probes_around_the_result_catch_a_neighbouring_bay_without_covariance(test_config: Config) -> None:
    rc = test_config.registration
    bay_m = 1.2  # closer than twice the probe step: the probes around the result reach the next basin
    surface, scan, true_pose = _bay_corridor(bay_m)
    registrar = make_registrar(rc)
    init = true_pose + np.array([0.8, 0.1, np.deg2rad(2.0)])
    result = registrar.register(scan, surface, init)
    np.testing.assert_allclose(result.pose, true_pose + np.array([bay_m, 0.0, 0.0]), atol=0.01)
    assert gate_registration(result, init, rc).accepted
    decision = gate_with_probes(scan, surface, result, init, rc)
    assert not decision.accepted and decision.reasons[0].startswith("ambiguous")
    no_probes = rc.model_copy(update={"ambiguity_probes": False})
    without = gate_with_probes(scan, surface, result, init, no_probes)
    assert without.accepted and without.alternatives == 0 and without.probes_ms == 0.0


def test_probe_starts_follow_the_information_and_the_coarse_covariance(test_config: Config) -> None:
    rc = test_config.registration
    pose = np.array([5.0, 2.0, 0.5])
    info = np.diag([1e2, 1e6, 1e5])  # x is the weak axis
    starts = probe_starts(_result(pose, information=info), rc)
    assert starts.shape == (6, 3)
    np.testing.assert_allclose(np.abs(starts[:2, 0] - pose[0]), rc.ambiguity_probe_m)  # weak axis first
    np.testing.assert_allclose(starts[:2, 1:], np.tile(pose[1:], (2, 1)))
    np.testing.assert_allclose(np.abs(starts[2:4, 1] - pose[1]), rc.ambiguity_probe_m)
    np.testing.assert_allclose(np.abs(starts[4:, 2] - pose[2]), np.deg2rad(rc.ambiguity_probe_deg))
    # A coarse pose more uncertain than the probe step along x and in yaw (not along y) adds starts around it.
    init = np.array([4.0, 2.5, 0.4])
    coarse = np.diag([3.0**2, 0.1**2, np.deg2rad(30.0) ** 2])
    wide = probe_starts(_result(pose, information=info), rc, init, coarse)
    assert wide.shape == (10, 3)
    np.testing.assert_allclose(wide[:6], starts)
    np.testing.assert_allclose(wide[6:8], [[init[0] + 3.0, *init[1:]], [init[0] - 3.0, *init[1:]]], atol=1e-9)
    np.testing.assert_allclose(wide[8:, 2], init[2] + np.deg2rad([30.0, -30.0]))
    assert probe_starts(_result(pose, information=info), rc, init, np.diag([0.1, 0.1, 0.01])).shape == (6, 3)


def test_correction_must_be_consistent_with_the_coarse_covariance(test_config: Config) -> None:
    rc = test_config.registration
    init = np.array([1.0, 2.0, 0.0])
    moved = _result(init + np.array([0.5, 0.0, 0.0]))
    assert gate_registration(moved, init, rc, np.diag([0.5**2, 0.5**2, 0.1**2])).correction_chi2 == pytest.approx(1.0)
    tight = gate_registration(moved, init, rc, np.diag([0.1**2, 0.1**2, 0.1**2]))
    assert not tight.accepted and tight.correction_chi2 == pytest.approx(25.0)
    assert tight.reasons == [f"inconsistent with the coarse pose: χ² 25.0 > {rc.consistency_chi2:.1f}"]
    assert gate_registration(moved, init, rc).correction_chi2 is None
