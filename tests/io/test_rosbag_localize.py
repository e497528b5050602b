"""End to end: a simulated recording written into a bag (keyframes, odometry, tf mount) and converted back
localizes as the simulator's own sequence does. Slower than a unit test (a simulation and two localizations): it is
the conversion's acceptance check against the localizer."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from bimfactor.io.sequence import read_sequence
from tests.cli import invoke
from tests.io.bags import R_LINK_OPTICAL, TestBag, rigid, rpy_deg
from tests.io.test_rosbag_sim import COLOUR_FRAME, DEPTH_AFTER_NS, MOUNT_XYZ

pytest.importorskip("rosbags", reason="the optional 'rosbags' package is not installed")

LOCALIZE = ("--set", "smcl.num_particles=300", "--set", "smcl.resampler.max_particles=3000")
MOUNT = ("--set", "sim.camera.mount_height_m=0.35", "--set", "sim.camera.mount_pitch_deg=10")


def _steps(run: Path) -> list[dict[str, str]]:
    return list(csv.DictReader((run / "steps.csv").read_text().splitlines()))


def test_a_recording_localizes_from_its_bag_as_from_the_simulator(
    paper_floor_prior: Path, cli_config_args: list[str], tmp_path: Path
) -> None:
    """The simulator's sequence written into a bag as a robot records it (keyframes, odometry, tf mount, and the sim
    detector's boxes as a vision_msgs/Detection2DArray topic) converts with no topic or mount flags and localizes with
    no --set as well as the simulator's own sequence does with its own perception."""
    from bimfactor.perception.detections import DETECTIONS_FILE

    original = tmp_path / "sim"
    length = ("--set", "evaluation.trajectory_length=20")
    result = invoke("simulate", paper_floor_prior, "-o", original, *length, *MOUNT, *cli_config_args)
    assert result.exit_code == 0, result.output
    seq = read_sequence(original)
    detected = [json.loads(line) for line in (original / DETECTIONS_FILE).read_text().splitlines()]
    K = seq.meta.intrinsics
    bag = TestBag(tmp_path / "bag")
    stamps = [round(t * 1e9) for t in seq.timestamps()]
    links = [("base_link", "camera_link", rigid(MOUNT_XYZ, rpy_deg(0, 10, 0)))]
    bag.tf("/tf_static", stamps[0], [*links, ("camera_link", COLOUR_FRAME, rigid(R=R_LINK_OPTICAL))])
    for t_ns, frame, line in zip(stamps, seq, detected, strict=True):
        bag.image("/camera/color/image_raw", t_ns, frame.rgb, "rgb8", COLOUR_FRAME)
        bag.camera_info("/camera/color/camera_info", t_ns, COLOUR_FRAME, (K.width, K.height), (K.fx, K.fy, K.cx, K.cy))
        bag.depth_mm("/camera/aligned_depth_to_color/image_raw", t_ns + DEPTH_AFTER_NS, frame.depth_m, COLOUR_FRAME)
        bag.odometry("/odom", t_ns, frame.odom_pose)
        bag.detections("/detector/detections", t_ns + 30_000_000, COLOUR_FRAME, line["detections"])
    bag.write()
    converted = tmp_path / "converted"
    gap = ("--set", "io.rosbag.max_odom_gap_s=5")  # odometry at the keyframes only, about 0.7 s apart
    result = invoke("convert", "rosbag", tmp_path / "bag", "-o", converted, "--all-frames", *gap)
    assert result.exit_code == 0, result.output
    assert "from the bag's /detector/detections" in result.stdout
    back = read_sequence(converted)
    assert len(back) == len(seq) and not back.meta.instances
    np.testing.assert_allclose(back.meta.T_base_camera, seq.meta.T_base_camera, atol=1e-9)
    np.testing.assert_allclose(back.odometry(), seq.odometry(), atol=1e-9)
    np.testing.assert_array_equal(back[5].rgb, seq[5].rgb)
    np.testing.assert_array_equal(back[5].depth_m, seq[5].depth_m)
    stored = [json.loads(line) for line in (converted / DETECTIONS_FILE).read_text().splitlines()]
    assert [len(line["detections"]) for line in stored] == [len(d["detections"]) for d in detected if d["detections"]]
    first = next(d for d in detected if d["detections"])["detections"][0]
    assert stored[0]["detections"][0]["label"] == first["label"]
    np.testing.assert_allclose(stored[0]["detections"][0]["box"], first["box"], atol=1e-6)

    steps = {}
    for name, folder, says in (("sim", original, "perception: sim"), ("bag", converted, "perception: detections")):
        run = tmp_path / f"run-{name}"
        result = invoke("localize", paper_floor_prior, folder, "-o", run, *LOCALIZE)
        assert result.exit_code == 0, result.output
        assert result.stdout.startswith(says), result.stdout
        steps[name] = _steps(run)
    truth = [(float(r["gt_x"]), float(r["gt_y"])) for r in steps["sim"]]  # the converted run has no ground truth
    trans = {}
    for name, rows in steps.items():
        xy = np.array([(float(r["x"]), float(r["y"])) for r in rows])
        trans[name] = np.hypot(*(xy - np.array(truth)).T)
    half = len(truth) // 2
    sim_median, bag_median = np.median(trans["sim"][half:]), np.median(trans["bag"][half:])
    print(f"median error over the second half: simulator's sequence {sim_median:.3f} m, bag {bag_median:.3f} m")
    assert sim_median < 1.0
    assert bag_median <= 1.2 * sim_median + 0.02, (sim_median, bag_median)
