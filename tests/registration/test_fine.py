"""The coarse-to-fine stage: corrections on simulated paper-floor keyframes, bad depth, the factor's information."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from bimfactor.backend.factors import X, covariance_body_to_world, information_pose_factor
from bimfactor.config import Config
from bimfactor.evaluation.registrars import perturb
from bimfactor.registration.fine import FineRegistration, factor_information, surface_models_for
from bimfactor.registration.scan import frame_scan
from bimfactor.registration.surface import SurfaceModel
from bimfactor.types import se2_to_matrix, wrap_angle

from ..sim.conftest import Building

START_TRANS_M, START_ROT_DEG = 0.3, 5.0
# A coarse pose whose σ matches that start error.
COARSE_COVARIANCE = np.diag([0.3**2, 0.3**2, np.deg2rad(5.0) ** 2])


@pytest.fixture(scope="module")
def fine(paper_floor: Building, keyframes_and_surfaces) -> FineRegistration:
    _, surfaces = keyframes_and_surfaces
    return FineRegistration(surfaces, paper_floor.cfg.registration, paper_floor.cfg.sensor)


def _is_symmetric_positive_definite(matrix: np.ndarray) -> bool:
    symmetric = np.allclose(matrix, matrix.T, rtol=0, atol=1e-9 * np.abs(matrix).max())
    return bool(symmetric and np.linalg.eigvalsh(matrix)[0] > 0)


def test_perturbed_mode_pose_is_corrected_and_accepted(fine: FineRegistration, keyframes_and_surfaces) -> None:
    keyframes, _ = keyframes_and_surfaces
    rng = np.random.default_rng(11)
    for key in keyframes:
        gt = key.frame.gt_pose
        start = perturb(gt, START_TRANS_M, np.deg2rad(START_ROT_DEG), rng)
        out = fine.register(key.frame, key.meta, start, key.frame.gt_storey, COARSE_COVARIANCE)
        assert out.accepted, (key.frame.index, out.reason)
        assert out.reasons == [] and out.reason == ""
        assert np.hypot(*(out.pose[:2] - gt[:2])) < 0.05
        assert abs(np.rad2deg(wrap_angle(out.pose[2] - gt[2]))) < 1.0
        np.testing.assert_array_equal(out.start_pose, start)
        assert out.storey == key.frame.gt_storey and out.scan_points == len(key.scan_base)
        assert _is_symmetric_positive_definite(out.information_body)
        assert out.gate is not None and out.gate.alternatives == 0 and out.gate.correction_chi2 is not None
        assert out.time_ms >= out.registration.time_ms > 0


def test_scan_is_built_once_per_frame_and_shared_by_the_modes(fine: FineRegistration, keyframes_and_surfaces) -> None:
    keyframes, _ = keyframes_and_surfaces
    key = keyframes[0]
    scan = fine.scan(key.frame, key.meta)
    np.testing.assert_array_equal(scan, key.scan_base)
    assert fine.scan(key.frame, key.meta) is scan
    rng = np.random.default_rng(3)
    for _ in range(2):  # two modes near the truth
        start = perturb(key.frame.gt_pose, 0.2, np.deg2rad(3.0), rng)
        assert fine.register_scan(scan, start, key.frame.gt_storey).accepted


@pytest.mark.parametrize("depth", ["nan", "zeros", "empty", "flat"])
def test_unusable_depth_is_not_accepted_and_never_raises(fine: FineRegistration, keyframes_and_surfaces, depth) -> None:
    keyframes, _ = keyframes_and_surfaces
    key = keyframes[0]
    image = {
        "nan": np.full_like(key.frame.depth_m, np.nan),
        "zeros": np.zeros_like(key.frame.depth_m),
        "empty": np.zeros((0, 0), np.float32),
        "flat": key.frame.depth_m.reshape(-1),
    }[depth]
    frame = dataclasses.replace(key.frame, index=10_000 + len(depth), depth_m=image)
    start = key.frame.gt_pose + np.array([0.1, 0.0, 0.0])
    out = fine.register(frame, key.meta, start, key.frame.gt_storey)
    assert not out.accepted
    assert out.reasons == ["scan has 0 points (< 100)"]
    np.testing.assert_array_equal(out.pose, start)
    np.testing.assert_array_equal(out.information_body, np.zeros((3, 3)))
    assert out.registration is None and out.gate is None


def test_bad_pose_or_storey_is_not_accepted(fine: FineRegistration, keyframes_and_surfaces) -> None:
    keyframes, _ = keyframes_and_surfaces
    key = keyframes[0]
    assert fine.register_scan(key.scan_base, np.array([np.nan, 0.0, 0.0])).reasons == ["the start pose is not finite"]
    out = fine.register_scan(key.scan_base, key.frame.gt_pose, storey=len(fine.surfaces))
    assert not out.accepted and out.reason.startswith("no surface model for storey")


def test_submap_of_two_frames_lies_on_the_walls(paper_floor: Building, keyframes_and_surfaces) -> None:
    keyframes, surfaces = keyframes_and_surfaces
    cfg = paper_floor.cfg.registration.model_copy(update={"submap_keyframes": 2})
    two = FineRegistration(surfaces, cfg, paper_floor.cfg.sensor)
    a, b = keyframes[0], keyframes[1]
    # Any two frames of one storey will do when the poses that place them are their true ones.
    previous = dataclasses.replace(b.frame, index=-1, timestamp_s=-1.0)
    submap = two.scan(a.frame, a.meta, recent=[previous], recent_poses=np.stack([b.frame.gt_pose, a.frame.gt_pose]))
    single = frame_scan(a.frame, a.meta, cfg, paper_floor.cfg.sensor)
    from scipy.spatial import cKDTree

    assert (cKDTree(single).query(submap)[0] > 0.2).sum() > 100  # the other frame's points are in it
    surface = surfaces[a.frame.gt_storey]
    T = se2_to_matrix(a.frame.gt_pose, surface.elevation_m)
    world = submap @ T[:3, :3].T + T[:3, 3]
    _, nearest = surface.nn_tree.query(world)
    point_to_plane = np.abs(np.einsum("ij,ij->i", surface.normals[nearest], world - surface.points[nearest]))
    assert np.median(point_to_plane) < 0.02  # depth noise; one frame misplaced by the other's pose would be metres
    assert two.register(a.frame, a.meta, a.frame.gt_pose, a.frame.gt_storey).scan_points == len(single)


def test_factor_information_is_the_floored_covariance_in_gtsam_body_frame(test_config: Config) -> None:
    rc = test_config.registration
    yaw = 0.7
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    # World-frame ICP information: weak along the robot's heading, strong across it.
    H_world = R @ np.diag([1e3, 1e7, 1e6]) @ R.T
    info_body = factor_information(H_world, yaw, rc)
    assert _is_symmetric_positive_definite(info_body)
    floor = np.diag([rc.factor_min_sigma_m**2, rc.factor_min_sigma_m**2, np.deg2rad(rc.factor_min_sigma_deg) ** 2])
    expected_world = np.linalg.inv(H_world) + floor
    # What GTSAM makes of the factor: a lone prior's marginal, rotated back to world (x, y, yaw).
    pose = np.array([2.0, -1.0, yaw])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(information_pose_factor(0, pose, info_body))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose2(*pose))
    marginal = gtsam.Marginals(graph, values).marginalCovariance(X(0))
    np.testing.assert_allclose(covariance_body_to_world(marginal, yaw), expected_world, rtol=1e-6, atol=1e-12)
    # A corridor: no information along one axis stays none, the others are floored.
    singular = factor_information(np.diag([0.0, 1e7, 1e6]), 0.0, rc)
    assert abs(singular[0, 0]) < 1e-9 and np.linalg.eigvalsh(singular)[0] > -1e-9
    np.testing.assert_allclose(singular[1, 1], 1 / (1e-7 + rc.factor_min_sigma_m**2))


def test_surface_models_are_built_once_per_prior(paper_floor: Building) -> None:
    first = FineRegistration.for_prior(paper_floor.prior, paper_floor.cfg)
    again = FineRegistration.for_prior(paper_floor.prior, paper_floor.cfg)
    assert again.surfaces is first.surfaces
    assert all(isinstance(s, SurfaceModel) for s in first.surfaces)
    assert len(first.surfaces) == len(paper_floor.prior.storeys)
    denser = paper_floor.cfg.model_copy(
        update={"registration": paper_floor.cfg.registration.model_copy(update={"surface_density_per_m2": 150.0})}
    )
    assert surface_models_for(paper_floor.prior, denser) is not first.surfaces


def test_the_fine_stage_needs_the_prior_alone_not_its_ifc(paper_floor: Building, tmp_path) -> None:
    """The prior stores its wall meshes: a saved and reloaded prior whose IFC file is gone gives the same samples."""
    import dataclasses

    from bimfactor.bim.prior import BimPrior

    paper_floor.prior.save(tmp_path / "prior")
    moved = dataclasses.replace(BimPrior.load(tmp_path / "prior"), source_file=str(tmp_path / "gone.ifc"))
    moved = dataclasses.replace(moved, source_sha256="f" * 64)  # another building for the cache
    reloaded = FineRegistration.for_prior(moved, paper_floor.cfg).surfaces
    built = FineRegistration.for_prior(paper_floor.prior, paper_floor.cfg).surfaces
    assert len(reloaded) == len(built) and sum(map(len, built)) > 1000
    for a, b in zip(reloaded, built, strict=True):
        np.testing.assert_array_equal(a.points, b.points)
