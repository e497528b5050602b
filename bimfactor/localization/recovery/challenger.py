"""The challenger, beyond the paper: a second, small filter that a converged belief must keep out-predicting.

Drawn from poses that explain the current frame's observations, it runs on the same frames as the belief; Page's
CUSUM of the two filters' log predictive likelihoods (a Bayes factor) hands its particles to the belief when it
passes `threshold_nats` while its estimate lies elsewhere. It also decides when a compact belief may be called
converged (`confirms`). Why and how: docs/filter.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from bimfactor.config import ChallengerConfig
from bimfactor.localization.measurements.base import FrameData
from bimfactor.localization.recovery.base import NO_POSES, WeightedSet

if TYPE_CHECKING:
    from bimfactor.localization.filter import PoseEstimate, SemanticMCL


class Challenger:
    def __init__(self, cfg: ChallengerConfig, rival: SemanticMCL) -> None:
        self.cfg, self.rival = cfg, rival  # `rival`: a filter of `particles` without relocalization or challenger
        self.running = False
        self.frames = 0  # frames followed since it was drawn
        self.agreeing = 0  # consecutive frames its estimate agreed with the belief's
        self.cusum = 0.0
        self.total = 0.0  # Σ ln p(z | challenger) − ln p(z | belief) since it was drawn
        self.confirmed = False  # a challenger looked for a look-alike of the compact belief and found none

    def reset(self) -> None:
        """Draw a new challenger at the next compact frame (the belief was spread or handed over)."""
        self.running = False
        self.confirmed = False

    def confirms(self) -> bool:
        return self.confirmed

    def start(self, frame: FrameData) -> None:
        """Draw the challenger from this frame: poses that explain its observations, screened by its scan."""
        sampler, n = self.rival.sampler, self.cfg.particles
        drawn = self.cfg.oversample * n
        poses, storeys = NO_POSES
        if frame.observations is not None:
            poses, storeys = sampler.from_observations(drawn, frame.observations)
        if len(poses) < drawn:
            more, more_storeys = sampler.uniform(drawn - len(poses))
            poses, storeys = np.concatenate([poses, more]), np.concatenate([storeys, more_storeys])
        self.rival.set_particles(*sampler.screen_by_scan(n, poses, storeys, frame))
        self.running, self.frames, self.agreeing, self.cusum, self.total = True, 0, 0, 0.0, 0.0

    def challenge(
        self, odom_increment: np.ndarray | None, frame: FrameData, estimate: PoseEstimate, log_evidence: float | None
    ) -> WeightedSet | None:
        """One frame, after the belief's step gave `estimate` with `log_evidence` ln p(z | belief): the
        challenger's particle set when the belief should take it over, else None."""
        cfg, rival = self.cfg, self.rival
        if not estimate.compact:
            self.confirmed = False
        if not self.running:
            has_data = (frame.observations is not None and len(frame.observations) > 0) or frame.has_scan
            if estimate.compact and has_data:
                self.start(frame)
            return None
        if odom_increment is not None:
            rival.predict(odom_increment, frame.storey_change)
        theirs = rival.update(frame).log_evidence
        rival.resample(frame)
        self.frames += 1
        if log_evidence is not None and theirs is not None:
            self.cusum = max(0.0, self.cusum + theirs - log_evidence)
            self.total += theirs - log_evidence
        guess = rival.estimate()
        apart = float(np.hypot(*(guess.pose[:2] - estimate.pose[:2])))
        agree = guess.storey == estimate.storey and apart <= cfg.agree_m
        self.agreeing = self.agreeing + 1 if agree else 0
        if self.cusum > cfg.threshold_nats and not agree:
            self.running = False
            return rival.particles, rival.storeys, rival.weights
        if self.agreeing >= cfg.agree_frames or self.frames >= cfg.max_frames:
            self.running = False
            # It found the belief's place, or none that predicts the frames better in sum: no look-alike.
            self.confirmed = estimate.compact and (self.agreeing >= cfg.agree_frames or self.total <= 0.0)
        return None
