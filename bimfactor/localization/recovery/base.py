"""What every recovery of the filter may do, and when the filter asks it (`filter.SemanticMCL.step`):

- `after_update`: after each measurement update, watch the update (augmented MCL's likelihood averages, the door
  plates the belief does not explain);
- `lost`: once a step, after the update: > 0 when the belief must be spread over the building again (the frames
  since it stopped explaining the data);
- `replacements` and `draw`: at a resampling, how many particles to redraw instead of resampling them, and the poses
  to redraw them at (fewer: the rest are drawn uniformly);
- `challenge`: after the estimate, a weighted particle set the belief should take over instead (or None);
- `confirms`: whether the recovery lets a compact estimate be reported converged (the challenger: only once it
  looked for a look-alike place and found none that explains the frames as well);
- `reset`: the particles were set anew (a start, a relocalization, a set taken over).

`RecoveryBase` does nothing at each; a recovery overrides the hooks it needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from bimfactor.localization.measurements.base import FrameData, Update
from bimfactor.localization.particles import Poses

if TYPE_CHECKING:
    from bimfactor.localization.filter import PoseEstimate

WeightedSet = tuple[np.ndarray, np.ndarray, np.ndarray]
"""(N, 3) poses, (N,) storeys and (N,) normalised weights of a particle set."""

NO_POSES: Poses = (np.zeros((0, 3)), np.zeros(0, np.int64))


class Recovery(Protocol):
    def reset(self) -> None: ...

    def after_update(self, update: Update, frame: FrameData) -> None: ...

    def lost(self, update: Update, frame: FrameData) -> int: ...

    def replacements(self, count: int, room: int) -> int: ...

    def draw(self, n: int, frame: FrameData) -> Poses: ...

    def challenge(
        self, odom_increment: np.ndarray | None, frame: FrameData, estimate: PoseEstimate, log_evidence: float | None
    ) -> WeightedSet | None: ...

    def confirms(self) -> bool: ...


class RecoveryBase:
    """A recovery that does nothing at any hook; subclasses override the ones they need."""

    def reset(self) -> None:
        return None

    def after_update(self, update: Update, frame: FrameData) -> None:
        return None

    def lost(self, update: Update, frame: FrameData) -> int:
        return 0

    def replacements(self, count: int, room: int) -> int:
        return 0

    def draw(self, n: int, frame: FrameData) -> Poses:
        return NO_POSES

    def challenge(
        self, odom_increment: np.ndarray | None, frame: FrameData, estimate: PoseEstimate, log_evidence: float | None
    ) -> WeightedSet | None:
        return None

    def confirms(self) -> bool:
        return True
