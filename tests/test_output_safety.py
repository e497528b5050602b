"""No user file is ever lost: every command that writes replaces only its own kind of output, never its input, checks
the destination before the work, and leaves nothing half-written when it fails, is interrupted or is terminated."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bimfactor.io.atomic import MARKER, read_marker
from tests.cli import assert_one_line_error, invoke

SLAMBOOK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "slambook-dining"


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def prior(paper_floor_prior: Path, tmp_path: Path) -> Path:
    """A private copy of the session's paper-floor prior, and of its IFC beside it."""
    copy = tmp_path / "prior"
    shutil.copytree(paper_floor_prior, copy)
    shutil.copy(paper_floor_prior.parent / "paper-floor.ifc", tmp_path / "paper-floor.ifc")
    return copy


@pytest.fixture
def user_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "mine"
    (folder / "sub").mkdir(parents=True)
    (folder / "thesis.tex").write_text("years of work")
    (folder / "sub" / "data.csv").write_text("1,2,3")
    return folder


def test_simulate_never_replaces_the_prior_it_reads(prior: Path, cli_config_args: list[str]) -> None:
    before = snapshot(prior)
    line = assert_one_line_error(invoke("simulate", prior, "-o", prior, "--overwrite", *cli_config_args))
    assert "holds this command's input" in line
    assert snapshot(prior) == before


def test_convert_overwrite_never_deletes_a_users_folder(user_folder: Path) -> None:
    if not SLAMBOOK.is_dir():
        pytest.skip(f"real frames not available: {SLAMBOOK}")
    before = snapshot(user_folder)
    line = assert_one_line_error(invoke("convert", "tum", SLAMBOOK, "-o", user_folder, "--overwrite"))
    assert "holds no bimfactor output marker" in line
    assert snapshot(user_folder) == before


def test_rebuilding_a_prior_in_its_own_folder_keeps_the_ifc_and_the_users_files(
    prior: Path, cli_config_args: list[str]
) -> None:
    shutil.copy(prior.parent / "paper-floor.ifc", prior / "model.ifc")
    (prior / "NOTES.txt").write_text("mine")
    before = snapshot(prior)
    line = assert_one_line_error(invoke("prior", prior / "model.ifc", "-o", prior, *cli_config_args))
    assert "holds this command's input" in line
    (prior / "model.ifc").rename(prior.parent / "model.ifc")
    line = assert_one_line_error(invoke("prior", prior.parent / "model.ifc", "-o", prior, *cli_config_args))
    assert "holds NOTES.txt, which bimfactor did not write" in line
    assert (prior / "NOTES.txt").read_text() == "mine"
    assert snapshot(prior) == {k: v for k, v in before.items() if k != "model.ifc"}


def test_simulate_asks_for_overwrite_and_names_the_flag(
    prior: Path, tmp_path: Path, cli_config_args: list[str]
) -> None:
    sets = ["--set", "evaluation.trajectory_length=3", *cli_config_args]
    assert invoke("simulate", prior, "-o", tmp_path / "seq", *sets).exit_code == 0
    line = assert_one_line_error(invoke("simulate", prior, "-o", tmp_path / "seq", *sets))
    assert line.endswith("exists already (--overwrite replaces it)")
    assert invoke("simulate", prior, "-o", tmp_path / "seq", "--overwrite", *sets).exit_code == 0
    assert read_marker(tmp_path / "seq")["files"] == sorted(
        str(p.relative_to(tmp_path / "seq")) for p in (tmp_path / "seq").rglob("*") if p.is_file() and p.name != MARKER
    )


def test_simulate_refuses_a_trajectory_that_does_not_exist(prior: Path, tmp_path: Path) -> None:
    line = assert_one_line_error(invoke("simulate", prior, "-o", tmp_path / "seq", "-k", "99"))
    assert "--trajectory 99: the standard trajectories are 0-5" in line
    assert not (tmp_path / "seq").exists()


