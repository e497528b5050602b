"""Safe outputs (`bimfactor.io.atomic`): only bimfactor's own folders are replaced, never an input, and an
interrupted write is either finished or undone by the next one."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bimfactor.errors import InputError
from bimfactor.io import atomic
from bimfactor.io.atomic import (
    MARKER,
    atomic_path,
    check_output_dir,
    container_dir,
    output_dir,
    read_marker,
    recover,
    write_text_atomic,
)


def _write_run(path: Path, text: str = "new", **kwargs) -> None:
    with output_dir(path, "run", **kwargs) as tmp:
        (tmp / "estimate.txt").write_text(text)
        (tmp / "modes").mkdir()
        (tmp / "modes" / "mode_0.txt").write_text(text)


def _tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): p.read_text() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_new_folder_gets_its_files_and_a_marker_listing_them(tmp_path: Path) -> None:
    _write_run(tmp_path / "run")
    marker = read_marker(tmp_path / "run")
    assert marker is not None
    assert marker["kind"] == "run" and marker["complete"] is True
    assert marker["files"] == ["estimate.txt", "modes/mode_0.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no temporaries left beside it


def test_a_folder_of_the_same_kind_is_replaced_whole(tmp_path: Path) -> None:
    _write_run(tmp_path / "run", "old")
    with output_dir(tmp_path / "run", "run") as tmp:
        (tmp / "estimate.txt").write_text("new")
    assert _tree(tmp_path / "run") == {MARKER: (tmp_path / "run" / MARKER).read_text(), "estimate.txt": "new"}


@pytest.mark.parametrize("replace", [True, False])
def test_a_folder_without_a_marker_is_never_touched(tmp_path: Path, replace: bool) -> None:
    user = tmp_path / "photos"
    user.mkdir()
    (user / "holiday.jpg").write_text("precious")
    with (
        pytest.raises(InputError, match="holds no bimfactor output marker"),
        output_dir(user, "sequence", replace=replace),
    ):
        pytest.fail("the block must not run")
    assert _tree(user) == {"holiday.jpg": "precious"}


def test_a_folder_of_another_kind_is_refused(tmp_path: Path) -> None:
    _write_run(tmp_path / "out")
    with pytest.raises(InputError, match="is a bimfactor run folder, not a prior folder"):
        check_output_dir(tmp_path / "out", "prior")


def test_a_file_the_marker_does_not_list_keeps_the_whole_folder(tmp_path: Path) -> None:
    _write_run(tmp_path / "run", "old")
    (tmp_path / "run" / "NOTES.txt").write_text("mine")
    (tmp_path / "run" / "modes" / "extra.txt").write_text("mine too")
    with pytest.raises(InputError, match=r"holds NOTES\.txt, which bimfactor did not write"):
        _write_run(tmp_path / "run")
    assert _tree(tmp_path / "run")["NOTES.txt"] == "mine"
    assert _tree(tmp_path / "run")["estimate.txt"] == "old"
    (tmp_path / "run" / "NOTES.txt").unlink()
    with pytest.raises(InputError, match=r"holds modes/extra\.txt"):
        _write_run(tmp_path / "run")


def test_replacing_an_own_folder_needs_replace_when_asked(tmp_path: Path) -> None:
    with output_dir(tmp_path / "seq", "sequence") as tmp:
        (tmp / "frames.csv").write_text("old")
    with pytest.raises(InputError, match=r"exists already \(--overwrite replaces it\)"):
        check_output_dir(tmp_path / "seq", "sequence", replace=False)
    check_output_dir(tmp_path / "seq", "sequence", replace=True)


def test_an_output_never_swallows_its_input(tmp_path: Path) -> None:
    _write_run(tmp_path / "prior")
    model = tmp_path / "prior" / "model.ifc"
    with pytest.raises(InputError, match="holds this command's input"):
        check_output_dir(tmp_path / "prior", "run", inputs=[model])
    with pytest.raises(InputError, match="holds this command's input"):
        check_output_dir(tmp_path / "prior", "run", inputs=[tmp_path / "prior"])
    with pytest.raises(InputError, match="holds this command's input"):
        check_output_dir(tmp_path / "bench", "bench", inputs=[tmp_path / "bench"])


def test_a_failing_block_leaves_the_old_folder_and_no_temporary(tmp_path: Path) -> None:
    _write_run(tmp_path / "run", "old")
    with pytest.raises(RuntimeError), output_dir(tmp_path / "run", "run") as tmp:
        (tmp / "estimate.txt").write_text("half")
        raise RuntimeError("crash while writing")
    assert _tree(tmp_path / "run")["estimate.txt"] == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_a_swap_cut_between_its_two_renames_is_undone_by_the_next_write(tmp_path: Path) -> None:
    """The state a crash between `path → .path.old` and `tmp → path` leaves: the old output is restored."""
    run = tmp_path / "run"
    _write_run(run, "old")
    os.replace(run, tmp_path / ".run.old")
    recover(run)
    assert _tree(run)["estimate.txt"] == "old"
    assert not (tmp_path / ".run.old").exists()
    # A crash after the second rename: the new output is in place, the old one beside it is dropped.
    _write_run(tmp_path / ".run.old", "older")
    _write_run(run, "new")
    assert _tree(run)["estimate.txt"] == "new"
    assert not (tmp_path / ".run.old").exists()


def test_a_backup_name_that_bimfactor_did_not_write_is_left_alone(tmp_path: Path) -> None:
    (tmp_path / ".run.old").mkdir()
    (tmp_path / ".run.old" / "mine.txt").write_text("mine")
    _write_run(tmp_path / "run")
    assert _tree(tmp_path / ".run.old") == {"mine.txt": "mine"}


def test_a_backup_holding_a_file_bimfactor_did_not_write_is_never_deleted(tmp_path: Path) -> None:
    """A copy of an output under the backup name, with a file of the user's added: neither the recovery nor the
    next replacement deletes it; the replacement is refused before its work, the output left as it was."""
    run, backup = tmp_path / "run", tmp_path / ".run.old"
    _write_run(run, "first")
    shutil.copytree(run, backup)
    (backup / "NOTES.txt").write_text("n")
    recover(run)
    with pytest.raises(InputError, match=r"\.run\.old: is in the way of replacing"):
        _write_run(run, "second")
    assert _tree(backup)["NOTES.txt"] == "n" and _tree(backup)["estimate.txt"] == "first"
    assert _tree(run)["estimate.txt"] == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".run.old", "run"]  # no temporary left


def test_temporaries_of_a_killed_writer_are_removed_by_the_next_write(tmp_path: Path) -> None:
    script = textwrap.dedent(
        f"""
        import os, signal
        from pathlib import Path
        from bimfactor.io.atomic import output_dir, write_text_atomic
        with output_dir(Path({str(tmp_path / "run")!r}), "run") as tmp:
            (tmp / "estimate.txt").write_text("half")
            stale = Path({str(tmp_path)!r}) / f".results.json.{{os.getpid()}}.x.part"
            stale.write_text("half")
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    left = sorted(p.name for p in tmp_path.iterdir())
    assert len(left) == 2 and all(name.endswith(".part") for name in left), left
    _write_run(tmp_path / "run")
    write_text_atomic(tmp_path / "results.json", "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json", "run"]


