"""Resamplers: systematic (the paper's) and KLD-sampling, each with the count it keeps."""

from __future__ import annotations

import numpy as np

from bimfactor.config import SmclConfig, updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.resampling import (
    KldResampler,
    SystematicResampler,
    kld_particle_count,
    make_resampler,
    systematic_resample,
)


def test_systematic_resampling_counts_are_proportional_to_weights():
    weights = np.array([0.1, 0.2, 0.3, 0.4, 0.0])
    for seed in range(5):
        idx = systematic_resample(weights, 1000, np.random.default_rng(seed))
        counts = np.bincount(idx, minlength=5)
        assert np.all(np.abs(counts - 1000 * weights) <= 1)  # low variance: ⌊n·w⌋ or ⌈n·w⌉
    idx = systematic_resample(np.array([0.25, 0.25, 0.5]), 7, np.random.default_rng(0))
    assert np.all(np.diff(idx) >= 0) and len(idx) == 7


def test_kld_particle_count_matches_fox_2003():
    # k = 30 bins, ε = 0.05, z = 2.33: 29 / 0.1 · (1 − 2/261 + √(2/261) · 2.33)³
    a = 2.0 / (9.0 * 29)
    assert kld_particle_count(30, 0.05, 2.33) == int(np.ceil(290.0 * (1.0 - a + np.sqrt(a) * 2.33) ** 3))
    counts = kld_particle_count(np.array([1, 2, 10, 100, 1000]), 0.05, 2.33)
    assert counts[0] == 1 and np.all(np.diff(counts) > 0)  # more occupied bins need more particles
    assert kld_particle_count(100, 0.01, 2.33) > kld_particle_count(100, 0.05, 2.33)  # a tighter bound needs more


def test_the_factory_picks_the_configured_resampler_and_a_fixed_count_is_systematic(smcl_cfg: SmclConfig):
    kld = updated(smcl_cfg.resampler, {"kind": "kld"})
    assert isinstance(make_resampler(kld, 200, fixed=False), KldResampler)
    assert isinstance(make_resampler(kld, 200, fixed=True), SystematicResampler)
    assert isinstance(make_resampler(updated(kld, {"kind": "systematic"}), 200, fixed=False), SystematicResampler)
    assert make_resampler(kld, 200, fixed=False).initial_count(200) == kld.max_particles


def test_the_systematic_resampler_leaves_room_for_the_recoveries_redraws():
    weights = np.full(10, 0.1)
    rng = np.random.default_rng(0)
    keep = SystematicResampler().resample(weights, np.zeros((10, 3)), np.zeros(10, np.int64), 4, lambda n: 0, rng)
    assert len(keep) == 6 and len(set(keep.tolist())) == 6  # 4 of the 10 are the recoveries' to redraw


def test_kld_sampling_starts_wide_and_shrinks_to_m_on_a_converged_cloud(box_prior, box_visibility, smcl_cfg):
    cfg = updated(
        smcl_cfg,
        {"resampler.kind": "kld", "num_particles": 200, "resampler.max_particles": 3000, "augmented.enabled": False},
    )
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0))
    mcl.initialize()
    assert mcl.num_particles == len(mcl.particles) == len(mcl.weights) == 3000
    # A spread belief (the weight on a uniform quarter of the particles) occupies hundreds of bins: it keeps
    # more particles than M …
    mcl.weights = np.where(np.arange(3000) % 4 == 0, 1.0, 1e-9)
    mcl.weights /= mcl.weights.sum()
    assert mcl.resample(FrameData()) == (True, 0)
    spread = mcl.num_particles
    assert 200 < spread <= 3000 and len(mcl.particles) == len(mcl.weights) == spread
    np.testing.assert_allclose(mcl.weights, np.full(spread, 1.0 / spread))
    # … a belief on three particles (three bins) needs a handful: the count falls to M.
    mcl.weights = np.zeros(spread)
    mcl.weights[[0, 1, 2]] = 1.0 / 3
    assert mcl.resample(FrameData()) == (True, 0)
    assert mcl.num_particles == len(mcl.particles) == 200
    assert len({tuple(p) for p in mcl.particles}) <= 3
    # A count given to the constructor is fixed (benchmarks measure one M).
    fixed = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=500)
    fixed.initialize()
    assert fixed.num_particles == 500


def test_a_kld_resampler_asks_the_recoveries_again_for_its_new_count(smcl_cfg: SmclConfig):
    cfg = updated(smcl_cfg.resampler, {"kind": "kld", "max_particles": 2000})
    resampler = KldResampler(cfg, 100)
    weights = np.zeros(2000)
    weights[:3] = 1.0 / 3  # three particles, three bins: the count falls to M = 100
    poses = np.zeros((2000, 3))
    poses[:3, 0] = [0.0, 5.0, 10.0]
    asked = []

    def recount(count: int) -> int:
        asked.append(count)
        return count // 10

    keep = resampler.resample(weights, poses, np.zeros(2000, np.int64), 500, recount, np.random.default_rng(0))
    assert asked == [100] and len(keep) == 90  # 10 of the new 100 left for the recoveries
