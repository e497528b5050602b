"""The challenger, beyond the paper: a second, small filter that a converged belief must keep out-predicting.

A belief that converged in the wrong one of two rooms of the same shape explains each frame almost as well as the
right one would: its scan fit stays at its usual level (the relocalization never fires) and augmented MCL's
averages settle there too. What tells the rooms apart is evidence summed over frames, against an alternative. The
challenger is that alternative: `particles` poses that explain the current frame's observations (each one
observation by one BIM object, `ParticleSampler.from_observations`; uniform over free space where those run short),
drawn from `oversample` times as many by the frame's scan, then run as a filter of its own on the same frames. From
the next frame on, each frame's log predictive likelihoods ln p(z | challenger) and ln p(z | belief) (one
measurement model for both, so their ratio is a Bayes factor) feed Page's CUSUM of their difference. When it
exceeds `threshold_nats` while the challenger's estimate lies elsewhere, the belief takes the challenger's
particles. A challenger that agrees with the belief (estimates within `agree_m` on one storey) for `agree_frames`
frames in a row, or has not won within `max_frames`, is drawn again at the next frame: the belief is checked
against fresh alternatives for as long as it is compact. The frame it is drawn from does not count (the draw was
chosen to fit it). Its draws come from a generator of its own, so the belief's draws are those it would make
without it.

The challenger also decides when a compact belief may be called converged (`confirms`): once a challenger agreed
with it, or ran `max_frames` while the belief predicted the frames at least as well in sum. Until then another
place may explain the frames as well, and the flag stays down: a belief that collapsed on a look-alike office is
compact but not converged. A belief that spreads again, or is handed over, must be confirmed anew.
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
