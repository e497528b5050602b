"""bench buildings: routes' outcomes, Ray's runs equal the process pool's, the report keyed by IFC file name."""

from __future__ import annotations

import json
from dataclasses import astuple
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from bimfactor.cli import app
from bimfactor.config import load_config
from bimfactor.evaluation.metrics import route_outcome


def _mode(x: float, probability: float, storey: int = 0) -> SimpleNamespace:
    return SimpleNamespace(pose=np.array([x, 0.0, 0.0]), storey=storey, probability=probability)


def test_route_outcome_success_distance_wrong_convergence_and_top3() -> None:
    gt = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])  # 1 m a step along x
    storeys = np.zeros(6, int)
    est = gt.copy()
    est[:3, 0] += [5.0, 3.0, 0.5]  # wrong for two steps, then right to the end
    est[2, 0] += 1.0  # ... step 2 still 1.5 m off
    converged = np.array([False, True, False, True, True, True])  # said converged at step 1, 3 m off: dangerous
    modes = [[_mode(gt[t, 0] + 4.0, 0.6), _mode(gt[t, 0] + (0.2 if t >= 1 else 9.0), 0.3)] for t in range(6)]
    out = route_outcome(est, storeys, gt, storeys, converged, modes)
    assert out.success and out.wrong_convergence
    assert out.distance_to_convergence_m == pytest.approx(3.0)  # correct from step 3 on, 3 m travelled by then
    assert out.keyframes_to_convergence == 3
    assert out.top3_share == pytest.approx(5 / 6)  # the second mode is right from step 1
    # On another storey nothing counts as correct, and saying converged there is a wrong convergence too.
    other = route_outcome(gt, storeys + 1, gt, storeys, np.ones(6, bool))
    assert not other.success and other.wrong_convergence and np.isnan(other.distance_to_convergence_m)
    assert np.isnan(other.top3_share)  # no modes: a variant without a back end
    calm = route_outcome(gt, storeys, gt, storeys, np.zeros(6, bool))
    assert calm.success and not calm.wrong_convergence and calm.distance_to_convergence_m == 0.0
    assert calm.keyframes_to_convergence == 0 and np.isnan(other.keyframes_to_convergence)


def test_ray_runs_equal_the_process_pool_runs(paper_floor_prior: Path, config_overrides: list[str]) -> None:
    pytest.importorskip("ray")
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.symmetry import twin_motions
    from bimfactor.evaluation.paper import paper_jobs, run_jobs

    cfg = load_config(
        None,
        [
            *config_overrides,
            "evaluation.num_trajectories=2",
            "evaluation.repeats=1",
            "evaluation.trajectory_length=4",
            "evaluation.warmup_max_steps=2",
            "evaluation.variants=[smcl,smcl+graph]",
        ],
    )
    jobs = paper_jobs(paper_floor_prior, cfg, twin_motions(BimPrior.load(paper_floor_prior)))
    local = run_jobs(jobs, "local", "processes", workers=1)
    on_ray = run_jobs(jobs, "ray", "ray", workers=1)
    assert [len(runs) for runs in on_ray] == [len(runs) for runs in local] == [2, 2]
    for mine, theirs in zip([r for runs in local for r in runs], [r for runs in on_ray for r in runs], strict=True):
        assert (mine.variant, mine.trajectory, mine.repeat) == (theirs.variant, theirs.trajectory, theirs.repeat)
        np.testing.assert_array_equal(mine.trans_err_m, theirs.trans_err_m)
        np.testing.assert_array_equal(mine.orient_err_deg, theirs.orient_err_deg)
        np.testing.assert_array_equal(mine.room_hit, theirs.room_hit)
        np.testing.assert_equal(astuple(mine.outcome), astuple(theirs.outcome))  # NaN equals NaN here


