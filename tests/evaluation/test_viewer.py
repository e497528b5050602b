"""Rerun recordings of runs (`--rerun`, `bimfactor.evaluation.viewer`), read back with rerun-sdk's own RRD reader."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import load_config
from bimfactor.evaluation.viewer import ENTITIES, TIMELINE, VIZ_INSTALL, record
from bimfactor.io.sequence import write_sequence
from bimfactor.perception.base import TextReading
from bimfactor.pipeline import Keyframe, localize_sequence
from bimfactor.types import Observations
from tests.cli import assert_one_line_error, invoke
from tests.evaluation.recordings import STATIC, logged

pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")
from rerun.chunk import RrdReader

N_FRAMES = 4
BIM = ("world/bim/walls", "world/bim/doors", "world/bim/objects", "world/bim/rooms")


class Watching:
    """A recorder that also notes whether any keyframe's frame had text read (the plates' entity exists then)."""

    def __init__(self, recorder) -> None:
        self.recorder, self.read_text = recorder, False

    def on_step(self, localizer, key, out) -> None:
        self.read_text |= bool(key.readings)
        self.recorder.on_step(localizer, key, out)


def test_a_full_run_is_recorded_under_every_entity_it_has_data_for(
    paper_floor, drive, text_embedder, config_overrides: list[str], tmp_path: Path
) -> None:
    cfg = load_config(None, [*config_overrides, "localization.variant=full"])
    path = tmp_path / "run.rrd"
    with record(path, paper_floor.prior, "drive") as recorder:
        watch = Watching(recorder)
        frames = drive.frames[:N_FRAMES]
        run = localize_sequence(
            paper_floor.prior, drive.meta, frames, cfg, 0, text_embedder=text_embedder, show_progress=False,
            observer=watch,
        )  # fmt: skip
    found = logged(path)
    every_step = set(range(N_FRAMES))
    expected = set(ENTITIES)
    if not watch.read_text:
        expected.discard("camera/plates")
    if not run.fine.ran.any():
        expected.discard("world/icp")
    assert expected <= set(found), expected - set(found)
    assert ("camera/plates" in found) == watch.read_text
    for entity in BIM:
        assert found[entity] == {STATIC}, entity
    for entity in expected - set(BIM):
        want = every_step if entity != "world/icp" else set(map(int, run.fine.ran.nonzero()[0]))
        assert found[entity] == want, entity
    assert any(run.modes), "the full run had modes, so its recording shows them"


def test_a_sequence_without_ground_truth_has_no_truth_in_its_recording(
    paper_floor, drive, text_embedder, config_overrides: list[str], tmp_path: Path
) -> None:
    cfg = load_config(None, [*config_overrides, "localization.variant=smcl"])
    frames = [dataclasses.replace(f, gt_pose=None, gt_storey=None) for f in drive.frames[:3]]
    path = tmp_path / "blind.rrd"
    with record(path, paper_floor.prior, "blind") as recorder:
        localize_sequence(
            paper_floor.prior, drive.meta, frames, cfg, 0, text_embedder=text_embedder, show_progress=False,
            observer=recorder,
        )  # fmt: skip
    found = logged(path)
    assert not any(entity.startswith("world/truth") for entity in found)
    assert "plots/error_m" not in found
    assert found["world/estimate"] == found["world/particles"] == found["plots/ess"] == {0, 1, 2}


def test_text_read_on_a_keyframe_is_recorded_as_plates_and_cleared_after(paper_floor, drive, tmp_path: Path) -> None:
    """The paper floor has no numbered rooms, so its runs read no text: a keyframe with a reading shows it, and the
    next keyframe, which reads none, clears it (else the viewer would go on showing it)."""
    reading = TextReading("B-101", np.array([10.0, 20.0, 60.0, 40.0]), 0.9)
    no_nodes = Observations(np.zeros((0, 4)), np.zeros(0), np.zeros(0))
    keys = [Keyframe(frame, None, None, None, None, no_nodes, 0.0, {}) for frame in drive.frames[:2]]
    keys[0].readings = [reading]
    path = tmp_path / "plates.rrd"
    with record(path, paper_floor.prior, "plates") as recorder:
        for step, key in ((7, keys[0]), (8, keys[1])):
            recorder.rec.set_time(TIMELINE, sequence=step)
            recorder._camera(key)
    found = logged(path)
    assert found["camera/plates"] == {7} and found["camera/image"] == {7, 8}
    batches = [c.to_record_batch() for c in RrdReader(path).stream() if c.entity_path == "/camera/plates"]
    labels = [b.column("Boxes2D:labels").to_pylist() for b in batches if "Boxes2D:labels" in b.schema.names]
    cleared = [b.column(TIMELINE).to_pylist() for b in batches if "Clear:is_recursive" in b.schema.names]
    assert labels == [[["B-101"]]] and cleared == [[8]]


def test_localize_and_refine_write_the_recording_they_are_asked_for(
    paper_floor, drive, config_overrides: list[str], cli_config_args: list[str], tmp_path: Path
) -> None:
    prior_dir, sequence = tmp_path / "prior", tmp_path / "seq"
    paper_floor.prior.save(prior_dir, config_yaml=paper_floor.cfg.dump_yaml())
    write_sequence(sequence, drive.meta, drive.frames[:3])
    for command, variant in (("localize", "smcl"), ("refine", "smcl+graph")):
        path = tmp_path / f"{command}.rrd"
        result = invoke(
            command, prior_dir, sequence, "-o", tmp_path / command, "--variant", variant, "--rerun", path,
            *cli_config_args,
        )  # fmt: skip
        assert result.exit_code == 0, result.output
        assert f"bimfactor view {path}" in result.stdout
        found = logged(path)
        assert found["world/estimate"] == found["world/truth"] == {0, 1, 2}, command


def test_view_prints_the_commands_where_no_display_exists(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    (tmp_path / "a").mkdir()
    for name in ("a/one.rrd", "two.rrd"):
        (tmp_path / name).write_bytes(b"")
    result = invoke("view", tmp_path)
    assert result.exit_code == 0, result.output
    assert f"rerun {tmp_path / 'a/one.rrd'} {tmp_path / 'two.rrd'}" in result.stdout
    assert f"rerun --web-viewer {tmp_path / 'a/one.rrd'}" in result.stdout
    assert_one_line_error(invoke("view", tmp_path / "a" / "nothing"), contains="no Rerun recording")


def test_rerun_without_the_extra_is_one_line_naming_it_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` fails as where rerun-sdk is not installed
    out = tmp_path / "demo"
    line = assert_one_line_error(invoke("demo", "-o", out, "--rerun", tmp_path / "demo.rrd"), contains=VIZ_INSTALL)
    assert "rerun-sdk" in line
    assert not out.exists() and not (tmp_path / "demo.rrd").exists()
    assert_one_line_error(invoke("demo", "-o", out, "--rerun", tmp_path / "demo.txt"), contains=".rrd")


def test_a_recording_inside_the_output_folder_is_refused_before_any_work(tmp_path: Path) -> None:
    """The demo's folder (and a run folder) is written whole or holds only bimfactor's files: a recording there would
    be lost or block the next run."""
    out = tmp_path / "demo"
    assert_one_line_error(invoke("demo", "-o", out, "--rerun", out / "demo.rrd"), contains="lies inside")
    assert not out.exists()
