"""The localizer's variants on a simulated drive through the paper-floor building: smcl, smcl+graph, and refine."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import load_config
from bimfactor.evaluation.metrics import translation_errors_m
from bimfactor.pipeline import LocalizationRun, localize_sequence, refine_run
from bimfactor.sim.simulate import SimResult, simulate_sequence
from tests.sim import conftest as sim_fixtures
from tests.sim.conftest import Building

# The simulator tests' session fixtures: the paper-floor prior and the text embedder.
paper_floor = sim_fixtures.paper_floor
text_embedder = sim_fixtures.text_embedder

SEED = 3
REFINE_TOLERANCE_M = 0.05


@pytest.fixture(scope="module")
def drive(paper_floor: Building) -> SimResult:
    """Standard trajectory 0 of the paper floor, T = 50."""
    return simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 0, 0, progress=False)


@pytest.fixture(scope="module")
def runs(paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]) -> dict:
    """The drive localized by each online variant with one seed."""
    out = {}
    for variant in ("smcl", "smcl+graph"):
        cfg = load_config(None, [*config_overrides, f"localization.variant={variant}"])
        out[variant] = localize_sequence(
            paper_floor.prior, drive.meta, drive.frames, cfg, SEED, text_embedder=text_embedder, show_progress=False
        )
    return out


def test_the_graph_variant_leaves_the_filter_as_it_is(runs: dict[str, LocalizationRun]) -> None:
    smcl, graph = runs["smcl"], runs["smcl+graph"]
    assert (smcl.variant, graph.variant) == ("smcl", "smcl+graph")
    # The back end only reads the particles: the filter's estimate is the same bit for bit.
    for name in ("poses", "covariances", "storeys", "rooms"):
        np.testing.assert_array_equal(getattr(graph.filter, name), getattr(smcl.filter, name), err_msg=name)
    np.testing.assert_array_equal(graph.ess, smcl.ess)
    assert smcl.graph is None and smcl.output is smcl.filter and not smcl.final_modes
    assert all(not modes for modes in smcl.modes)
    assert graph.graph is not None and graph.output is graph.graph
    assert graph.odom_increments.shape == (len(graph.poses) - 1, 3)
    assert np.all(graph.graph.step_ms >= graph.filter.step_ms)


def test_the_graph_output_is_the_most_probable_mode(runs: dict[str, LocalizationRun]) -> None:
    run = runs["smcl+graph"]
    assert run.graph is not None
    with_modes = [i for i, modes in enumerate(run.modes) if modes]
    assert len(with_modes) > len(run.modes) // 2
    for i, modes in enumerate(run.modes):
        if not modes:  # no cluster heavy enough yet: the filter's estimate stands
            np.testing.assert_array_equal(run.poses[i], run.filter.poses[i])
            continue
        probabilities = [m.probability for m in modes]
        assert probabilities == sorted(probabilities, reverse=True)
        assert sum(probabilities) == pytest.approx(1.0)
        np.testing.assert_array_equal(run.poses[i], modes[0].pose)
        np.testing.assert_array_equal(run.covariances[i], modes[0].covariance)
        assert np.all(np.linalg.eigvalsh(run.covariances[i]) > 0)
    assert run.final_modes and run.final_modes[0].mode_id == run.modes[-1][0].mode_id


def test_refine_improves_or_matches_the_forward_pass(
    paper_floor: Building, runs: dict[str, LocalizationRun], config_overrides: list[str]
) -> None:
    run = runs["smcl+graph"]
    cfg = load_config(None, [*config_overrides, "localization.variant=smcl+graph"])
    refined = refine_run(run, paper_floor.prior, cfg)
    assert refined.modes and [m.mode_id for m in refined.modes] == [m.mode_id for m in run.final_modes]
    estimate = refined.estimate
    assert estimate.poses.shape == run.poses.shape and estimate.covariances.shape == run.covariances.shape
    np.testing.assert_array_equal(estimate.poses, refined.modes[0].poses)
    forward_m = translation_errors_m(run.poses, run.gt_poses).mean()
    refined_m = translation_errors_m(estimate.poses, run.gt_poses).mean()
    assert refined_m <= forward_m + REFINE_TOLERANCE_M
    assert all(m.batch.error_after <= m.batch.error_before for m in refined.modes)
    assert np.all(estimate.step_ms > run.graph.step_ms)


def test_refine_needs_a_graph_run(paper_floor: Building, runs: dict[str, LocalizationRun], test_config) -> None:
    with pytest.raises(ValueError, match="pose-graph variant"):
        refine_run(runs["smcl"], paper_floor.prior, test_config)