def test_an_interrupted_simulate_leaves_no_folder_that_looks_finished(
    prior: Path, tmp_path: Path, cli_config_args: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The figures are written last; a failure there must leave no sequence folder behind."""
    import bimfactor.evaluation.plots as plots

    def crash(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "save_trajectory_plot", crash)
    result = invoke(
        "simulate", prior, "-o", tmp_path / "seq", "--set", "evaluation.trajectory_length=3", *cli_config_args
    )
    assert assert_one_line_error(result, exit_code=130) == "error: interrupted"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper-floor.ifc", "prior"]


def test_localize_never_writes_into_its_inputs(prior: Path, tmp_path: Path, cli_config_args: list[str]) -> None:
    sets = ["--set", "evaluation.trajectory_length=3", *cli_config_args]
    assert invoke("simulate", prior, "-o", tmp_path / "seq", *sets).exit_code == 0
    before = snapshot(prior)
    for out in (prior, tmp_path / "seq", tmp_path):
        line = assert_one_line_error(invoke("localize", prior, tmp_path / "seq", "-o", out, *sets))
        assert "holds this command's input" in line
    assert snapshot(prior) == before


def test_output_problems_are_found_before_the_work(tmp_path: Path) -> None:
    """The destination is checked first: a broken IFC is never even read when -o cannot be written."""
    (tmp_path / "broken.ifc").write_text("not an IFC at all")
    (tmp_path / "plain-file").write_text("x")
    line = assert_one_line_error(invoke("prior", tmp_path / "broken.ifc", "-o", tmp_path / "plain-file" / "prior"))
    assert "is a file" in line
    line = assert_one_line_error(invoke("synth", "-o", tmp_path))
    assert "is a folder; give a file name" in line
    (tmp_path / "user.ifc").write_text("ISO-10303-21; my model")
    line = assert_one_line_error(invoke("synth", "-o", tmp_path / "user.ifc"))
    assert "was not written by bimfactor synth" in line
    assert (tmp_path / "user.ifc").read_text() == "ISO-10303-21; my model"


def test_a_folder_given_as_model_that_is_not_a_prior(user_folder: Path) -> None:
    line = assert_one_line_error(invoke("prior", user_folder))
    assert "a folder but not a bimfactor prior (no prior.json)" in line


def test_a_bench_never_writes_into_a_users_folder(user_folder: Path) -> None:
    before = snapshot(user_folder)
    line = assert_one_line_error(invoke("bench", "scanmatch", "-o", user_folder))
    assert "holds no bimfactor output marker" in line
    assert snapshot(user_folder) == before


@pytest.mark.parametrize(
    "args",
    [("simulate", "P", "--seed", "abc", "-o", "x"), ("bogus",), ("bench", "paper", "--workers", "0"), ("localize",)],
)
def test_usage_errors_are_one_line(args: tuple[str, ...]) -> None:
    line = assert_one_line_error(invoke(*args))
    assert line.endswith("(see --help)")


def _demo_under_way(out: Path, sets: list[str]) -> subprocess.Popen:
    """`bimfactor demo -o OUT` in a child process, once it has written its building (or ended, or 2 min passed)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "bimfactor", "demo", "-o", str(out), *sets],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not (out / "paper-floor.ifc").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc


@pytest.mark.parametrize(("signum", "says"), [(signal.SIGTERM, "terminated"), (signal.SIGHUP, "hung up")])
def test_sigterm_and_sighup_are_handled_like_ctrl_c(
    tmp_path: Path, config_overrides: list[str], signum: int, says: str
) -> None:
    """`timeout`, `docker stop` and systemd send SIGTERM, a closed terminal SIGHUP: the demo stops with one line
    (exit 128 + the signal) and leaves no temporaries."""
    out = tmp_path / "demo"
    proc = _demo_under_way(out, [a for o in config_overrides for a in ("--set", o)])
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, stderr
    assert stderr.strip() == f"error: {says}"
    leftovers = [p for p in out.rglob("*") if ".part" in p.name]
    assert leftovers == []
    assert read_marker(out) is not None and read_marker(out)["complete"] is False
    assert not (out / "prior").exists() or read_marker(out / "prior")["complete"] is True
    assert os.path.isfile(out / "config.yaml")


@pytest.mark.skipif(not SLAMBOOK.is_dir(), reason="needs ../shared/data/real")
@pytest.mark.parametrize("kind", ["dangling link", "loop of links", "name too long"])
def test_an_output_path_that_cannot_be_a_folder_is_refused_before_the_work(tmp_path: Path, kind: str) -> None:
    """A dangling link, a link to itself or a name past the file system's limit: one line and exit 2 before the
    recording is read, the link left as it was."""
    out = tmp_path / ("x" * 300 if kind == "name too long" else "out")
    if kind == "dangling link":
        out.symlink_to(tmp_path / "gone")
    elif kind == "loop of links":
        out.symlink_to(out)
    says = {"dangling link": "is a link to nothing", "loop of links": "is a link to nothing"}.get(kind, "longer than")
    started = time.perf_counter()
    result = invoke("scene-graph", SLAMBOOK, "-o", out, "--intrinsics", "518,519,325.5,253.5")
    assert_one_line_error(result, contains=says)
    assert time.perf_counter() - started < 5.0  # before YOLOX runs on the frames
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if kind == "name too long" else ["out"])
    assert kind == "name too long" or out.is_symlink()


