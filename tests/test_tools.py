"""The diagnostics in tools/ (scripts, loaded by path)."""

from __future__ import annotations

import importlib.util
import json
import re
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


def _bench_paper_report(trans: float, *, variants: tuple[str, ...] = ("smcl", "smcl+graph")) -> dict:
    """A results.json of `bimfactor bench paper` cut down to what the renderer reads: two routes of one repeat."""

    def cell(t: float, runs: int) -> dict:
        return {
            "trans_err_m": t,
            "trans_err_std_m": t / 2,
            "orient_err_deg": 10 * t,
            "orient_err_std_deg": 5 * t,
            "room_acc": 0.95,
            "room_acc_std": 0.2,
            "step_ms_median": 4.6,
            "steps_to_converge": [3] * runs,
            "scored_from_steps": [4, 7][:runs],
            "converged_runs": runs,
            "runs": runs,
            "relocalized_runs": 0,
            "challenged_runs": 0,
            "trans_err_conv_m": t / 4,
            "orient_err_conv_deg": t,
            "trans_err_conv_run_mean_m": t / 4,
            "ellipse_coverage": 0.97,
            "from_start": {
                "trans_err_m": 3 * t,
                "trans_err_std_m": t,
                "orient_err_deg": 30 * t,
                "orient_err_std_deg": t,
                "room_acc": 0.9,
            },
        }

    report: dict = {
        "benchmark": "paper",
        "created_utc": "2025-01-01T00:00:00+00:00",
        "prior": "runs/bench-paper/prior",
        "protocol": {
            "trajectories": 2,
            "steps": 50,
            "repeats": 1,
            "score_from": "filter_converged",
            "warmup_max_steps": 30,
            "scenario": "global",
        },
        "variants": list(variants),
        "storeys": 1,
        "twins": {},
    }
    for i, variant in enumerate(variants):
        t = trans / (i + 1)
        average = {
            **cell(t, 2),
            "trans_err_ci95_m": [t / 2, 2 * t],
            "orient_err_ci95_deg": [1.0, 9.0],
            "room_acc_ci95": [0.9, 1.0],
        }
        report[variant] = {"average": average, "per_trajectory": {"0": cell(t, 1), "1": cell(t, 1)}}
    return report


