"""Where particles come from: poses drawn so that they explain an observation."""

from __future__ import annotations

import numpy as np

from bimfactor.config import updated
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.measurements.semantic import polar_coordinates
from tests.localization.handmade import object_id, observe


def test_poses_drawn_from_an_observation_explain_it(box_prior, box_visibility, smcl_cfg):
    # One chair seen 1.5 m ahead, 0.3 rad to the left: every drawn pose has the chair there (without motion noise),
    # stands on navigable space, and lists the chair as visible; the table cannot explain it.
    cfg = updated(smcl_cfg, {"motion.sigma_trans_m": 0.0, "motion.sigma_rot_deg": 0.0})
    sampler = SemanticMCL(box_prior, box_visibility, cfg, np.random.default_rng(1), num_particles=10).sampler
    poses, storeys = sampler.from_observations(300, observe(("chair", 1.5, 0.3)))
    assert len(poses) == 300 and (storeys == 0).all()
    chair = np.asarray(box_prior.objects[object_id(box_prior, "chair")].position_m[:2])
    d, alpha = polar_coordinates(poses, chair[None, :])
    np.testing.assert_allclose(d, 1.5, atol=1e-9)
    np.testing.assert_allclose(alpha, 0.3, atol=1e-9)
    assert sampler.free.contains(poses, storeys).all()
    assert len({round(float(a), 1) for a in np.arctan2(poses[:, 1] - chair[1], poses[:, 0] - chair[0])}) > 20
    unexplained = observe(("bookshelf", 20.0, 0.0))  # nowhere in the building is a bookshelf 20 m away
    assert len(sampler.from_observations(50, unexplained)[0]) == 0


def test_the_scan_screen_keeps_the_poses_the_scan_favours(box_prior, box_visibility, smcl_cfg):
    sampler = SemanticMCL(box_prior, box_visibility, smcl_cfg, np.random.default_rng(0), num_particles=10).sampler
    poses, storeys = sampler.uniform(400)
    endpoints = np.array([[1.0, 0.0], [1.0, 0.2], [1.0, -0.2]])  # a wall 1 m ahead
    kept, _ = sampler.screen_by_scan(40, poses, storeys, FrameData(scan=endpoints))
    scores = sampler.scan.scores(poses, storeys, endpoints)
    kept_scores = sampler.scan.scores(kept, np.zeros(len(kept), np.int64), endpoints)
    assert len(kept) == 40 and kept_scores.mean() > scores.mean() + 0.1
    unscreened, _ = sampler.screen_by_scan(40, poses, storeys, FrameData())  # no scan: the first n
    np.testing.assert_array_equal(unscreened, poses[:40])
