"""Whole simulated sequences: frames and metadata, reproducibility, as-built worlds, and loading the inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bimfactor.errors import InputError
from bimfactor.sim.simulate import SimResult, load_world_inputs, simulate_sequence
from bimfactor.types import CameraIntrinsics, se2_between

from .conftest import Building, config_with

SMALL_CAMERA = ["sim.camera.width=64", "sim.camera.height=48"]


@pytest.fixture(scope="module")
def sequence(paper_floor: Building) -> SimResult:
    return simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 1, seed=0, progress=False)


def test_sequence_frames_and_meta(paper_floor: Building, sequence: SimResult) -> None:
    cfg = paper_floor.cfg
    cam = cfg.sim.camera
    meta, frames, trajectory = sequence.meta, sequence.frames, sequence.trajectory
    assert len(frames) == cfg.evaluation.trajectory_length
    assert meta.source == "sim" and meta.prior_sha256 == paper_floor.prior.source_sha256
    assert meta.intrinsics == CameraIntrinsics.from_hfov(cam.width, cam.height, cam.hfov_deg)
    assert meta.T_base_camera.shape == (4, 4)
    assert meta.extras["trajectory_index"] == 1 and meta.extras["seed"] == 0
    assert meta.extras["as_built_changes"] == []
    json.dumps(meta.extras)  # plain data, ready for the sequence writer
    ids = {rec["id"] for rec in meta.instances}
    for i, frame in enumerate(frames):
        assert frame.index == i and frame.gt_storey == trajectory.storey_index
        assert frame.rgb.shape == (cam.height, cam.width, 3) and frame.rgb.dtype == np.uint8
        assert frame.depth_m.shape == (cam.height, cam.width) and frame.depth_m.dtype == np.float32
        assert frame.instance_ids.dtype == np.int32
        assert set(np.unique(frame.instance_ids).tolist()) <= ids | {-1}
        np.testing.assert_array_equal(frame.gt_pose, trajectory.keyframe_poses[i])
    np.testing.assert_array_equal(frames[0].odom_pose, [0.0, 0.0, 0.0])
    assert np.all(np.diff([f.timestamp_s for f in frames]) > 0)
    # Odometry drifts, but each increment stays close to the true one.
    gt = np.asarray([f.gt_pose for f in frames])
    odom = np.asarray([f.odom_pose for f in frames])
    error = se2_between(odom[:-1], odom[1:]) - se2_between(gt[:-1], gt[1:])
    assert 0 < np.abs(error[:, :2]).max() < 0.5


def test_sequence_reproducible(paper_floor: Building, config_overrides: list[str]) -> None:
    cfg = config_with(config_overrides, *SMALL_CAMERA)
    first, again, other = (
        simulate_sequence(paper_floor.prior, paper_floor.model, cfg, 2, seed=s, progress=False) for s in (0, 0, 1)
    )
    for a, b in zip(first.frames, again.frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m, equal_nan=True)
        assert np.array_equal(a.odom_pose, b.odom_pose) and np.array_equal(a.instance_ids, b.instance_ids)
    assert not np.array_equal(first.frames[5].gt_pose, other.frames[5].gt_pose)


def test_as_built_sequence_drives_around_the_clutter(paper_floor: Building, config_overrides: list[str]) -> None:
    overrides = [*SMALL_CAMERA, "sim.as_built.clutter_count=5", "sim.as_built.moved_fraction=0.3"]
    cfg = config_with(config_overrides, *overrides)
    result = simulate_sequence(paper_floor.prior, paper_floor.model, cfg, 0, seed=0, progress=False)
    clutter = [c for c in result.meta.extras["as_built_changes"] if c["kind"] == "clutter"]
    assert len(clutter) == 5
    json.dumps(result.meta.extras)
    assert any(c["kind"] == "moved" for c in result.meta.extras["as_built_changes"])
    xy = result.trajectory.poses[:, :2]
    margin = cfg.bim.grid.robot_radius_m - paper_floor.prior.grid.resolution_m
    for box in clutter:
        c, s = np.cos(box["yaw_rad"]), np.sin(box["yaw_rad"])
        local = (xy - box["position_m"][:2]) @ np.array([[c, -s], [s, c]])
        outside = np.maximum(np.abs(local) - np.asarray(box["size_m"][:2]) / 2, 0.0)
        assert np.hypot(outside[:, 0], outside[:, 1]).min() >= margin


def test_load_world_inputs_checks_the_ifc(paper_floor: Building, tmp_path: Path) -> None:
    ifc = tmp_path / "building.ifc"
    shutil.copy(paper_floor.ifc_path, ifc)
    prior_dir = tmp_path / "prior"
    paper_floor.prior.save(prior_dir)
    meta_file = prior_dir / "prior.json"
    meta = json.loads(meta_file.read_text())
    meta["source_file"] = str(ifc)
    meta_file.write_text(json.dumps(meta))
    prior, model = load_world_inputs(prior_dir, paper_floor.cfg)
    assert model.sha256 == prior.source_sha256 and len(model.elements) == len(paper_floor.model.elements)
    with ifc.open("ab") as fh:
        fh.write(b"/* edited */\n")
    with pytest.raises(InputError, match="changed since the prior"):
        load_world_inputs(prior_dir, paper_floor.cfg)
    ifc.unlink()
    with pytest.raises(InputError, match="is missing"):
        load_world_inputs(prior_dir, paper_floor.cfg)


def test_the_ifc_is_found_from_another_working_directory_and_beside_a_moved_prior(
    paper_floor: Building, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A prior built from a relative IFC path stores it resolved, so another working directory finds it; a prior moved
    together with its IFC (the stored path gone) finds the file of that name beside it."""
    from bimfactor.bim.prior import build_prior

    work = tmp_path / "work"
    (work / "data").mkdir(parents=True)
    shutil.copy(paper_floor.ifc_path, work / "data" / "building.ifc")
    monkeypatch.chdir(work)
    prior = build_prior(Path("data/building.ifc"), paper_floor.cfg)
    assert Path(prior.source_file) == work / "data" / "building.ifc"
    prior.save(work / "runs" / "prior")  # neither beside nor above the IFC's relative path
    monkeypatch.chdir(tmp_path)
    assert load_world_inputs(work / "runs" / "prior", paper_floor.cfg)[1].sha256 == prior.source_sha256
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.move(work / "runs" / "prior", moved / "prior")
    shutil.move(work / "data" / "building.ifc", moved / "building.ifc")
    assert load_world_inputs(moved / "prior", paper_floor.cfg)[1].sha256 == prior.source_sha256


