"""The registration commands end to end: compare-registrars on a recorded sequence, and bench registration."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bimfactor.cli import app

from ..sim.conftest import Building

runner = CliRunner()
SHORT = ["--set", "evaluation.num_trajectories=2"]  # the first dozen keyframes see too little wall


def invoke(*args: str | Path):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def prior_and_sequence(paper_floor: Building, tmp_path_factory: pytest.TempPathFactory, cli_config_args: list[str]):
    """The paper floor's prior on disk and the sequence of its trajectory 0."""
    folder = tmp_path_factory.mktemp("registration-cli")
    paper_floor.prior.save(folder / "prior")
    result = invoke("simulate", folder / "prior", "-o", folder / "seq", *SHORT, *cli_config_args)
    assert result.exit_code == 0, result.output
    return folder / "prior", folder / "seq"


def test_compare_registrars_on_a_recorded_sequence(prior_and_sequence, tmp_path: Path, cli_config_args) -> None:
    prior, sequence = prior_and_sequence
    out = tmp_path / "compare"
    tiny = ["registration.compare_keyframes=2", "registration.compare_perturbations=2"]
    result = invoke(
        "compare-registrars", prior, sequence, "-o", out, "-m", "planar", *[a for t in tiny for a in ("--set", t)],
        *cli_config_args,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "| planar |" in result.stdout
    records = json.loads((out / "records.json").read_text())
    assert len(records) == 2 * 2 and {r["registrar"] for r in records} == {"planar"}
    # The keyframes are frames of the recorded sequence.
    recorded = {int(line.split(",")[0]) for line in (sequence / "frames.csv").read_text().splitlines()[1:]}
    assert {r["frame_index"] for r in records} <= recorded
    (row,) = json.loads((out / "summary.json").read_text())
    assert row["runs"] == 4 and {"accepted_wrong", "accepted_without_probes_wrong", "accepted_coarse_wrong"} <= set(row)
    missing = invoke("compare-registrars", prior, tmp_path / "nowhere", "-o", out, *cli_config_args)
    assert missing.exit_code == 2 and "nowhere" in missing.stderr
