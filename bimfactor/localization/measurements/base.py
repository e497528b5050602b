"""What every measurement model of the filter takes and gives: one frame's data in, one log-likelihood term out."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from bimfactor.types import Observations


@dataclass(frozen=True)
class FrameData:
    """What one keyframe gives the filter to weigh by: the scene graph's observations (with any door-plate text
    read) and the depth frame's (N, 2) base-frame scan endpoints; either may be None or empty. `storey_change`: the
    floors the robot went up (+) or down (−) since the last keyframe, when it was told (0: no word)."""

    observations: Observations | None = None
    scan: np.ndarray | None = None
    storey_change: int = 0

    @property
    def has_scan(self) -> bool:
        return self.scan is not None and len(self.scan) > 0


@dataclass(frozen=True)
class Term:
    """One measurement model's share of a frame's likelihood: (M,) log p(z | x_i), and the per-particle evidence
    the recoveries watch (semantic: the mean matched score over T; scan: the score in [0, 1]; text: (R, M)
    P(reading | x_i) per reading)."""

    log_likelihood: np.ndarray
    evidence: np.ndarray


class MeasurementModel(Protocol):
    """A factor of P(z | x): `weigh` scores every particle against its part of the frame."""

    name: str

    def weigh(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> Term | None:
        """The (M,) (x, y, yaw) particles on their (M,) storeys against the frame; None when the frame holds
        nothing this model weighs by."""
        ...


@dataclass(frozen=True)
class Update:
    """One measurement update of the whole belief: the weights before it, each model's term by name, and ln p(z |
    belief) = ln Σ_i w_i p(z | x_i), the frame's predictive likelihood (None when nothing weighed)."""

    weights: np.ndarray
    terms: dict[str, Term]
    log_evidence: float | None = None

    @property
    def scan_fit(self) -> float | None:
        """The belief's predicted scan score Σ w_i s_i (weights before the update); None without a scan term."""
        term = self.terms.get("scan")
        return None if term is None else float(np.dot(self.weights, term.evidence) / self.weights.sum())
