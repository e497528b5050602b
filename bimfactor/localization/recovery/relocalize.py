"""Relocalization, beyond the paper: the kidnapped robot. When the belief stops explaining the depth scans
(`LostMonitor`), the filter spreads its particles over the building again, as at the start, and weighs the frame
that showed it by the new cloud. A trickle of augmented MCL's random particles recovers from a kidnapping slowly."""

from __future__ import annotations

import numpy as np

from bimfactor.config import RelocalizeConfig
from bimfactor.localization.measurements.base import FrameData, Update


class LostMonitor:
    """Tells when a belief that was tracking stops explaining the depth scans: the kidnapped robot.

    Each frame's fit is the belief's predicted scan score, Σ w_i s_i in [0, 1] (`Update.scan_fit`): about
    0.55 while tracking (the prediction's spread and the depth noise keep it under 1), about 0.1 for a cloud
    spread over the building, 0.01–0.2 in the first frames after a kidnapping to an unlike place, and 0.3–0.45 for
    many frames after one to a place whose walls the old belief half explains. The monitor keeps a running average
    of the fit (rate `fit_alpha`) and is armed once that average covers 1 / `fit_alpha` frames and has
    reached `min_fit` (a belief still spread or just converged after a global start is never called lost).
    Armed, two tests say lost:
    - a sudden drop: `frames` consecutive frames below `fit_ratio` × the average. It must be quick:
      within two or three frames of a kidnapping the motion noise finds the old belief places nearby that fit the
      new scans locally;
    - a held one, Page's CUSUM of the fit's log-ratio to the average: S ← max(0, S + min(ln(average / fit), h) −
      `cusum_drift`), lost when S exceeds h = `cusum_threshold`. A fit held at half the average takes
      four frames; fits above e^−drift ≈ 0.67 of it never add up (a robot nosing up to furniture the map lacks
      dips to about half for a few frames).
    No single frame says lost (a passer-by filling the view). Frames that start or continue either test stay out
    of the average. Frames with fewer than `min_endpoints` scan endpoints (facing a wall at arm's length)
    leave it as it is.

    When it says lost, it also says since when: the frames of the excursion that led there, from the frame at which
    S (or the streak) last left zero. That is Page's estimate of the change point, where a kidnapped recording's
    continuous stretches part (`LocalizationRun.segments`).
    """

    def __init__(self, cfg: RelocalizeConfig) -> None:
        self.cfg = cfg
        self.average: float | None = None
        self.frames = 0  # frames in the average
        self.streak = 0  # consecutive frames below fit_ratio × the average
        self.cusum = 0.0
        self.excursion = 0  # frames, with a scan or not, since S or the streak last left zero (0: at zero)

    def reset(self) -> None:
        self.average, self.frames, self.streak, self.cusum, self.excursion = None, 0, 0, 0.0, 0

    def lost(self, fit: float | None, n_endpoints: int) -> int:
        """Feed one frame's fit (None: no scan). When the belief is lost, the number of frames (this one included)
        since it stopped explaining the scans, and the monitor starts over; otherwise 0."""
        cfg = self.cfg
        if self.excursion:
            self.excursion += 1
        if fit is None or n_endpoints < cfg.min_endpoints:
            return 0
        average = self.average
        if average is not None and average >= cfg.min_fit and self.frames * cfg.fit_alpha >= 1:
            self.streak = self.streak + 1 if fit < cfg.fit_ratio * average else 0
            surprise = min(float(np.log(average / max(fit, 1e-3))), cfg.cusum_threshold)
            self.cusum = max(0.0, self.cusum + surprise - cfg.cusum_drift)
            if self.streak or self.cusum > 0.0:
                self.excursion = self.excursion or 1
                if self.streak >= cfg.frames or self.cusum > cfg.cusum_threshold:
                    since = self.excursion
                    self.reset()
                    return since
                return 0
            self.excursion = 0
        self.frames += 1
        self.average = fit if average is None else average + cfg.fit_alpha * (fit - average)
        return 0


class Relocalize:
    """Says when the belief is lost: `lost` > 0 (the frames since it stopped explaining the scans)."""

    def __init__(self, cfg: RelocalizeConfig) -> None:
        self.monitor = LostMonitor(cfg)

    def reset(self) -> None:
        self.monitor.reset()

    def lost(self, update: Update, frame: FrameData) -> int:
        return self.monitor.lost(update.scan_fit, 0 if frame.scan is None else len(frame.scan))
