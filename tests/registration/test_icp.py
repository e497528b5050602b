"""Registrars on a hand-made room: every one recovers a known planar offset; the information sees the room."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import Config
from bimfactor.errors import ConfigError, DependencyError
from bimfactor.registration import external
from bimfactor.registration.gate import degeneracy_ratio, gate_registration
from bimfactor.registration.icp import REGISTRARS, available_registrars, make_registrar
from bimfactor.registration.scan import voxel_downsample
from bimfactor.types import wrap_angle

from .synthetic import room_boxes, scan_from, surface_from_boxes

TRUE_POSE = np.array([3.0, 2.0, 0.3])
OFFSET = np.array([0.25, -0.15, np.deg2rad(4.0)])
# KISS-ICP is point-to-point: against 10 cm surface samples it stops about 1 cm short (measured 1.1 cm).
TOLERANCE_M = {"kiss_icp": 0.02}


@pytest.fixture(scope="module")
def room():
    """The room's surface model and a scan of it: another sampling of the same walls, seen from TRUE_POSE."""
    surface = surface_from_boxes(room_boxes(), density_per_m2=100.0, seed=0)
    scan = voxel_downsample(scan_from(surface_from_boxes(room_boxes(), 400.0, seed=1), TRUE_POSE), 0.1)
    return surface, scan


def _errors(pose: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(pose[:2] - TRUE_POSE[:2]))), float(abs(np.rad2deg(wrap_angle(pose[2] - TRUE_POSE[2]))))


def test_default_registrar_recovers_a_planar_offset(room, test_config: Config) -> None:
    surface, scan = room
    registrar = make_registrar(test_config.registration)
    assert registrar.name == test_config.registration.method == "point_to_plane"
    result = registrar.register(scan, surface, TRUE_POSE + OFFSET)
    trans_err, rot_err = _errors(result.pose)
    assert trans_err < 0.01 and rot_err < 0.2
    assert result.converged and result.fitness > 0.99 and result.inlier_rmse < 0.01
    assert 0 < result.iterations <= test_config.registration.max_iterations  # the planar polish's
    np.testing.assert_allclose(result.T[:3, 3], [*result.pose[:2], surface.elevation_m])
    # The room constrains every direction; the information is symmetric positive definite.
    np.testing.assert_allclose(result.information, result.information.T)
    assert np.linalg.eigvalsh(result.information)[0] > 0
    assert degeneracy_ratio(result.information) > 0.2
    assert gate_registration(result, TRUE_POSE + OFFSET, test_config.registration).accepted


@pytest.mark.parametrize("method", sorted(REGISTRARS))
def test_every_registrar_recovers_the_offset(room, test_config: Config, method: str) -> None:
    if method in external.OPTIONAL_MODULES:
        pytest.importorskip(external.OPTIONAL_MODULES[method], reason=f"optional registrar {method} not installed")
    surface, scan = room
    result = make_registrar(test_config.registration, method).register(scan, surface, TRUE_POSE + OFFSET)
    trans_err, rot_err = _errors(result.pose)
    assert trans_err < TOLERANCE_M.get(method, 0.01) and rot_err < 0.2, (method, trans_err, rot_err)
    assert result.method == method


def test_empty_scan_fails_cleanly(room, test_config: Config) -> None:
    surface, _ = room
    for method in available_registrars():
        result = make_registrar(test_config.registration, method).register(np.zeros((0, 3)), surface, TRUE_POSE)
        assert result.fitness == 0.0 and not result.converged
        assert not gate_registration(result, TRUE_POSE, test_config.registration).accepted


def test_unknown_registrar_is_a_config_error(test_config: Config) -> None:
    with pytest.raises(ConfigError, match="unknown registrar"):
        make_registrar(test_config.registration, "ndt")


def test_missing_optional_registrar_is_a_dependency_error(test_config: Config, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(external.OPTIONAL_MODULES, "small_gicp", "bimfactor_no_such_module")
    assert "small_gicp" not in available_registrars()
    with pytest.raises(DependencyError, match=r"pip install 'bimfactor\[registrars\]'"):
        make_registrar(test_config.registration, "small_gicp")


def test_planar_multistart_ends_where_the_planar_solver_does_from_each_start(room, test_config: Config) -> None:
    """Every start of the batched solve (the ambiguity probes' solver) ends where `PlanarIcp` ends from it alone, on
    the same crop: the batch changes the cost, not the answer (a start with too few matches stays put)."""
    from bimfactor.registration.icp import PlanarIcp, planar_multistart, scan_reach

    surface, scan = room
    rc = test_config.registration
    local = surface.facing(TRUE_POSE[:2], scan_reach(scan) + rc.max_correspondence_m + rc.crop_margin_m + 1.0)
    starts = TRUE_POSE + np.array(
        [[0.25, -0.15, 0.07], [-0.3, 0.2, -0.05], [0.0, 0.0, 0.15], [0.1, 0.4, 0.0], [60.0, 60.0, 0.0]]
    )
    ends = planar_multistart(scan, local, starts, surface.elevation_m, rc)
    np.testing.assert_allclose(ends[-1], starts[-1], atol=1e-12)  # far off the room: nothing matches, nothing moves
    alone = PlanarIcp(rc, near_cells=None)
    for start, end in zip(starts[:-1], ends[:-1], strict=True):
        want = alone.register(scan, local, start).pose
        np.testing.assert_allclose(end[:2], want[:2], atol=2e-3)
        assert abs(wrap_angle(end[2] - want[2])) < np.deg2rad(0.05)
    assert max(_errors(end)[0] for end in ends[:-1]) < 0.01  # and those starts all reach the truth
