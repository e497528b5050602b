"""Augmented MCL: random particles injected when the short-term likelihood average drops below the long-term one."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.recovery.augmented import AugmentedMCL
from tests.localization.handmade import observe


def augmented_of(mcl: SemanticMCL) -> AugmentedMCL:
    return next(r for r in mcl.recoveries.injections if isinstance(r, AugmentedMCL))


def test_augmented_mcl_injects_random_particles_when_the_short_average_drops(box_prior, box_visibility, smcl_cfg):
    cfg = updated(smcl_cfg, {"augmented.enabled": True, "augmented.injection": "uniform"})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=1000)
    mcl.initialize()
    recovery = augmented_of(mcl)
    recovery.w_slow, recovery.w_fast = 1.0, 0.2
    assert recovery.probability() == pytest.approx(0.8)
    resampled, injected = mcl.resample(FrameData())
    assert resampled and abs(injected - 800) < 60
    assert mcl.fresh.sum() == injected  # left out of the estimate until weighed
    paper = SemanticMCL(
        box_prior, box_visibility, updated(cfg, {"augmented.enabled": False}), np.random.default_rng(0), 1000
    )
    paper.initialize()
    assert not any(isinstance(r, AugmentedMCL) for r in paper.recoveries.injections)
    assert paper.resample(FrameData()) == (False, 0)


def test_the_averages_watch_the_mean_score_whatever_the_count_exponent(box_prior, box_visibility, smcl_cfg):
    both = observe(("chair", 1.0, 0.0), ("table", 2.0, 0.0))  # from the first particle: the chair scores 1, the table 0
    averages = []
    temperature = smcl_cfg.semantic.temperature
    for gamma in (1.0, 0.0):
        cfg = updated(smcl_cfg, {"augmented.enabled": True, "semantic.count_exponent": gamma, "scan.enabled": False})
        mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=2)
        mcl.initialize()
        mcl.particles = np.array([[4.0, 3.0, np.pi], [4.0, 3.0, 0.0]])
        mcl.storeys = np.zeros(2, np.int64)
        mcl.update(FrameData(both))
        averages.append(augmented_of(mcl).w_fast)
        ratio = np.exp(temperature**-1 * (0.5 if gamma == 1.0 else 1.0))  # exp(K^(1-γ) · mean / T), mean 0.5
        np.testing.assert_allclose(mcl.weights[0] / mcl.weights[1], ratio, rtol=1e-6)
    # Both started from equal weights: the average of the likelihoods of mean scores 0.5 and 0, on the mean's scale.
    expected = 0.5 * (np.exp(-0.5 / temperature) + np.exp(-1.0 / temperature))
    np.testing.assert_allclose(averages, expected)


def test_augmented_mcl_can_inject_poses_that_explain_the_observations(box_prior, box_visibility, smcl_cfg):
    cfg = updated(smcl_cfg, {"augmented.enabled": True, "augmented.injection": "observations"})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=1000)
    mcl.initialize()
    recovery = augmented_of(mcl)
    recovery.w_slow, recovery.w_fast = 1.0, 0.0
    obs = observe(("chair", 1.0, 0.0))
    resampled, injected = mcl.resample(FrameData(obs))
    assert resampled and injected == 1000
    assert mcl.models.semantic.scores(mcl.particles, mcl.storeys, obs).mean() > 0.5


def test_a_start_forgets_the_averages(box_prior, box_visibility, smcl_cfg):
    mcl = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=100)
    mcl.initialize()
    recovery = augmented_of(mcl)
    recovery.w_slow, recovery.w_fast = 1.0, 0.2
    mcl.initialize()
    assert recovery.w_slow is None and recovery.probability() == 0.0
