"""Twin evidence: a belief is told from its twin image only by what the twin motion does not carry."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.symmetry import Motion
from bimfactor.localization.measurements.base import FrameData
from bimfactor.localization.twins import SETTLED_NATS, TwinEvidence

HALF_TURN = Motion(np.pi, np.zeros(2), matched=10, total=10)  # (x, y) ↦ (−x, −y): the twin across the origin


def _evidence(log_likelihood) -> tuple[TwinEvidence, np.ndarray, np.ndarray, np.ndarray]:
    particles = np.array([[2.0, 1.0, 0.0], [2.1, 0.9, 0.1], [1.9, 1.1, -0.1]])
    storeys, weights = np.zeros(3, np.int64), np.full(3, 1 / 3)
    return TwinEvidence({0: HALF_TURN}, log_likelihood), particles, storeys, weights


def _belief_log_evidence(evidence: TwinEvidence, particles, storeys, weights) -> float:
    ll = evidence.log_likelihood(particles, storeys, FrameData())
    return float(np.log(np.sum(weights * np.exp(ll))))


def test_evidence_that_only_the_belief_explains_settles_it() -> None:
    # A plate at x > 0: frames seen from the belief's side are likelier there than at the twin image (x < 0).
    evidence, particles, storeys, weights = _evidence(lambda p, s, f: np.where(p[:, 0] > 0, 0.0, -2.0))
    assert not evidence.settled(0)
    evidence.observe(
        particles, storeys, weights, _belief_log_evidence(evidence, particles, storeys, weights), FrameData()
    )
    assert evidence.nats == pytest.approx(2.0) and not evidence.settled(0)
    evidence.observe(
        particles, storeys, weights, _belief_log_evidence(evidence, particles, storeys, weights), FrameData()
    )
    assert evidence.nats >= SETTLED_NATS and evidence.settled(0)
    evidence.reset()
    assert not evidence.settled(0) and evidence.settled(1)  # a storey without a twin needs no evidence


def test_evidence_the_twin_explains_as_well_never_settles() -> None:
    # Objects and walls: the same at a pose and at its image (a function of the distance from the origin only).
    evidence, particles, storeys, weights = _evidence(lambda p, s, f: -np.hypot(p[:, 0], p[:, 1]))
    for _ in range(20):
        log_evidence = _belief_log_evidence(evidence, particles, storeys, weights)
        evidence.observe(particles, storeys, weights, log_evidence, FrameData())
    assert abs(evidence.nats) < 1e-9 and not evidence.settled(0)
