"""Twin evidence: a belief is told from its twin image only by what the twin motion does not carry."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.symmetry import Motion
from bimfactor.localization.measurements.base import FrameData
from bimfactor.localization.twins import SETTLED_NATS, TwinEvidence

HALF_TURN = Motion(np.pi, np.zeros(2), matched=10, total=10)  # (x, y) ↦ (−x, −y): the twin across the origin
PARTICLES = np.array([[2.0, 1.0, 0.0], [2.1, 0.9, 0.1], [1.9, 1.1, -0.1]])
STOREYS, WEIGHTS = np.zeros(3, np.int64), np.full(3, 1 / 3)


def _frames(evidence: TwinEvidence, n: int, particles: np.ndarray = PARTICLES) -> None:
    for _ in range(n):
        own = evidence.log_likelihood(particles, STOREYS, FrameData())
        evidence.observe(particles, STOREYS, WEIGHTS, own, FrameData())


def test_evidence_that_only_the_belief_explains_settles_it() -> None:
    # A plate at x > 0: frames seen from the belief's side are likelier there than at the twin image (x < 0).
    evidence = TwinEvidence({0: HALF_TURN}, lambda p, s, f: np.where(p[:, 0] > 0, 0.0, -2.0))
    assert not evidence.settled(0)
    _frames(evidence, 1)
    assert evidence.nats == pytest.approx(2.0) and not evidence.settled(0)
    _frames(evidence, 1)
    assert evidence.nats >= SETTLED_NATS and evidence.settled(0)
    evidence.reset()
    assert not evidence.settled(0) and evidence.settled(1)  # a storey without a twin needs no evidence


def test_evidence_the_twin_explains_as_well_never_settles() -> None:
    # Objects and walls: the same at a pose and at its image (a function of the distance from the origin only).
    evidence = TwinEvidence({0: HALF_TURN}, lambda p, s, f: -np.hypot(p[:, 0], p[:, 1]))
    _frames(evidence, 20)
    assert abs(evidence.nats) < 1e-9 and not evidence.settled(0)


def test_a_twin_on_either_side_of_a_translation_is_a_rival() -> None:
    # Three bays 5 m apart along x, alike: a belief in the last bay has its twin behind it (T⁻¹), none ahead (T).
    bays = TwinEvidence(
        {0: Motion(0.0, np.array([5.0, 0.0]), 10, 10)}, lambda p, s, f: np.where(p[:, 0] < 12, 0.0, -9.0)
    )
    _frames(bays, 5, np.add(PARTICLES, [8.0, 0.0, 0.0]))  # x ≈ 10: the image ahead (x ≈ 15) is off the bays
    assert abs(bays.nats) < 1e-9 and not bays.settled(0)
    turn = Motion(0.3, np.array([1.0, 2.0]), 10, 10)
    np.testing.assert_allclose(turn.inverse().apply(turn.apply(PARTICLES)), PARTICLES, atol=1e-12)
