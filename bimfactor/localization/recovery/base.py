"""The three roles a recovery of the filter plays, and when the filter asks each (`filter.SemanticMCL.step`):

- an `Injection` watches each update (`after_update`) and redraws particles at a resampling (`replacements`, `draw`);
- a `LostDetection` says after the update that the belief must be spread over the building again (`lost` > 0);
- a `Verification` may hand over a particle set the belief should take (`challenge`) and decides whether a compact
  estimate may be reported converged (`confirms`).

Each starts over (`reset`) when the particles are set anew. `Recoveries` holds the ones the configuration enables.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from bimfactor.localization.measurements.base import FrameData, Update
from bimfactor.localization.particles import Poses

if TYPE_CHECKING:
    from bimfactor.localization.filter import PoseEstimate

WeightedSet = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(N, 3) poses, (N,) storeys and (N,) normalised weights of a particle set."""

NO_POSES: Poses = (np.zeros((0, 3)), np.zeros(0, np.int64))


class Injection(Protocol):
    def reset(self) -> None: ...

    def after_update(self, update: Update, frame: FrameData) -> None: ...

    def replacements(self, count: int, room: int) -> int: ...

    def draw(self, n: int, frame: FrameData) -> Poses: ...


class LostDetection(Protocol):
    def reset(self) -> None: ...

    def lost(self, update: Update, frame: FrameData) -> int: ...


class Verification(Protocol):
    def reset(self) -> None: ...

    def challenge(
        self, odom_increment: np.ndarray | None, frame: FrameData, estimate: PoseEstimate, log_evidence: float | None
    ) -> WeightedSet | None: ...

    def confirms(self) -> bool: ...


@dataclass
class Recoveries:
    """The filter's recoveries by role. `injections` in the order of their redraws at a resampling."""

    injections: list[Injection]
    lost_detection: LostDetection | None = None
    verification: Verification | None = None

    def reset(self) -> None:
        for recovery in (*self.injections, self.lost_detection, self.verification):
            if recovery is not None:
                recovery.reset()

    def after_update(self, update: Update, frame: FrameData) -> None:
        for injection in self.injections:
            injection.after_update(update, frame)

    def lost(self, update: Update, frame: FrameData) -> int:
        """The frames since the belief stopped explaining the data (0: it still does, or nothing watches)."""
        return 0 if self.lost_detection is None else self.lost_detection.lost(update, frame)

    def challenge(
        self, odom_increment: np.ndarray | None, frame: FrameData, estimate: PoseEstimate, log_evidence: float | None
    ) -> WeightedSet | None:
        if self.verification is None:
            return None
        return self.verification.challenge(odom_increment, frame, estimate, log_evidence)

    def confirms(self) -> bool:
        return self.verification is None or self.verification.confirms()
