"""The README's "From Python" code, run as written: the online loop on a demo-like folder, and the live-robot
snippet up to the one-line errors it promises without weight files, with its keyframe gate."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from bimfactor.io.sequence import write_sequence
from bimfactor.odometry import keyframe_indices
from bimfactor.sim.simulate import simulate_sequence
from bimfactor.types import se2_between
from tests.sim import conftest as sim_fixtures
from tests.sim.conftest import Building

paper_floor = sim_fixtures.paper_floor
text_embedder = sim_fixtures.text_embedder

README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks() -> list[str]:
    """The ```python blocks of the README's "From Python" section, in order."""
    text = README.read_text()
    section = text.split("\n## From Python\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


@pytest.fixture(scope="module")
def demo_folder(paper_floor: Building, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder laid out as `bimfactor demo` leaves it: runs/demo/prior and runs/demo/sequence (trajectory 0)."""
    root = tmp_path_factory.mktemp("readme")
    paper_floor.prior.save(root / "runs/demo/prior")
    drive = simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 0, 0, progress=False)
    write_sequence(root / "runs/demo/sequence", drive.meta, drive.frames)
    return root


def test_the_readme_has_the_three_blocks() -> None:
    blocks = python_blocks()
    assert len(blocks) == 3
    assert "localizer.step(frame)" in blocks[0] and "Localizer(" in blocks[1] and "def on_camera_frame" in blocks[2]


def test_the_online_loop_localizes_the_demo_sequence(
    demo_folder: Path, paper_floor: Building, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    monkeypatch.chdir(demo_folder)
    scope: dict = {}
    exec(python_blocks()[0], scope)
    step, frame = scope["step"], scope["frame"]
    assert np.hypot(*(step.pose[:2] - frame.gt_pose[:2])) < 0.5
    truth_room = int(paper_floor.prior.room_at(frame.gt_pose[None, :2], 0)[0])
    assert scope["room"] == next(r.category for r in paper_floor.prior.rooms if r.id == truth_room)
    assert scope["hypotheses"] and 0.0 < scope["sigma_xy_m"] < 0.5  # the graphs' modes, and an honest spread
    assert f"converged {step.filtered.converged}" in capsys.readouterr().out


def test_the_live_snippet_runs_the_shipped_detector(demo_folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With no weight files and no detections file, the live localizer's eyes are the shipped YOLOX-Nano, and one
    camera frame steps it."""
    monkeypatch.chdir(demo_folder)
    first, live = python_blocks()[:2]
    scope: dict = {}
    exec(first.split("localizer = ")[0], scope)  # the imports, without running the loop again
    scope["BimPrior"].load("runs/demo/prior").save(demo_folder / "runs/prior/my-building")
    exec(live, scope)
    robot = scope["robot"]
    assert robot.perception.backend == "yolox"
    k = scope["meta"].intrinsics
    frame = scope["Frame"](
        0, 0.0, np.zeros((k.height, k.width, 3), np.uint8), np.full((k.height, k.width), 2.0, np.float32), np.zeros(3)
    )
    step = robot.step(frame)
    assert step.skipped is None and step.perception_parts["detector"] > 0


def test_the_live_callback_steps_the_localizer_at_keyframes_only(
    demo_folder: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every camera frame goes to the localizer, which steps at the frames the odometry keyframe rule keeps and
    returns None for the others."""
    monkeypatch.chdir(demo_folder)
    first, live, callback = python_blocks()
    scope: dict = {}
    exec(first.split("localizer = ")[0], scope)
    scope["BimPrior"].load("runs/demo/prior").save(demo_folder / "runs/prior/my-building")
    exec(live, scope)
    exec(callback, scope)
    t = np.arange(120) * 0.05
    odometry = np.column_stack([0.3 * t, 0.1 * np.sin(t), np.minimum(0.4 * t, 2.0)])  # 0.3 m/s; turning 23°/s, then not
    k = scope["meta"].intrinsics
    image, depth = np.zeros((k.height, k.width, 3), np.uint8), np.full((k.height, k.width), 2.0, np.float32)
    returned = [scope["on_camera_frame"](i, t[i], image, depth, odometry[i]) for i in range(len(t))]
    cfg = scope["live"].localization
    want = keyframe_indices(odometry, cfg.keyframe_distance_m, np.radians(cfg.keyframe_angle_deg))
    assert 5 < len(want) < 60
    assert [i for i, step in enumerate(returned) if step is not None] == want.tolist()
    np.testing.assert_allclose(returned[want[3]].odom_increment, se2_between(odometry[want[2]], odometry[want[3]]))
