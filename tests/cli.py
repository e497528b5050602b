"""Running the `bimfactor` command in tests, and what every error of it must look like."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from bimfactor.cli import app

runner = CliRunner()


def invoke(*args: str | Path):
    """`bimfactor ARGS...` in this process (stdout and stderr apart)."""
    return runner.invoke(app, [str(a) for a in args])


def assert_one_line_error(result, exit_code: int = 2, contains: str = "") -> str:
    """Exit code as given, exactly one `error:` line on stderr, no traceback anywhere; returns the line."""
    assert isinstance(result.exception, SystemExit), f"uncaught {result.exception!r}"
    assert result.exit_code == exit_code, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    assert exit_code == 1 or "internal" not in lines[0], lines[0]
    assert contains in lines[0], lines[0]
    return lines[0]
