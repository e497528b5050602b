"""The storeys scenario: routes through a lift, each run localized without and with the storey-change event."""

from __future__ import annotations

from pathlib import Path

import pytest

from bimfactor.bim.prior import build_prior
from bimfactor.bim.synth import write_building
from bimfactor.config import load_config
from bimfactor.evaluation.buildings import changes_storey
from bimfactor.evaluation.paper import _run_one, paper_report, reported_variants


@pytest.fixture(scope="module")
def lift_house_prior(tmp_path_factory: pytest.TempPathFactory, config_overrides: list[str]) -> Path:
    folder = tmp_path_factory.mktemp("lift-house")
    write_building("lift-house", 0, folder / "lift-house.ifc")
    cfg = load_config(None, config_overrides)
    build_prior(folder / "lift-house.ifc", cfg).save(folder / "prior", config_yaml=cfg.dump_yaml())
    return folder / "prior"


def test_the_storeys_scenario_scores_each_run_without_and_with_the_event(
    lift_house_prior: Path, config_overrides: list[str], paper_floor_prior: Path
) -> None:
    from bimfactor.bim.prior import BimPrior

    cfg = load_config(
        None,
        [*config_overrides, "evaluation.trajectory_length=24", "evaluation.warmup_max_steps=0",
         "evaluation.variants=[smcl]", "evaluation.scenario=storeys", "evaluation.score_from=start",
         "evaluation.num_trajectories=1", "evaluation.repeats=1"],
    )  # fmt: skip
    assert reported_variants(cfg.evaluation) == ["smcl", "smcl+event"]
    prior = BimPrior.load(lift_house_prior)
    assert changes_storey(prior, cfg) and not changes_storey(BimPrior.load(paper_floor_prior), cfg)
    results = _run_one(str(lift_house_prior), cfg.model_dump_json(), 0, 0, {})
    assert [r.variant for r in results] == ["smcl", "smcl+event"]
    for result in results:
        assert result.storey_hit_after_change is not None and len(result.storey_hit_after_change) == 10
    report = paper_report(lift_house_prior, prior, cfg, {}, results)
    assert 0.0 <= report["smcl+event"]["average"]["storey_acc_after_change"] <= 1.0
