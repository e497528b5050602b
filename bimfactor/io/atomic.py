"""Safe outputs: a file or folder appears complete under its final name or not at all, and nothing bimfactor did
not write is ever removed.

Every folder a command writes carries a marker file, `.bimfactor.json` (`{"kind", "complete", "files"}`), written
last; a command replaces only a folder of its own kind whose every file the marker lists, and an output never
swallows its input. `output_dir` (prior, sequence, run) builds in a hidden temporary folder and swaps it in (on a
mount point: moves the files in one by one); `container_dir` (demo, bench, `simulate --all`) collects several outputs,
each written atomically. Temporary names carry the writer's pid (`.NAME.<pid>.<random>.part`), so a later run removes
what a killed run left behind. docs/reliability.md.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from bimfactor.errors import InputError

log = logging.getLogger(__name__)

MARKER = ".bimfactor.json"
ATOMIC_KINDS = ("prior", "sequence", "run", "scene-graph")
CONTAINER_KINDS = ("demo", "bench", "sequences")


def _umask() -> int:
    """The process's umask (read by setting it, so set back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}."


# ------------------------------------------------------------------------------------------------ files


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds.

    Works for writers that insist on a file name (ifcopenshell, matplotlib, numpy) as well as our own.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp_name = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=".part" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    os.chmod(tmp, 0o666 & ~_umask())
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def check_output_file(path: str | Path, *, inputs: Iterable[str | Path] = ()) -> None:
    """Raise InputError unless a file can be written at `path`: not a folder, not an input, in a writable place."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give a file name")
    for given in inputs:
        if _same(path, Path(given)):
            raise InputError(f"{path}: is also this command's input; write the output elsewhere")
    _check_writable(path.parent)


# ------------------------------------------------------------------------------------------------ folders


def read_marker(folder: str | Path) -> dict | None:
    """The folder's marker (`{"kind", "complete", "files"}`), or None when it has none or an unreadable one."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("kind"), str) or not isinstance(data.get("files"), list):
        return None
    return data


def through_link(path: Path) -> Path:
    """The folder a link at `path` points to (`runs/latest` → `runs/2026-11-28`): the output replaces that folder and
    the link stays a link; any other path as it is."""
    return path.resolve() if path.is_symlink() and path.is_dir() else path


def is_mount_point(path: Path) -> bool:
    """Whether `path` is a mount point, a bind mount of a folder of the same file system included (which
    `os.path.ismount` misses, and which cannot be renamed: EBUSY)."""
    if os.path.ismount(path):
        return True
    try:
        target = str(Path(path).resolve())
        with open("/proc/self/mountinfo", encoding="utf-8", errors="replace") as f:
            points = {line.split()[4].replace("\\040", " ") for line in f if len(line.split()) > 4}
    except OSError:
        return False
    return target in points


def check_output_dir(
    path: str | Path, kind: str, *, inputs: Iterable[str | Path] = (), replace: bool = True, flag: str = "--overwrite"
) -> None:
    """Raise InputError unless a `kind` folder may be written at `path`; cheap, so call it before the heavy work.

    Allowed: an absent or empty folder in a writable place, or a folder of the same kind that bimfactor wrote (every
    file in it listed in its marker; for an atomic kind only with `replace`). Refused: a file, any other non-empty
    folder, a place that holds one of `inputs` (an IFC, a prior, a sequence) or lies inside one that would
    be replaced, and a replacement whose backup name (`.NAME.old`) something of the user's holds.
    """
    path = Path(path)
    name_max = _name_max(path.parent)
    if len(path.name.encode()) > name_max:
        raise InputError(
            f"{path.parent / path.name[:40]}…: a name of {len(path.name.encode())} bytes, longer than this file "
            f"system's {name_max}"
        )
    if path.is_symlink() and not path.exists():
        raise InputError(
            f"{path}: is a link to nothing (a missing target or a loop of links); remove it or choose another"
        )
    path = through_link(path)
    for given in map(Path, inputs):
        if _same(path, given) or (kind in ATOMIC_KINDS and _inside(given, path)):
            raise InputError(f"{path}: holds this command's input {given}; write the output to another folder")
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: is a file, not a folder")
    if path.is_dir() and any(path.iterdir()):
        marker = read_marker(path)
        if marker is None:
            raise InputError(
                f"{path}: is not empty and holds no bimfactor output marker ({MARKER}); choose a new or empty folder "
                "(nothing in it was touched)"
            )
        if marker["kind"] != kind:
            raise InputError(f"{path}: is a bimfactor {marker['kind']} folder, not a {kind} folder; choose another")
        if kind in ATOMIC_KINDS:
            foreign = _unlisted(path, marker)
            if foreign is not None:
                raise InputError(
                    f"{path}: holds {foreign}, which bimfactor did not write there; move it away or choose another "
                    "folder (nothing was touched)"
                )
            if not replace:
                raise InputError(f"{path}: exists already ({flag} replaces it)")
            if not is_mount_point(path):
                _check_backup_free(path)
    _check_writable(path if is_mount_point(path) else path.parent)