def _frames(poses: np.ndarray, odometry: np.ndarray, t0: float) -> list:
    from bimfactor.types import Frame

    blank = np.zeros((2, 2), np.float32)
    return [
        Frame(i, t0 + i, np.zeros((2, 2, 3), np.uint8), blank, odometry[i], gt_pose=poses[i], gt_storey=0)
        for i in range(len(poses))
    ]


def test_a_kidnapped_robot_jumps_in_truth_while_its_odometry_stands_still() -> None:
    from bimfactor.sim.simulate import kidnap

    rng = np.random.default_rng(0)
    first = _frames(rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), t0=100.0)
    second = _frames(rng.normal(size=(8, 3)) + 20.0, rng.normal(size=(8, 3)), t0=7.0)
    frames = kidnap(first, second, at=4, resume_at=3)
    assert len(frames) == 4 + 4 and [f.index for f in frames] == list(range(8))
    np.testing.assert_array_equal(
        [f.gt_pose for f in frames], [*(f.gt_pose for f in first[:4]), *(f.gt_pose for f in second[4:])]
    )
    odometry = np.asarray([f.odom_pose for f in frames])
    # carried, not driven, to second's keyframe 3 (no keyframe: the odometry stood still), then its own increments
    for i in range(3, 7):
        np.testing.assert_allclose(
            se2_between(odometry[i], odometry[i + 1]),
            se2_between(second[i].odom_pose, second[i + 1].odom_pose),
            atol=1e-9,
        )
    np.testing.assert_array_equal(odometry[:4], [f.odom_pose for f in first[:4]])
    times = [f.timestamp_s for f in frames]
    assert np.all(np.diff(times) > 0) and times[4] == pytest.approx(times[3] + 1.0)
    assert first[0].index == 0 and second[3].index == 3  # the inputs are left as they were
    with pytest.raises(ValueError, match="out of range"):
        kidnap(first, second, at=7, resume_at=0)


def test_a_storey_route_rides_the_lift_and_tells_of_it(lift_house: Building, config_overrides: list[str]) -> None:
    from bimfactor.sim.trajectory import LIFT_RIDE_S
    from bimfactor.types import STOREY_CHANGE

    cfg = config_with(config_overrides, *SMALL_CAMERA)
    result = simulate_sequence(lift_house.prior, lift_house.model, cfg, 0, seed=0, progress=False, change_storey=True)
    trajectory, frames = result.trajectory, result.frames
    storeys = trajectory.keyframe_storeys
    (change,) = np.flatnonzero(np.diff(storeys)) + 1  # one ride, up from the ground floor
    assert storeys[0] == 0 and storeys[-1] == 1 and 0 < change < len(frames) - 10
    assert [f.gt_storey for f in frames] == storeys.tolist()
    assert [f.extras.get(STOREY_CHANGE) for f in frames] == [1.0 if i == change else None for i in range(len(frames))]
    # the ride: no keyframe, the wheels still for LIFT_RIDE_S while time passes, then out on the other floor
    (arrival,) = np.flatnonzero(np.diff(trajectory.storeys)) + 1
    ride = round(LIFT_RIDE_S / cfg.sim.robot.control_dt_s)
    assert trajectory.keyframe_indices[change - 1] < arrival - ride and trajectory.keyframe_indices[change] > arrival
    np.testing.assert_array_equal(np.diff(trajectory.poses[arrival - ride : arrival], axis=0), 0.0)
    np.testing.assert_array_equal(trajectory.commands[arrival - ride : arrival], 0.0)