def test_a_live_writers_temporary_is_kept(tmp_path: Path) -> None:
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".run.{sleeper.pid}.abc.part"
        live.mkdir()
        _write_run(tmp_path / "run")
        assert live.is_dir()
    finally:
        sleeper.kill()
        sleeper.wait()


def test_the_umask_decides_permissions(tmp_path: Path) -> None:
    old = os.umask(0o002)
    try:
        _write_run(tmp_path / "run")
        with atomic_path(tmp_path / "figure.png") as tmp:
            tmp.write_bytes(b"png")
    finally:
        os.umask(old)
    assert (tmp_path / "run").stat().st_mode & 0o777 == 0o775
    assert (tmp_path / "run" / "modes").stat().st_mode & 0o777 == 0o775
    assert (tmp_path / "run" / "estimate.txt").stat().st_mode & 0o777 == 0o664
    assert (tmp_path / "run" / MARKER).stat().st_mode & 0o777 == 0o664
    assert (tmp_path / "figure.png").stat().st_mode & 0o777 == 0o664


def test_a_mount_point_is_written_inside_not_renamed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    volume = tmp_path / "volume"
    volume.mkdir()
    real_ismount = os.path.ismount
    monkeypatch.setattr(atomic.os.path, "ismount", lambda p: Path(p) == volume or real_ismount(p))
    renamed: list[tuple[str, str]] = []
    real_replace = os.replace

    def spy(src, dst):
        renamed.append((str(src), str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", spy)
    _write_run(volume, "old")
    with output_dir(volume, "run") as tmp:
        (tmp / "estimate.txt").write_text("new")
        (tmp / "steps.csv").write_text("new")
    assert all(Path(src) != volume for src, _ in renamed)  # the mount point itself is never renamed
    assert _tree(volume) == {MARKER: (volume / MARKER).read_text(), "estimate.txt": "new", "steps.csv": "new"}
    assert read_marker(volume) == {**json.loads((volume / MARKER).read_text()), "complete": True}


def test_a_container_is_marked_complete_only_at_the_end(tmp_path: Path) -> None:
    with container_dir(tmp_path / "bench", "bench") as folder:
        write_text_atomic(folder / "results.json", "{}")
        assert read_marker(folder)["complete"] is False
    assert read_marker(tmp_path / "bench")["complete"] is True
    (tmp_path / "bench" / "my-notes.txt").write_text("kept")
    with container_dir(tmp_path / "bench", "bench") as folder:
        write_text_atomic(folder / "results.json", "{}")
    assert (tmp_path / "bench" / "my-notes.txt").read_text() == "kept"


def test_unwritable_places_are_refused_before_any_work(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is a file"):
        check_output_dir(tmp_path / "file", "run")
    with pytest.raises(InputError, match=r"cannot be created, .* is a file"):
        check_output_dir(tmp_path / "file" / "run", "run")


def test_a_read_only_folder_is_refused(tmp_path: Path) -> None:
    """A real permission check; as root (CI) in a child process without the capability to override permissions."""
    readonly = tmp_path / "readonly"
    readonly.mkdir()
    readonly.chmod(0o555)
    script = textwrap.dedent(
        f"""
        from bimfactor.errors import InputError
        from bimfactor.io.atomic import check_output_dir
        try:
            check_output_dir({str(readonly / "run")!r}, "run")
        except InputError as exc:
            print(exc)
        """
    )
    command = [sys.executable, "-c", script]
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        assert setpriv is not None, "setpriv (util-linux) is needed to drop root's permission override"
        command = [setpriv, "--bounding-set=-dac_override,-dac_read_search", *command]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert "cannot write here (Permission denied)" in proc.stdout, proc.stdout + proc.stderr
    assert list(readonly.iterdir()) == []
