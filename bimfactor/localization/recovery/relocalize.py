"""Relocalization, beyond the paper: the kidnapped robot. When the belief stops explaining the depth scans
(`LostMonitor`), the filter spreads its particles over the building again, as at the start, and weighs the frame
that showed it by the new cloud. A trickle of augmented MCL's random particles recovers from a kidnapping slowly."""

from __future__ import annotations

import numpy as np

from bimfactor.config import RelocalizeConfig
from bimfactor.localization.measurements.base import FrameData, Update


class LostMonitor:
    """Tells when a belief that was tracking stops explaining the depth scans: the kidnapped robot.

    Each frame's fit is the belief's predicted scan score Σ w_i s_i in [0, 1] (`Update.scan_fit`). Armed once its
    running average (rate `fit_alpha`) covers 1 / `fit_alpha` frames and has reached `min_fit`, it says lost on a sudden
    drop (`frames` consecutive frames below `fit_ratio` × the average) or a held one (Page's CUSUM of ln(average / fit),
    less `cusum_drift`, above `cusum_threshold`); frames in either test stay out of the average, and frames with fewer
    than `min_endpoints` endpoints leave it as it is. It also says since when: Page's change point, where the run's
    stretches part (`LocalizationRun.segments`). Measurements behind the numbers: docs/filter.md, "Relocalization".
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