def test_bench_buildings_writes_a_block_per_ifc_file_name(
    paper_floor_prior: Path, cli_config_args: list[str], tmp_path: Path
) -> None:
    """One block per building; two files of one name in different folders are both run, each named by its folder."""
    import shutil

    ifc = paper_floor_prior.parent / "paper-floor.ifc"
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        shutil.copy(ifc, tmp_path / folder / ifc.name)
    out = tmp_path / "bench"
    result = CliRunner().invoke(
        app,
        [
            "bench", "buildings", str(tmp_path / "a" / ifc.name), str(tmp_path / "b" / ifc.name), "-o", str(out),
            "--runner", "processes", "--workers", "1",
            "--variant", "smcl+graph", *cli_config_args,
            "--set", "evaluation.num_trajectories=1", "--set", "evaluation.repeats=1",
            "--set", "evaluation.trajectory_length=4", "--set", "evaluation.warmup_max_steps=2",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads((out / "results.json").read_text())
    assert sorted(report["buildings"]) == ["a/paper-floor.ifc", "b/paper-floor.ifc"]
    block = report["buildings"]["a/paper-floor.ifc"]["smcl+graph"]["average"]
    for key in ("trans_err_m", "orient_err_deg", "room_acc", "storey_acc", "success_rate", "wrong_convergence_rate"):
        assert key in block
    assert 0.0 <= block["success_rate"] <= 1.0 and block["top3_rate"] is not None
    assert report["worst"]["building"] in report["buildings"]
    assert "## b/paper-floor.ifc" in (out / "report.md").read_text() and (out / "buildings.png").stat().st_size > 0
    assert sorted(p.name for p in (out / "priors").iterdir()) == ["a", "b"]


def test_bench_buildings_records_every_forward_pass(
    paper_floor_prior: Path, cli_config_args: list[str], tmp_path: Path
) -> None:
    pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")
    from tests.evaluation.recordings import logged

    out, recordings = tmp_path / "bench", tmp_path / "rrd"
    result = CliRunner().invoke(
        app,
        [
            "bench", "buildings", str(paper_floor_prior.parent / "paper-floor.ifc"), "-o", str(out),
            "--runner", "processes", "--workers", "1", "--variant", "smcl", "--rerun", str(recordings),
            *cli_config_args,
            "--set", "evaluation.num_trajectories=1", "--set", "evaluation.repeats=2",
            "--set", "evaluation.trajectory_length=4", "--set", "evaluation.warmup_max_steps=2",
        ],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in recordings.iterdir())
    assert names == ["paper-floor-t0-r0-smcl.rrd", "paper-floor-t0-r1-smcl.rrd"], names
    found = logged(recordings / names[0])
    assert found["world/estimate"] == found["world/truth"] and len(found["world/estimate"]) >= 4
    assert (out / "results.json").is_file()


def test_bench_buildings_refuses_bad_input_before_any_prior(tmp_path: Path) -> None:
    runner = CliRunner()
    broken = tmp_path / "broken.ifc"
    broken.write_text("not an ifc\n")
    for args, message in (
        ([str(tmp_path / "gone.ifc")], "no such IFC file"),
        ([str(broken)], "not an IFC file"),
        ([str(broken), "--runner", "slurm"], "unknown runner"),
        ([str(broken), "--address", "garbage"], "--address 'garbage': expected ray://HOST:PORT, HOST:PORT or auto"),
        ([str(broken), "--runner", "processes", "--address", "head:6379"], "it applies to --runner ray"),
        ([str(broken), "--rerun", str(broken)], "a folder, not a file"),
        ([str(broken), "--rerun", str(tmp_path / "out" / "rrd")], "lies inside"),
        ([str(broken), "--rerun", str(tmp_path / "rrd"), "--scenario", "active"], "the active scenario has none"),
    ):
        result = runner.invoke(app, ["bench", "buildings", *args, "-o", str(tmp_path / "out")])
        assert result.exit_code == 2 and message in result.output, result.output
        assert not (tmp_path / "out").exists()
    # "paper-floor" names the preset, not a file: the error is about the missing file after it
    result = runner.invoke(app, ["bench", "buildings", "paper-floor", str(tmp_path / "gone.ifc"), "-o", str(tmp_path)])
    assert result.exit_code == 2 and "gone.ifc" in result.output and "paper-floor" not in result.output


def test_a_prior_is_kept_only_for_the_same_ifc_and_prior_settings(
    paper_floor_prior: Path, config_overrides: list[str], tmp_path: Path
) -> None:
    import shutil

    from bimfactor.evaluation.buildings import reusable_prior

    ifc = paper_floor_prior.parent / "paper-floor.ifc"
    cfg = load_config(None, config_overrides)
    prior_dir = tmp_path / "prior"
    shutil.copytree(paper_floor_prior, prior_dir)
    (prior_dir / "config.yaml").write_text(cfg.dump_yaml())  # as bench buildings saves it
    assert reusable_prior(prior_dir, ifc, cfg)
    # the filter or the simulator may change: the prior stays
    assert reusable_prior(prior_dir, ifc, load_config(None, [*config_overrides, "smcl.num_particles=500"]))
    # a prior setting, the seed or another file: it is rebuilt
    assert not reusable_prior(prior_dir, ifc, load_config(None, [*config_overrides, "bim.grid.resolution_m=0.1"]))
    assert not reusable_prior(prior_dir, ifc, load_config(None, [*config_overrides, "seed=1"]))
    edited = tmp_path / "edited.ifc"
    edited.write_bytes(ifc.read_bytes() + b"/* edited */\n")
    assert not reusable_prior(prior_dir, edited, cfg)
    (prior_dir / "config.yaml").unlink()
    assert not reusable_prior(prior_dir, ifc, cfg)
