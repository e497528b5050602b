"""`bimfactor scene-graph`: the online open-set scene graph of a real recording from its 6-DoF camera poses, with the
shipped detector; and of a simulated sequence from its ground-truth poses through the camera mount."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from bimfactor.perception.mapping import sequence_camera_poses, up_direction
from bimfactor.types import Frame, se2_to_matrix
from tests.cli import assert_one_line_error, invoke

DINING_INTRINSICS = "518,519,325.5,253.5"  # slambook-dining's README


def _graph(out: Path) -> tuple[dict, Counter]:
    record = json.loads((out / "scene_graph.json").read_text())
    return record, Counter(node["label"] for node in record["nodes"])


def test_an_office_desk_seen_by_a_hand_held_camera(real_recording, cli_config_args, tmp_path: Path) -> None:
    """tum-fr1-rpy: 58 frames rolling, pitching and yawing up to ~110° over two desks. Each screen, keyboard and chair
    ends as one node: at most 3 tv, 3 keyboard and 4 chair nodes (measured: 2, 1, 3)."""
    out = tmp_path / "tum"
    result = invoke("scene-graph", real_recording("tum-fr1-rpy"), "-o", out, *cli_config_args)
    assert result.exit_code == 0, result.output
    record, counts = _graph(out)
    assert record["frames_used"] == 58 and record["poses"].startswith("groundtruth.txt")
    assert 1 <= counts["tv"] <= 3 and 1 <= counts["keyboard"] <= 3 and 1 <= counts["chair"] <= 4
    assert (out / "scene_graph.png").stat().st_size > 10_000 and (out / "config.yaml").is_file()
    node = record["nodes"][0]
    assert set(node) >= {"label", "centre_m", "extent_m", "n_observations", "n_voxels"}
    assert all(n["n_observations"] >= 2 for n in record["nodes"])  # a single sighting is pruned at the end
    desk = [n for n in record["nodes"] if n["label"] in ("tv", "keyboard")]
    assert all(0.5 < n["centre_m"][2] < 1.5 for n in desk)  # on the desks, in the motion-capture frame (z up)


def test_a_dining_room_from_five_frames(real_recording, cli_config_args, tmp_path: Path) -> None:
    """slambook-dining: one dining table and about six chairs and an armchair; exactly one table node and 4-9 chair
    nodes (measured: 1 and 5)."""
    out = tmp_path / "dining"
    recording = real_recording("slambook-dining")
    result = invoke("scene-graph", recording, "-o", out, "--intrinsics", DINING_INTRINSICS, *cli_config_args)
    assert result.exit_code == 0, result.output
    assert "1 dining table" in result.stdout
    _, counts = _graph(out)
    assert counts["dining table"] == 1 and 4 <= counts["chair"] <= 9


def test_what_is_not_a_recording_is_refused_in_one_line(real_recording, cli_config_args, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    result = invoke("scene-graph", empty, "-o", tmp_path / "out", *cli_config_args)
    assert_one_line_error(result, contains="neither a TUM RGB-D folder (rgb.txt) nor a bimfactor sequence")
    no_poses = tmp_path / "no-poses"
    no_poses.mkdir()
    source = real_recording("slambook-dining")
    for name in ("rgb.txt", "depth.txt"):
        (no_poses / name).write_text((source / name).read_text())
    for kind in ("rgb", "depth"):
        (no_poses / kind).symlink_to(source / kind)
    result = invoke("scene-graph", no_poses, "-o", tmp_path / "out", *cli_config_args)
    assert_one_line_error(result, contains="no groundtruth.txt")
    result = invoke("scene-graph", source, "-o", tmp_path / "out", "--intrinsics", "518,519", *cli_config_args)
    assert_one_line_error(result, contains="expected FX,FY,CX,CY")
    assert not (tmp_path / "out").exists()


def test_a_robots_camera_poses_are_its_base_poses_through_the_mount() -> None:
    mount = np.array([[0.0, 0.0, 1.0, 0.15], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0]])
    frames = [
        Frame(i, float(i), np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.float32), np.array([9.0, 9.0, 0.0]),
              gt_pose=np.array([i, 2.0, np.pi / 2]))
        for i in range(3)
    ]  # fmt: skip
    poses, source = sequence_camera_poses(frames, mount)
    assert source == "ground truth"
    np.testing.assert_allclose(poses[1], se2_to_matrix(np.array([1.0, 2.0, np.pi / 2])) @ mount)
    np.testing.assert_allclose(poses[1][:3, 3], [1.0, 2.15, 0.5], atol=1e-12)  # 15 cm ahead (+y), 0.5 m up
    np.testing.assert_allclose(up_direction(poses), [0.0, 0.0, 1.0], atol=1e-12)
    frames[1].gt_pose = None
    assert sequence_camera_poses(frames, mount)[1] == "odometry"


@pytest.mark.parametrize("pitch_deg", [0.0, 30.0])
def test_up_is_against_the_cameras_mean_down_axis(pitch_deg: float) -> None:
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (2, 1, 1))
    # an OpenCV camera looking along world +x, its y (down) along world −z, pitched down about its x axis
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:, :3, :3] = level @ Rotation.from_euler("x", -pitch_deg, degrees=True).as_matrix()
    up = up_direction(T)
    assert np.degrees(np.arccos(up[2])) == pytest.approx(pitch_deg, abs=1e-9)
