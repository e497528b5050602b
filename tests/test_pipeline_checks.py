"""The localizer's checks of its input: a sequence against the prior (ground-truth storeys, the building it was
simulated in) before any work, and implausible frames (unusable depth, odometry jumps) skipped and reported.

The localizer runs on the hand-built two-room box (tests/localization/handmade.py) with a stand-in perception that
records the frames it is given and sees nothing, so a run of a few frames takes a fraction of a second.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

import bimfactor.pipeline
from bimfactor.bim.ifc import file_sha256
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.synth import write_building
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.cli import app
from bimfactor.config import Config, load_config
from bimfactor.errors import InputError
from bimfactor.evaluation.report import write_run
from bimfactor.io.sequence import read_sequence, write_sequence
from bimfactor.pipeline import (
    FrameSkip,
    LocalizationRun,
    building_mismatch,
    check_sequence_against_prior,
    depth_problem,
    localize_sequence,
    skipped_frames_note,
)
from bimfactor.types import CameraIntrinsics, Frame, Observations, SequenceMeta, se2_compose
from tests.io.synthetic import make_frames, make_meta
from tests.localization.handmade import LABELS, make_prior

W, H = 16, 12
DT_S = 0.5
STEP_M = 0.3  # 0.6 m/s along y = 3 in room A of the box
N_FRAMES = 10
JUMP_M = 1e6


class OneHot:
    """The text embedder the hand-made prior names (only its name and size are read: perception is stood in for)."""

    name = "one-hot"
    dim = len(LABELS)


class StubPerception:
    """Records the frames it is stepped with and sees nothing in them."""

    reader = None  # reads no text

    def __init__(self) -> None:
        self.frames: list[Frame] = []

    def step(self, frame: Frame, plate_columns: np.ndarray | None = None) -> SimpleNamespace:
        self.frames.append(frame)
        empty = Observations(np.zeros((0, OneHot.dim), np.float32), np.zeros(0), np.zeros(0))
        return SimpleNamespace(observations=empty, timing_ms={}, detections=[], readings=[])


@pytest.fixture(scope="module")
def box(test_config: Config) -> BimPrior:
    prior = make_prior()
    prior.visibility = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    return prior


@pytest.fixture
def perception(monkeypatch: pytest.MonkeyPatch) -> StubPerception:
    stub = StubPerception()
    monkeypatch.setattr(bimfactor.pipeline, "make_perception", lambda *args, **kwargs: stub)
    return stub


@pytest.fixture(scope="module")
def cfg(config_overrides: list[str]) -> Config:
    """A belief started tight about the true start; nothing but odometry moves it (no scan term, no injection); every
    frame of the drive (`STEP_M` apart) is a keyframe."""
    return load_config(
        None,
        [
            *config_overrides,
            f"localization.keyframe_distance_m={STEP_M / 2}",
            "smcl.num_particles=300",
            "smcl.resampler.kind=systematic",
            "smcl.augmented.enabled=false",
            "smcl.scan.enabled=false",
            "smcl.relocalize.enabled=false",
            "smcl.challenger.enabled=false",
            "smcl.start.pose=[2.0, 3.0, 0.0]",
            "smcl.start.sigma_xy_m=0.05",
            "smcl.start.sigma_yaw_deg=1.0",
        ],
    )


def _meta(prior_sha256: str = "") -> SequenceMeta:
    K = CameraIntrinsics.from_hfov(W, H, 90.0)
    return SequenceMeta("drive", "sim", K, np.array(make_meta().T_base_camera), prior_sha256=prior_sha256)


def _truth(k: int) -> np.ndarray:
    return np.array([2.0 + STEP_M * k, 3.0, 0.0])


def _frames() -> list[Frame]:
    """A straight drive; frame 2 has no depth return, frame 4 every return at 65.535 m (saturated 16-bit), frame 6's
    odometry glitches 1e6 m away for one message, and from frame 8 on the odometry is re-based 1e6 m away."""
    rng = np.random.default_rng(0)
    frames = []
    for k in range(N_FRAMES):
        depth = rng.uniform(0.5, 4.0, size=(H, W)).astype(np.float32)
        odom = _truth(k)
        if k == 2:
            depth[:] = np.nan
        if k == 4:
            depth[:] = 65.535
            depth[0, :3] = np.nan  # no-return pixels do not make a saturated image usable
        if k == 6 or k >= 8:
            odom = odom + np.array([JUMP_M, 0.0, 0.0])
        frames.append(
            Frame(
                index=100 + k,
                timestamp_s=DT_S * k,
                rgb=np.zeros((H, W, 3), np.uint8),
                depth_m=depth,
                odom_pose=odom,
                gt_pose=_truth(k),
                gt_storey=0,
            )
        )
    return frames


def _localize(box: BimPrior, cfg: Config, frames: list[Frame]) -> LocalizationRun:
    return localize_sequence(box, _meta(), frames, cfg, 3, text_embedder=OneHot(), show_progress=False, twins={})


# ------------------------------------------------------------------------------------------ implausible frames


def test_implausible_frames_are_skipped_and_the_particles_are_not_teleported(
    box: BimPrior, cfg: Config, perception: StubPerception
) -> None:
    run = _localize(box, cfg, _frames())

    assert run.skip_reasons == [
        "", "", "empty depth", "", "saturated depth", "", "odometry jump of 1e6 m", "", "odometry jump of 1e6 m", "",
    ]  # fmt: skip
    assert [s.kind for s in run.skipped if s is not None] == ["empty_depth", "saturated_depth", *["odometry_jump"] * 2]
    assert skipped_frames_note(run) == (
        "skipped 4 frames: 1 with empty depth (step 2), 1 with saturated depth (step 4), "
        "2 with odometry jumps of up to 1e6 m (steps 6, 8)"
    )
    # Perception never saw a skipped frame, and saw one continuous odometry: the re-based frame 9 mapped back.
    assert [f.index for f in perception.frames] == [100, 101, 103, 105, 107, 109]
    for seen in perception.frames:
        np.testing.assert_allclose(seen.odom_pose, _truth(seen.index - 100), atol=1e-6)
    # The motion applied over the run is the drive's: the glitch made up at frame 7, the guess over the re-base
    # (the previous step's motion, here the true one) continued at frame 9.
    assert run.odom_increments.shape == (N_FRAMES - 1, 3)
    pose = _truth(0)
    for increment in run.odom_increments:
        pose = se2_compose(pose, increment)
    np.testing.assert_allclose(pose, _truth(N_FRAMES - 1), atol=1e-6)
    assert np.abs(run.odom_increments).max() < 1.0
    # so the belief follows the drive (unchecked, the jump would have carried every particle 1e6 m off the box)
    errors = np.hypot(*(run.poses[:, :2] - run.gt_poses[:, :2]).T)
    assert errors.max() < 0.5, errors
    # skipped frames bring no observation: the filter weighed nothing there
    assert [len(obs) for obs in run.observations] == [0] * N_FRAMES
    assert all(run.scans[k] is None for k in (2, 4, 6, 8))


def test_a_clean_drive_skips_nothing(box: BimPrior, cfg: Config, perception: StubPerception) -> None:
    frames = _frames()
    for k, frame in enumerate(frames):
        frame.odom_pose = _truth(k)
        frame.depth_m = frames[0].depth_m
    run = _localize(box, cfg, frames)
    assert run.skipped == [None] * N_FRAMES and run.skip_reasons == [""] * N_FRAMES
    assert skipped_frames_note(run) is None
    assert len(perception.frames) == N_FRAMES
    for k, frame in enumerate(perception.frames):
        assert frame is frames[k]  # untouched: the odometry is passed on as it came


def test_steps_csv_says_why_a_step_was_skipped(
    box: BimPrior, cfg: Config, perception: StubPerception, tmp_path: Path
) -> None:
    run = _localize(box, cfg, _frames()[:7])
    write_run(run, box, tmp_path / "run", "", "drive against the box")
    rows = list(csv.DictReader((tmp_path / "run" / "steps.csv").read_text().splitlines()))
    assert [row["skipped"] for row in rows] == [
        "", "", "empty depth", "", "saturated depth", "", "odometry jump of 1e6 m",
    ]  # fmt: skip


def test_a_sequence_whose_every_frame_is_skipped_is_an_input_error(
    box: BimPrior, cfg: Config, perception: StubPerception
) -> None:
    """All-zero or all-saturated depth in every frame: no estimate to report, an InputError that says why."""
    frames = _frames()
    for k, frame in enumerate(frames):
        frame.depth_m = np.zeros_like(frame.depth_m) if k % 2 else np.full_like(frame.depth_m, 65.535)
    with pytest.raises(InputError, match=r"no frame could be used, skipped 10 frames: 5 with empty depth"):
        _localize(box, cfg, frames)
    assert perception.frames == []


def test_depth_problems(test_config: Config) -> None:
    depth = np.full((4, 5), 2.5, np.float32)
    assert depth_problem(depth, test_config) is None  # a wall straight ahead: one depth, but within range
    assert depth_problem(np.zeros((4, 5), np.float32), test_config) == FrameSkip("empty_depth")
    assert depth_problem(np.full((4, 5), np.nan, np.float32), test_config) == FrameSkip("empty_depth")
    assert depth_problem(np.full((4, 5), 65.535, np.float32), test_config) == FrameSkip("saturated_depth")
    far = np.full((4, 5), 30.0, np.float32)
    far[0, 0] = 29.0
    assert depth_problem(far, test_config) is None  # far, but not one single value: a hall, not a stuck sensor


def test_the_note_lists_many_steps_briefly() -> None:
    skipped = [FrameSkip("empty_depth") if k % 2 else None for k in range(30)]
    run = SimpleNamespace(skipped=skipped)
    note = skipped_frames_note(run, max_steps=3)  # type: ignore[arg-type]
    assert note == "skipped 15 frames: 15 with empty depth (steps 1, 3, 5, … (15 in all))"
    one = SimpleNamespace(skipped=[None, FrameSkip("odometry_jump", 37.24)])
    assert skipped_frames_note(one) == "skipped 1 frame: 1 with an odometry jump of 37.2 m (step 1)"  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------ sequence vs prior


def test_a_ground_truth_storey_past_the_priors_is_an_input_error(box: BimPrior, tmp_path: Path) -> None:
    frames = make_frames(4)  # indices 10, 12, 14, 16; storeys 0, None, 0, 1
    write_sequence(tmp_path / "seq", make_meta(), frames)
    sequence = read_sequence(tmp_path / "seq")
    message = "frame 16 (step 3): gt_storey 1 is not a storey of the prior, which has 1 storey (0)"
    with pytest.raises(InputError) as exc_info:
        check_sequence_against_prior(sequence, box)
    assert str(exc_info.value).startswith(message) and "\n" not in str(exc_info.value)
    with pytest.raises(InputError, match=r"frame 16 .*gt_storey 1"):
        check_sequence_against_prior(frames, box)  # frames in memory too
    frames[3].gt_storey = -1
    with pytest.raises(InputError, match="gt_storey -1 is not a storey"):
        check_sequence_against_prior(frames, box)
    frames[3].gt_storey = 0
    check_sequence_against_prior(frames, box)
    two = make_prior(n_storeys=2)
    check_sequence_against_prior(sequence, two)  # storey 1 exists there


def test_localize_refuses_a_storey_past_the_prior_in_one_line(
    box: BimPrior, tmp_path: Path, cli_config_args: list[str]
) -> None:
    box.save(tmp_path / "prior")
    frames = make_frames(3)
    frames[2].gt_storey = 5
    write_sequence(tmp_path / "seq", make_meta(), frames)
    result = CliRunner().invoke(
        app, ["localize", str(tmp_path / "prior"), str(tmp_path / "seq"), "-o", str(tmp_path / "run"), *cli_config_args]
    )
    assert isinstance(result.exception, SystemExit) and result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert lines == ["error: frame 14 (step 2): gt_storey 5 is not a storey of the prior, which has 1 storey (0); "
                     "is the sequence from another building?"]  # fmt: skip
    assert "Traceback" not in result.output


def test_a_sequence_from_another_building_is_named(box: BimPrior, tmp_path: Path) -> None:
    """Two synth buildings of different seeds: the sequence records the one it was simulated in (the SHA-256 of the
    IFC file its prior was built from, as `simulate_sequence` writes it), the prior the one it was built from."""
    write_building("office", 0, tmp_path / "office-0.ifc")
    write_building("office", 1, tmp_path / "office-1.ifc")
    built_from, simulated_in = file_sha256(tmp_path / "office-0.ifc"), file_sha256(tmp_path / "office-1.ifc")
    assert built_from != simulated_in
    prior = dataclasses.replace(box, source_file=str(tmp_path / "office-0.ifc"), source_sha256=built_from)
    write_sequence(tmp_path / "seq", _meta(prior_sha256=simulated_in), _frames()[:2])
    meta = read_sequence(tmp_path / "seq").meta

    message = building_mismatch(meta, prior)
    assert message == (
        f"sequence 'drive' was recorded in the building of IFC file sha256 {simulated_in[:12]}…, but the prior was "
        f"built from office-0.ifc (sha256 {built_from[:12]}…): another building, or another version of it"
    )
    assert building_mismatch(dataclasses.replace(meta, prior_sha256=built_from), prior) is None
    assert building_mismatch(dataclasses.replace(meta, prior_sha256=built_from.upper()), prior) is None
    assert building_mismatch(dataclasses.replace(meta, prior_sha256=""), prior) is None  # a converted recording
    assert building_mismatch(meta, dataclasses.replace(prior, source_sha256="")) is None


def test_localize_refuses_another_building_unless_forced(
    box: BimPrior, tmp_path: Path, cli_config_args: list[str]
) -> None:
    dataclasses.replace(box, source_sha256="a" * 64).save(tmp_path / "prior")
    write_sequence(tmp_path / "seq", _meta(prior_sha256="b" * 64), _frames()[:3])
    args = ["localize", str(tmp_path / "prior"), str(tmp_path / "seq"), "-o", str(tmp_path / "run"), *cli_config_args]
    refused = CliRunner().invoke(app, args)
    assert refused.exit_code == 2, refused.output
    assert refused.stderr.strip().splitlines() == [
        "error: sequence 'drive' was recorded in the building of IFC file sha256 bbbbbbbbbbbb…, but the prior was "
        "built from handmade (sha256 aaaaaaaaaaaa…): another building, or another version of it; --force localizes it "
        "all the same"
    ]
    assert not (tmp_path / "run").exists()
    forced = CliRunner().invoke(app, [*args, "--force"])
    assert forced.stderr.startswith("warning: sequence 'drive' was recorded in the building"), forced.output
    assert "--force" not in forced.stderr
