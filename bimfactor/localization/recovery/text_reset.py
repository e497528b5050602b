"""Door-plate resets (sensor resetting, Lenser and Veloso 2000), beyond the paper: a reading the particles do not
explain redraws a share of them in front of the plates it names, kept from several times as many drawn by how well
they explain the frame's depth scan. Weighing alone cannot move a belief to a place it holds no particles at."""

from __future__ import annotations

import numpy as np

from bimfactor.config import TextResetConfig
from bimfactor.localization.measurements.base import FrameData, Update
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.particles import ParticleSampler, Poses
from bimfactor.localization.recovery.base import NO_POSES
from bimfactor.types import TextObservations


class TextReset:
    def __init__(self, cfg: TextResetConfig, plates: PlateLikelihood, sampler: ParticleSampler) -> None:
        self.cfg, self.plates, self.sampler = cfg, plates, sampler
        self.unexplained: list[int] = []  # the last update's readings the belief did not explain

    def reset(self) -> None:
        self.unexplained = []

    def after_update(self, update: Update, frame: FrameData) -> None:
        term = update.terms.get("text")
        self.unexplained = []
        if term is not None and frame.observations is not None:
            self.unexplained = self.unexplained_readings(term.evidence, update.weights, frame.observations.texts)

    def unexplained_readings(self, per_reading: np.ndarray, weights: np.ndarray, texts: TextObservations) -> list[int]:
        """The readings (indices) that name a plate and that the belief explains poorly: of the most that P(t | x)
        rises above ε for the reading's text (a particle right before its best-matching plate), the particles'
        weighted average holds less than `below`. A look-alike misread is judged as the text it reads."""
        plates, eps = self.plates, self.plates.cfg.unexplained
        explained = per_reading @ (weights / weights.sum())
        out = []
        for k, text in enumerate(texts.texts):
            if not len(plates.named_plates(text)):
                continue
            most = (1.0 - eps) * float(plates.text_match(text).max())
            if (explained[k] - eps) < self.cfg.below * most:
                out.append(k)
        return out

    def replacements(self, count: int, room: int) -> int:
        return min(round(self.cfg.share * count), room) if self.unexplained else 0

    def draw(self, n: int, frame: FrameData) -> Poses:
        if frame.observations is None or not self.unexplained:
            return NO_POSES
        drawn = self.sampler.from_texts(self.cfg.oversample * n, frame.observations, self.unexplained)
        return self.sampler.screen_by_scan(n, *drawn, frame)
