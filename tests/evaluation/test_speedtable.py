"""`bench speed`'s parts that decide what it reports (the timings themselves are what the command measures)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bimfactor.evaluation.speedtable import TARGETS, SpeedRow, format_speed_table, wall_clock


def test_the_table_marks_each_target_met_or_missed() -> None:
    rows = [
        SpeedRow("full per keyframe, median", "duplex.ifc", 42.0, "ms", TARGETS["full per keyframe, median"]),
        SpeedRow("bimfactor --help", "-", 0.4, "s", TARGETS["bimfactor --help"]),
        SpeedRow("  planar / point_to_plane time", "paper floor", 1.7, "×"),
    ]
    assert [r.met for r in rows] == [False, True, None]
    lines = format_speed_table(rows).splitlines()
    assert lines[2] == "| full per keyframe, median | duplex.ifc | 42.0 ms | ≤ 30 ms | **no** |"
    assert lines[3] == "| bimfactor --help | - | 0.40 s | ≤ 1 s | yes |"
    assert lines[4] == "|   planar / point_to_plane time | paper floor | 1.70 × |  |  |"


def test_a_wall_clock_runs_a_fresh_process_and_a_failing_command_is_an_error(tmp_path: Path) -> None:
    assert wall_clock(["--help"], tmp_path) > 0.0
    with pytest.raises(RuntimeError, match=r"bimfactor prior .* failed"):
        wall_clock(["prior", str(tmp_path / "missing.ifc"), "-o", str(tmp_path / "p")], tmp_path)
