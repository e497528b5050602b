"""The diagnostics in tools/ (scripts, loaded by path)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from bimfactor.perception.text import read_probability

TOOLS = Path(__file__).resolve().parent.parent / "tools"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_belief_at_truth_summary_splits_the_error_into_first_keyframes_and_late_strays() -> None:
    summarise = _load("belief_at_truth").summarise
    # Three runs of 12 keyframes: one settles at keyframe 3, one never had a particle at the truth until keyframe 2,
    # one strays 5 m away at keyframe 11.
    settles = [8.0, 4.0] + [0.1] * 10
    late = [6.0, 3.0, 1.0] + [0.2] * 9
    strays = [2.0] + [0.1] * 9 + [5.0, 5.0]
    runs = [
        {"trans_err_m": settles, "near_count": [3] * 12, "near_weight": [0.1, 0.5] + [0.9] * 10},
        {"trans_err_m": late, "near_count": [0, 4] + [9] * 10, "near_weight": [0.0, 0.2] + [0.8] * 10},
        {"trans_err_m": strays, "near_count": [5] * 12, "near_weight": [0.3] * 10 + [0.0, 0.0]},
    ]
    s = summarise(runs)
    total = sum(settles) + sum(late) + sum(strays)
    assert s["runs"] == 3
    assert s["trans_err_m"] == pytest.approx(total / 36)
    assert s["share_of_error_steps_1_4"] == pytest.approx((12.2 + 10.2 + 2.3) / total)
    assert s["runs_without_particle_at_truth_after_frame_1"] == 1
    assert s["first_step_with_particle_at_truth"] == [1, 2, 1]
    assert s["runs_off_by_2m_after_step_10"] == 1
    assert s["share_of_error_of_those_after_step_10"] == pytest.approx(10.0 / total)
    assert s["mean_weight_at_truth_by_step"][0] == pytest.approx(0.4 / 3)
    assert s["trans_err_by_step_m"][-1] == pytest.approx((0.1 + 0.2 + 5.0) / 3)


def test_text_reader_calibration_fits_the_sim_readers_rates() -> None:
    reader_model = _load("calibrate_text_reader")._reader_model
    rows = [
        {"text": "B201", "read": ["8201"], "sim_legible": True},  # one look-alike
        {"text": "A101", "read": ["T", "101"], "sim_legible": True},  # one lost; the best of two readings counts
        {"text": "A102", "read": ["A1X2"], "sim_legible": True},  # one other ("X" does not look like "0")
        {"text": "B104", "read": [], "sim_legible": True},  # not read
        {"text": "B105", "read": ["XXXX"], "sim_legible": False},  # not legible to the sim reader: left out
    ]
    for row, width in zip(rows, (60, 60, 60, 12, 60), strict=True):
        row["plate_width_px"] = width  # 15 px per character, and 3 for the plate not read
    fit = reader_model(rows)
    assert fit["legible_views"] == 4 and fit["read_share"] == pytest.approx(0.75)
    assert fit["characters"] == {"same": 9, "look_alike": 1, "other": 1, "dropped": 1, "inserted": 0}
    assert fit["look_alike_rate"] == fit["char_error_rate"] == fit["drop_rate"] == pytest.approx(1 / 12)
    # Every wide plate read, the narrow one not: the fitted chance is near its most for the one, near 0 for the other.
    chance = fit["read_probability"], fit["read_char_px"], fit["read_char_scale_px"]
    assert fit["read_probability"] > 0.95 and 3.0 < fit["read_char_px"] < 15.0
    assert read_probability(15.0, *chance) > 0.9 and read_probability(3.0, *chance) < 0.1
