"""Augmented MCL (Thrun et al., Probabilistic Robotics, Table 8.3), beyond the paper: random particles are injected
with probability max(0, 1 − w_fast / w_slow), the ratio of a short-term to a long-term average of the measurement
likelihood, to recover from a wrong convergence. The averages watch the semantic term alone: a wrong place of the
same shape fits the depth scan as well as the right one."""

from __future__ import annotations

import numpy as np

from bimfactor.config import AugmentedConfig
from bimfactor.localization.measurements.base import FrameData, Update
from bimfactor.localization.particles import ParticleSampler, Poses
from bimfactor.localization.recovery.base import NO_POSES


class AugmentedMCL:
    def __init__(self, cfg: AugmentedConfig, temperature: float, sampler: ParticleSampler) -> None:
        self.cfg, self.temperature, self.sampler = cfg, temperature, sampler
        self.w_slow: float | None = None
        self.w_fast: float | None = None

    def reset(self) -> None:
        self.w_slow = self.w_fast = None

    def after_update(self, update: Update, frame: FrameData) -> None:
        """Average likelihood, on an absolute scale (a perfect match = 1), of the mean matched score, whatever the
        number of observations; into the slow and the fast average."""
        term = update.terms.get("semantic")
        if term is None:
            return
        w_avg = float(np.dot(update.weights, np.exp(term.evidence - 1.0 / self.temperature)))
        rate_slow, rate_fast = self.cfg.alpha_slow, self.cfg.alpha_fast
        self.w_slow = w_avg if self.w_slow is None else self.w_slow + rate_slow * (w_avg - self.w_slow)
        self.w_fast = w_avg if self.w_fast is None else self.w_fast + rate_fast * (w_avg - self.w_fast)

    def probability(self) -> float:
        """max(0, 1 − w_fast / w_slow); 0 before the first update."""
        if not self.w_slow or self.w_fast is None:
            return 0.0
        return max(0.0, 1.0 - self.w_fast / self.w_slow)

    def replacements(self, count: int, room: int) -> int:
        return min(int(self.sampler.rng.binomial(count, self.probability())), room)

    def draw(self, n: int, frame: FrameData) -> Poses:
        """Poses that explain one of the frame's observations (`injection: observations`); none for `uniform`
        (the filter draws those over free space)."""
        if self.cfg.injection == "observations" and frame.observations is not None:
            return self.sampler.from_observations(n, frame.observations)
        return NO_POSES