@contextlib.contextmanager
def output_dir(
    path: str | Path, kind: str, *, inputs: Iterable[str | Path] = (), replace: bool = True, flag: str = "--overwrite"
) -> Iterator[Path]:
    """Yield an empty temporary folder; when the block succeeds it becomes `path`, marker written last.

    Checks the destination first (`check_output_dir`). The folder replaced, if any, was bimfactor's own.
    """
    if kind not in ATOMIC_KINDS:
        raise ValueError(f"output_dir: kind {kind!r} is not one of {ATOMIC_KINDS}")
    path = through_link(Path(path))
    recover(path)
    check_output_dir(path, kind, inputs=inputs, replace=replace, flag=flag)
    if is_mount_point(path):
        with _in_place(path, kind) as tmp:
            yield tmp
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _make_temp_dir(path.parent, _temp_prefix(path))
    try:
        yield tmp
        _write_marker(tmp, kind, complete=True)
        if path.exists():
            backup = _backup(path)
            os.replace(path, backup)
            os.replace(tmp, path)
            shutil.rmtree(backup, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def container_dir(path: str | Path, kind: str, *, inputs: Iterable[str | Path] = ()) -> Iterator[Path]:
    """Yield `path` as a folder that collects several outputs (a demo, a benchmark); marked complete at the end."""
    if kind not in CONTAINER_KINDS:
        raise ValueError(f"container_dir: kind {kind!r} is not one of {CONTAINER_KINDS}")
    path = through_link(Path(path))
    check_output_dir(path, kind, inputs=inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _exclusive(path):
        path.mkdir(exist_ok=True)
        _write_marker(path, kind, complete=False)
        yield path
        _write_marker(path, kind, complete=True)


@contextlib.contextmanager
def _exclusive(path: Path) -> Iterator[None]:
    """Hold `.NAME.lock` beside `path` (an advisory lock the system drops when the process dies): a second command
    writing the same collecting folder at once is refused instead of mixing its outputs with the first's."""
    import fcntl

    lock = path.with_name(f".{path.name}.lock")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(
                f"{path}: another bimfactor command is writing this folder now; wait or choose another"
            ) from None
        try:
            yield
        finally:
            lock.unlink(missing_ok=True)  # while still held: a waiting command then finds none to fight over
    finally:
        os.close(fd)


def recover(path: str | Path) -> None:
    """Finish what an interrupted write to `path` left: restore a folder that a replacement had moved aside, drop
    one that the replacement had already superseded, and remove dead writers' temporaries."""
    path = Path(path)
    backup = _backup(path)
    if _own_backup(backup):
        if path.exists():
            shutil.rmtree(backup, ignore_errors=True)
        else:
            os.replace(backup, path)
            log.warning("%s: restored the previous output, which an interrupted run had moved aside", path)
    remove_stale_temporaries(path)
    if is_mount_point(path):
        remove_stale_temporaries(path / "bimfactor")


def _own_backup(backup: Path) -> bool:
    """Whether `backup` is a folder bimfactor moved aside: a real folder with a marker listing every file in it (the
    rule by which a command replaces a folder at all); anything else under that name is the user's."""
    if backup.is_symlink() or not backup.is_dir():
        return False
    marker = read_marker(backup)
    return marker is not None and _unlisted(backup, marker) is None


def _check_backup_free(path: Path) -> None:
    """InputError when `path` is to be replaced and the name its old output moves to is taken by something
    bimfactor did not write (one it did write, `recover` restores or drops)."""
    backup = _backup(path)
    if path.exists() and (backup.exists() or backup.is_symlink()) and not _own_backup(backup):
        raise InputError(
            f"{backup}: is in the way of replacing {path} and is not an output bimfactor moved aside (it holds files "
            "its marker does not list, or none); move or remove it"
        )


def remove_stale_temporaries(path: Path) -> None:
    """Remove `.NAME.<pid>.*.part*` temporaries beside `path` whose writer is gone (killed before it cleaned up)."""
    parent = path.parent
    if not parent.is_dir():
        return
    prefix = f".{path.name}."
    for entry in parent.glob(f"{glob_escape(prefix)}*.part*"):
        pid_text = entry.name[len(prefix) :].split(".", 1)[0]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        log.info("removed %s, left by an interrupted run", entry)


def glob_escape(text: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in text)


# ------------------------------------------------------------------------------------------------ internals


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _backup(path: Path) -> Path:
    return path.with_name(f".{path.name}.old")


def _make_temp_dir(parent: Path, prefix: str) -> Path:
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".part", dir=parent))
    os.chmod(tmp, 0o777 & ~_umask())
    return tmp