def test_render_results_writes_table_one_into_the_readme_and_the_full_tables_into_a_page(tmp_path: Path) -> None:
    render = _load("render_results")
    results = tmp_path / "docs/results"
    results.mkdir(parents=True)
    (results / "paper-floor-seed0-default.json").write_text(json.dumps(_bench_paper_report(0.3)))
    (results / "paper-floor-seed1-default.json").write_text(json.dumps(_bench_paper_report(0.5)))
    # Other benchmarks' results lie beside them, for renderers of their own: left alone, not an error.
    (results / "buildings.json").write_text(json.dumps({"benchmark": "buildings", "buildings": {}}))
    (results / "speed.json").write_text(json.dumps({"benchmark": "speed"}))
    readme, page = tmp_path / "README.md", tmp_path / "docs/results.md"
    readme.write_text("# x\n\nbefore\n<!-- results:begin -->\nold table\n<!-- results:end -->\nafter\n")
    args = ["--results", str(results), "--readme", str(readme), "--page", str(page)]

    assert render.main(args) == 0
    text = readme.read_text()
    assert text.startswith("# x\n\nbefore\n<!-- results:begin -->\n") and text.endswith("<!-- results:end -->\nafter\n")
    assert "old table" not in text and "buildings" not in text
    assert (
        "| Variant | [seed 0, default](docs/results/paper-floor-seed0-default.json) "
        "| [seed 1, default](docs/results/paper-floor-seed1-default.json) |" in text
    )
    assert "| smcl | 0.30 m / 3.0° / 95.0 % | 0.50 m / 5.0° / 95.0 % |" in text
    assert "| smcl+graph | 0.15 m / 1.5° / 95.0 % | 0.25 m / 2.5° / 95.0 % |" in text
    # The command that regenerates each file: the default preset needs no -c, seed 1 its --set, 2 x 1 runs theirs.
    seed1 = re.search(r"- seed 1, default \(2 runs, .*\): `(.*)`", text)[1]
    assert seed1.startswith(".venv/bin/bimfactor bench paper --set seed=1 --set evaluation.num_trajectories=2")
    assert "-c " not in seed1 and "--variant smcl --variant smcl+graph" in seed1
    assert seed1.endswith(
        "-o runs/paper-floor-seed1-default && cp runs/paper-floor-seed1-default/results.json "
        "docs/results/paper-floor-seed1-default.json"
    )

    full = page.read_text()
    row = "| [seed 0, default](results/paper-floor-seed0-default.json) | smcl | 0.30 [0.15–0.60] | 3.0 [1.0–9.0] "
    assert row in full
    assert "| 0.075 m / 0.30° | 2 / 2 | 97 % | 0.90 m / 9.0° / 90.0 % |" in full
    assert "| 2 | 0.30 ± 0.15 | 3.0 ± 1.5 | 95.0 ± 20.0 | 1 / 1 | 0.075 m / 0.30° | 97 % |" in full
    assert "- the same runs from their first frame (the uniform cloud included): 0.90 m, 9.0°, 90.0 %" in full
    assert "- scored from the step the filter first reported itself converged: median step 5.5 (range 4–7)" in full

    # Rendering again changes nothing; --check agrees.
    before = readme.read_text(), page.read_text()
    assert render.main(args) == 0 and (readme.read_text(), page.read_text()) == before
    assert render.main([*args, "--check"]) == 0

    # A run of the paper preset gets its own column beside the default one, with -c in its command.
    (results / "paper-floor-seed0-paper.json").write_text(json.dumps(_bench_paper_report(0.7, variants=("smcl",))))
    assert render.main([*args, "--check"]) == 1
    render.main(args)
    text = readme.read_text()
    assert re.search(r"\| Variant \| \[seed 0, default\]\(.*\) \| \[seed 0, paper\]\(.*\) \| \[seed 1, default\]", text)
    assert "| smcl+graph | 0.15 m / 1.5° / 95.0 % | – | 0.25 m / 2.5° / 95.0 % |" in text
    assert "bimfactor bench paper -c paper " in text


def test_the_speed_page_is_the_committed_speed_results_rendered() -> None:
    """docs/speed.md's table is docs/results/speed.json as `tools/render_speed.py` renders it, and it holds every
    figure the issue names (a stale or hand-edited page fails until the tool is run)."""
    render = _load("render_speed")
    page = render.PAGE.read_text()
    assert render.replace_block(page, render.render(), render.BEGIN, render.END) == page
    names = {r["what"] for r in json.loads(render.RESULTS.read_text())["rows"]}
    from bimfactor.evaluation.speedtable import TARGETS

    assert set(TARGETS) <= names


def test_the_buildings_page_is_the_committed_buildings_results_rendered() -> None:
    """docs/buildings.md's tables are docs/results/buildings*.json as `tools/render_buildings.py` renders them, with a
    block for the paper floor and every shared IFC file (a stale or hand-edited page fails until the tool is run)."""
    render = _load("render_buildings")
    assert render.main(["--check"]) == 0
    report = json.loads(render.RESULTS["buildings"].read_text())
    assert "paper-floor.ifc" in report["buildings"] and "AC11-Institute-Var-2-IFC.ifc" in report["buildings"]
    for block in report["buildings"].values():
        average = block[report["variants"][0]]["average"]
        assert {"trans_err_m", "orient_err_deg", "room_acc", "success_rate", "wrong_convergence_rate"} <= set(average)


def test_the_paper_reproduction_page_is_the_committed_ablation_rendered() -> None:
    """docs/paper-reproduction.md is docs/results/paper-ablation.json as `tools/paper_ablation.py render` writes it:
    one row per step on both seeds, from the paper's filter alone to every component of ours added."""
    ablation = _load("paper_ablation")
    assert ablation.main(["render", "--check"]) == 0
    report = json.loads(ablation.RESULTS.read_text())
    assert [s["set"] for s in report["steps"]] == [own for _, own in ablation.STEPS]
    for seed in report["seeds"]:
        rows = report["rows"][str(seed)]
        assert len(rows) == len(ablation.STEPS) and all(0.0 <= r["success_rate"] <= 1.0 for r in rows)