def test_a_full_disk_is_one_line_naming_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ENOSPC (and the other errors of the place written to) while writing: exit 2 and the path, not 'internal'."""
    import errno

    import bimfactor.evaluation.mapping as mapping

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "out" / "scene_graph.json"))

    monkeypatch.setattr(mapping, "output_dir", full)
    if not SLAMBOOK.is_dir():
        pytest.skip("needs ../shared/data/real")
    result = invoke("scene-graph", SLAMBOOK, "-o", tmp_path / "out", "--intrinsics", "518,519,325.5,253.5")
    line = assert_one_line_error(result, contains="scene_graph.json: No space left on device")
    assert "internal" not in line and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (("config", "-c", ""), "-c is empty"),
        (("scene-graph", str(SLAMBOOK), "-o", ""), "-o is empty"),
        (("config", "-c", "/dev/null"), "/dev/null is not a regular file"),
        (("config", "-c", "room_categories"), "config file not found: room_categories (no such file, and the presets"),
        (("convert", "tum", str(SLAMBOOK), "-o", "OUT", "--detections", "."), "is a folder, not a detections file"),
    ],
    ids=["empty config", "empty output", "device as config", "data table as preset", "folder as detections"],
)
def test_each_wrong_kind_of_path_is_named_for_what_it_is(tmp_path: Path, args: tuple[str, ...], says: str) -> None:
    args = tuple(str(tmp_path / "out") if a == "OUT" else a for a in args)
    assert_one_line_error(invoke(*args), contains=says)
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(not SLAMBOOK.is_dir(), reason="needs ../shared/data/real")
def test_an_output_through_a_link_replaces_the_linked_run_and_keeps_the_link(tmp_path: Path) -> None:
    """`-o runs/latest`, a link to an earlier run: that run is replaced, the link stays, nothing is left beside."""
    first = tmp_path / "first"
    args = ("scene-graph", SLAMBOOK, "--intrinsics", "518,519,325.5,253.5", "-o")
    assert invoke(*args, first).exit_code == 0
    (first / "scene_graph.json").write_text("{}")  # to see it replaced (the marker lists the file)
    latest = tmp_path / "latest"
    latest.symlink_to(first)
    assert invoke(*args, latest).exit_code == 0
    assert latest.is_symlink() and latest.resolve() == first.resolve()
    assert (first / "scene_graph.json").read_text() != "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first", "latest"]


def test_a_second_demo_into_the_folder_a_first_is_writing_is_refused(
    tmp_path: Path, config_overrides: list[str]
) -> None:
    """Two demos into one folder at once mixed their outputs under a marker that said complete: the second is now one
    line and exit 2 while the first runs, and the first ends complete."""
    out = tmp_path / "demo"
    sets = [a for o in config_overrides for a in ("--set", o)]
    first = _demo_under_way(out, sets)
    second = invoke("demo", "-o", out, *sets)
    _, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert_one_line_error(second, contains="another bimfactor command is writing this folder now")
    assert read_marker(out)["complete"] is True
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]


@pytest.mark.skipif(not SLAMBOOK.is_dir(), reason="needs ../shared/data/real")
def test_an_output_folder_that_is_a_bind_mount_is_written_in_place(tmp_path: Path) -> None:
    """A bind mount of a folder of the same file system cannot be renamed (EBUSY, after all the work): it is written
    in place, as a volume is. Needs the privilege to bind-mount (a root container), else skipped."""
    source, out = tmp_path / "source", tmp_path / "out"
    source.mkdir()
    out.mkdir()
    if (
        shutil.which("mount") is None
        or subprocess.run(["mount", "--bind", source, out], capture_output=True).returncode
    ):
        pytest.skip("cannot bind-mount here")
    try:
        result = invoke("scene-graph", SLAMBOOK, "--intrinsics", "518,519,325.5,253.5", "-o", out)
        assert result.exit_code == 0, result.output
        assert (source / "scene_graph.json").is_file() and read_marker(out)["complete"] is True
    finally:
        subprocess.run(["umount", out], capture_output=True)
