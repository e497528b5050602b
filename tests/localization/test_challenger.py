"""The challenger: a second, small filter that a converged belief must keep out-predicting."""

from __future__ import annotations

import numpy as np

from bimfactor.config import updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.recovery.challenger import Challenger
from tests.localization.handmade import observe


def test_the_challenger_draws_from_its_own_generator(box_prior, box_visibility, smcl_cfg):
    # The belief's own draws are those it makes without a challenger: runs stay comparable until a hand-over.
    poses = []
    for enabled in (False, True):
        cfg = updated(
            smcl_cfg, {"challenger.enabled": enabled, "motion.sigma_trans_m": 0.0, "motion.sigma_rot_deg": 0.0}
        )
        mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(3), num_particles=300)
        mcl.initialize_around(np.array([4.0, 3.0, np.pi]), 0, 0.2, 0.1)
        for _ in range(6):
            result = mcl.step(np.array([0.0, 0.0, 0.0]), observe(("chair", 1.0, 0.0)))
        assert result.converged and not result.challenged
        challengers = [r for r in [mcl.recoveries.verification] if isinstance(r, Challenger)]
        assert bool(challengers) == enabled
        if enabled:  # it ran: drawn at a converged frame, with a filter of its own size and no challenger of its own
            rival = challengers[0].rival
            assert rival._initialized and rival.num_particles == cfg.challenger.particles
            assert rival.recoveries.verification is None and rival.recoveries.lost_detection is None
        poses.append(mcl.particles.copy())
    np.testing.assert_array_equal(*poses)


def test_a_belief_in_the_wrong_room_is_handed_to_a_challenger_that_explains_the_frames(
    box_prior, box_visibility, smcl_cfg, fixed_value
):
    # The belief sits at (8, 3) facing west, where the frames (a chair 1 m ahead) are not explained; the challenger,
    # drawn from the observation, finds the chair's place and out-predicts it until the belief moves there.
    fixed_value("smcl.challenger.threshold_nats", 5.0)
    cfg = updated(smcl_cfg, {"relocalize.enabled": False, "augmented.enabled": False})
    mcl = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(0), num_particles=300)
    mcl.initialize_around(np.array([8.0, 3.0, np.pi]), 0, 0.05, 0.02)
    challenged = []
    for _ in range(12):
        challenged.append(mcl.step(np.zeros(3), observe(("chair", 1.0, 0.0))).challenged)
    assert any(challenged)
    chair = np.array([3.0, 3.0])
    assert np.hypot(*(mcl.estimate().pose[:2] - chair)) < 1.5