def _files(folder: Path) -> list[str]:
    names = (str(p.relative_to(folder)) for p in folder.rglob("*") if not p.is_dir() or p.is_symlink())
    return sorted(name for name in names if name != MARKER)


def _write_marker(folder: Path, kind: str, *, complete: bool, files: list[str] | None = None) -> None:
    from bimfactor import __version__

    marker = {"kind": kind, "complete": complete, "bimfactor": __version__, "files": files or _files(folder)}
    write_text_atomic(folder / MARKER, json.dumps(marker, indent=1) + "\n")


def _unlisted(folder: Path, marker: dict) -> str | None:
    """The first file or link under `folder` that its marker does not list (None when all are listed)."""
    listed = set(marker["files"])
    for entry in sorted(folder.rglob("*")):
        rel = str(entry.relative_to(folder))
        if entry.name == MARKER and entry.parent == folder:
            continue
        if entry.is_dir() and not entry.is_symlink():
            if not any(name.startswith(rel + os.sep) for name in listed):
                return rel + os.sep
            continue
        if rel not in listed:
            return rel
    return None


def _same(a: Path, b: Path) -> bool:
    return a.resolve() == b.resolve()


def _inside(child: Path, parent: Path) -> bool:
    return child.resolve().is_relative_to(parent.resolve())


def _name_max(folder: Path) -> int:
    """The longest file name the file system of `folder` (or its nearest existing ancestor) takes, in bytes."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def _check_writable(where: Path) -> None:
    """Raise InputError unless a file can be created at `where` or its nearest existing ancestor (a real probe)."""
    probe_dir = where
    while not probe_dir.exists():
        if probe_dir.is_symlink():
            raise InputError(f"{probe_dir}: is a broken link")
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        raise InputError(f"{where}: cannot be created, {probe_dir} is a file")
    try:
        fd, probe = tempfile.mkstemp(prefix=_temp_prefix(Path("write-probe")), suffix=".part", dir=probe_dir)
    except OSError as exc:
        raise InputError(f"{probe_dir}: cannot write here ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(probe)


@contextlib.contextmanager
def _in_place(path: Path, kind: str) -> Iterator[Path]:
    """`output_dir` for a mount point: build inside it, then move the new files over the old ones it listed."""
    tmp = _make_temp_dir(path, _temp_prefix(Path("bimfactor")))
    try:
        yield tmp
        new = _files(tmp)
        old = read_marker(path)
        old_files = [] if old is None else [f for f in old["files"] if isinstance(f, str)]
        _write_marker(path, kind, complete=False, files=sorted({*old_files, *new}))
        for rel in old_files:
            (path / rel).unlink(missing_ok=True)
        for folder in sorted((p for p in path.rglob("*") if p.is_dir() and not p.is_symlink()), reverse=True):
            if not folder.is_relative_to(tmp) and not any(folder.iterdir()):
                folder.rmdir()
        for entry in tmp.iterdir():
            os.replace(entry, path / entry.name)
        _write_marker(path, kind, complete=True, files=new)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
