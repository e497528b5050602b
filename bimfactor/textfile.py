"""Reading a user's text file: UTF-8 (a byte-order mark allowed), or one error that says where it is not."""

from __future__ import annotations

from pathlib import Path

from bimfactor.errors import InputError


def read_utf8(path: Path, error: type[InputError] = InputError, hint: str = "") -> str:
    """The text of `path`; `error` (one line: the file, the first bad byte, its offset and line, and `hint`) when it
    cannot be read or is not UTF-8."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or type(exc).__name__})") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise error(
            f"{path}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset {exc.start} (line {line})"
            + (f"; {hint}" if hint else "")
        ) from None
