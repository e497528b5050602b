"""The offline refinement stage (`refine_run`): every candidate mode of a localized run smoothed as a whole, one
continuous stretch at a time, and the stretches' best fits joined into the estimate (docs/refine.md).

`_Refiner` settles the stretches (`join_false_alarms`, `search_seams`, `split_stretches`), refines each stretch's
candidates once (`refine_stretch`, `refined_modes`) and joins the best fits (`assemble_estimate`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Self

import numpy as np

from bimfactor.backend.factors import Landmarks
from bimfactor.backend.posegraph import AssociateFn, ModeHistory, PoseFactorFn, semantic_associator
from bimfactor.backend.refine import RefinedMode, refine_mode, track_from
from bimfactor.backend.scan_factor import CorrelativeMatcher
from bimfactor.bim.prior import BimPrior
from bimfactor.config import BackendConfig, Config
from bimfactor.localization.measurements import FrameData, MeasurementModel
from bimfactor.localization.measurements.scan import ScanLikelihood
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.pipeline import GRAPH_VARIANTS, LocalizationRun, Track, _stretches, scan_matcher, visibility_of
from bimfactor.progress import progress
from bimfactor.types import Observations

log = logging.getLogger(__name__)


@dataclass
class RefinedRun:
    """The offline pass over a localized run, one continuous stretch at a time (`segments`; `offline_seams` the first
    steps of those parted offline): every candidate mode refined, by stretch and best fit first, with its fit (`fits`:
    the filter's measurement log-likelihood along the refined trajectory); `best` per stretch (None: the forward
    estimate stands); the estimate, the best fits joined, whose `step_ms` adds the refinement's time shared over the
    steps."""

    forward: LocalizationRun
    modes: list[RefinedMode]
    estimate: Track
    refine_ms: float
    fits: list[float] = field(default_factory=list)
    segments: list[range] = field(default_factory=list)
    best: list[RefinedMode | None] = field(default_factory=list)
    offline_seams: list[int] = field(default_factory=list)

    @property
    def begins(self) -> list[str]:
        """How each stretch begins: at the `start`, where the filter `relocalized`, or where refine parted one
        `offline`."""
        kinds = {0: "start", **dict.fromkeys(self.offline_seams, "offline")}
        return [kinds.get(steps.start, "relocalized") for steps in self.segments]

    def best_at(self, step: int) -> RefinedMode | None:
        """The refined mode the estimate reports at `step` (None: the forward pass's estimate there)."""
        for steps, mode in zip(self.segments, self.best, strict=True):
            if step in steps:
                return mode
        return None


def refine_run(
    run: LocalizationRun,
    prior: BimPrior,
    cfg: Config,
    matcher: CorrelativeMatcher | None = None,
    show_progress: bool = False,
) -> RefinedRun:
    """Batch Levenberg–Marquardt smoothing of every candidate mode of the forward pass over its stretch.

    The run parts into stretches at the lost monitor's change points, settled by joining false alarms
    (`backend.refine_join`), searching the seams in hindsight (`backend.refine_seam_window`) and splitting
    kidnappings the filter missed (`backend.refine_split`, `_offline_split`); docs/refine.md. In each stretch the
    modes born in it (alive at the end, or pruned after `backend.refine_retired_min_keyframes` keyframes) are
    refined (`refine_mode`) and scored by the filter's measurement models over their refined trajectory, and the
    best fits join into the estimate. With `backend.scan_factor.enabled` the scans are matched anew by `matcher`; a
    full forward pass's accepted pose factors enter each mode's graph. ValueError for a run without pose graphs; a
    run without modes keeps the forward estimate.
    """
    if run.graph is None:
        raise ValueError(f"refinement needs a pose-graph variant ({', '.join(GRAPH_VARIANTS)}), not {run.variant}")
    candidates = [*run.final_modes, *run.retired_modes]
    if not candidates:
        log.warning("no mode formed in the forward pass: nothing to refine")
        return RefinedRun(run, [], run.graph, 0.0)
    started = time.perf_counter()
    refiner = _Refiner.start(run, prior, cfg, candidates, matcher, show_progress)
    segments = run.segments()
    limits: list[int | None] = [int(k) for k in np.flatnonzero(run.relocalized)]  # None: a seam parted offline
    # 1. join: the relocalizations the frames do not bear out.
    segments, limits = refiner.join_false_alarms(segments, limits)
    # 2. seam: each seam searched again in hindsight.
    segments = refiner.search_seams(segments, limits)
    # 3. split: the stretches two modes explain far better than one, parted offline until none parts.
    segments, limits = refiner.split_stretches(segments, limits)
    offline_seams = [steps.start for steps, limit in zip(segments[1:], limits, strict=True) if limit is None]
    # 4. refine each stretch: its candidates, best fit first.
    modes, fits, best = refiner.refined_modes(segments)
    refine_ms = (time.perf_counter() - started) * 1000
    # 5. join the best fits: the estimate.
    estimate = refiner.assemble_estimate(segments, best, refine_ms)
    log.info(
        "refined %d modes over %d stretch(es) in %.0f ms; best fits: %s",
        len(modes),
        len(segments),
        refine_ms,
        ", ".join("-" if m is None else f"mode {m.mode_id}" for m in best),
    )
    return RefinedRun(run, modes, estimate, refine_ms, fits, segments, best, offline_seams)


@dataclass
class _Refiner:
    """One refinement of a forward pass (`refine_run`): its inputs, the filter's measurement models and the back
    end's association and scan matching for every keyframe, and the stretches refined so far (`stretches`, by
    first and end step)."""

    run: LocalizationRun
    prior: BimPrior
    cfg: Config
    candidates: list[ModeHistory]
    associate_fns: list[AssociateFn]
    landmarks: Landmarks
    measure_fns: list[PoseFactorFn | None] | None
    models: list[MeasurementModel]
    show_progress: bool = False
    stretches: dict[tuple[int, int], tuple[list[RefinedMode], list[np.ndarray]]] = field(default_factory=dict)

    @classmethod
    def start(
        cls,
        run: LocalizationRun,
        prior: BimPrior,
        cfg: Config,
        candidates: list[ModeHistory],
        matcher: CorrelativeMatcher | None,
        show_progress: bool,
    ) -> Self:
        """The refinement of `candidates`, its models built (a scan matcher too, without `matcher`, where the back
        end matches scans)."""
        semantic = SemanticLikelihood(prior, visibility_of(prior, cfg), cfg.smcl.semantic)
        plates = PlateLikelihood(prior, cfg.smcl)
        associate_fns = [semantic_associator(semantic, plates, obs) for obs in run.observations]
        landmarks = Landmarks.from_prior(prior)
        has_scans = any(scan is not None for scan in run.scans)
        measure_fns: list[PoseFactorFn | None] | None = None
        if cfg.backend.scan_factor.enabled and has_scans:
            matcher = matcher or scan_matcher(prior, cfg)
            measure_fns = [None if scan is None else matcher.factor_fn(scan, recentre=0) for scan in run.scans]
        # The filter's measurement models; the scan term wherever the run has scans, as the matcher had them.
        models: list[MeasurementModel] = [
            semantic,
            plates,
            *([ScanLikelihood(prior, cfg.smcl.scan)] if has_scans else []),
        ]
        return cls(run, prior, cfg, candidates, associate_fns, landmarks, measure_fns, models, show_progress)

    def frame_fits(self, poses: np.ndarray, storey: int, steps: range) -> np.ndarray:
        """(len(steps),) the filter's measurement log-likelihood of the keyframes `steps` at `poses` on `storey`."""
        own = slice(steps.start, steps.stop)
        return _frame_fits(poses, storey, self.run.observations[own], self.run.scans[own], self.models)

    def refine_stretch(self, steps: range) -> tuple[list[RefinedMode], list[np.ndarray]]:
        """The candidates born in a stretch refined over it, best fit first, and their per-keyframe fits."""
        run, cfg = self.run, self.cfg
        key = (steps.start, steps.stop)
        if key not in self.stretches:
            own = slice(steps.start, steps.stop)
            born = [mode for mode in self.candidates if mode.first_index in steps]
            desc = f"refine steps {steps.start}–{steps.stop - 1}"
            refined = [
                refine_mode(
                    mode.within(steps),
                    run.odom_increments[steps.start : steps.stop - 1],
                    run.observations[own],
                    self.associate_fns[own],
                    self.landmarks,
                    cfg.backend,
                    cfg.odometry,
                    None if self.measure_fns is None else self.measure_fns[own],
                )
                for mode in (progress(born, desc=desc, unit="mode") if self.show_progress else born)
            ]
            refined = [
                dataclasses.replace(m, first_index=m.first_index + steps.start, start=steps.start) for m in refined
            ]
            fits = [self.frame_fits(m.poses, m.storey, steps) for m in refined]
            order = sorted(range(len(refined)), key=lambda k: -fits[k].sum())
            self.stretches[key] = [refined[k] for k in order], [fits[k] for k in order]
        return self.stretches[key]

    def join_false_alarms(
        self, segments: list[range], limits: list[int | None]
    ) -> tuple[list[range], list[int | None]]:
        """With `backend.refine_join`, the stretches with each relocalization the frames do not bear out joined: two
        neighbours whose modes, refined over both, give no offline split (`_offline_split`) are one stretch."""
        j = 1
        while self.cfg.backend.refine_join and j < len(segments):
            both = range(segments[j - 1].start, segments[j].stop)
            if _offline_split(both, *self.refine_stretch(both), self.cfg.backend) is None:
                log.info("the relocalization at step %d was a false alarm: steps %d–%d refined as one", limits[j - 1],
                         both.start, both.stop - 1)  # fmt: skip
                segments, limits = [*segments[: j - 1], both, *segments[j + 1 :]], [*limits[: j - 1], *limits[j:]]
            else:
                j += 1
        return segments, limits

    def search_seams(self, segments: list[range], limits: list[int | None]) -> list[range]:
        """The seams searched again in hindsight (`_hindsight_segments`), while one moves (each move gains
        likelihood; bounded)."""
        run, cfg = self.run, self.cfg
        for _ in range(len(run.timestamps_s)):
            if len(segments) < 2 or cfg.backend.refine_seam_window == 0:
                break
            best_fits = [(self.refine_stretch(steps)[0] or [None])[0] for steps in segments]
            moved = _hindsight_segments(
                segments, limits, best_fits, run, self.measure_fns, self.frame_fits, cfg.backend
            )
            if moved == segments:
                break
            log.info("seams moved in hindsight: %s → %s", [s.start for s in segments[1:]], [s.start for s in moved[1:]])
            segments = moved
        return segments

    def split_stretches(self, segments: list[range], limits: list[int | None]) -> tuple[list[range], list[int | None]]:
        """With `backend.refine_split`, the stretches parted offline where `_offline_split` parts them, the seams
        searched again after each round, until none parts (every split adds a seam: it ends); a seam parted offline
        has no limit (None)."""
        while self.cfg.backend.refine_split:
            parted = [_offline_split(steps, *self.refine_stretch(steps), self.cfg.backend) for steps in segments]
            parted = [seam for seam in parted if seam is not None]
            if not parted:
                break
            log.info("stretches parted offline at %s", parted)
            seams = [(steps.start, limit) for steps, limit in zip(segments[1:], limits, strict=True)]
            seams = sorted([*seams, *((seam, None) for seam in parted)])
            limits = [limit for _, limit in seams]
            segments = _stretches([0, *(seam for seam, _ in seams)], len(self.run.timestamps_s))
            segments = self.search_seams(segments, limits)
        return segments, limits

    def refined_modes(self, segments: list[range]) -> tuple[list[RefinedMode], list[float], list[RefinedMode | None]]:
        """Every stretch's candidates refined over it, by stretch (`segment`) and best fit first within one; their
        fits, summed over the keyframes; and each stretch's best fit (None: no mode was born there)."""
        by_stretch = [
            [dataclasses.replace(m, segment=index) for m in self.refine_stretch(steps)[0]]
            for index, steps in enumerate(segments)
        ]
        modes = [m for stretch in by_stretch for m in stretch]
        fits = [float(f.sum()) for steps in segments for f in self.refine_stretch(steps)[1]]
        best = [stretch[0] if stretch else None for stretch in by_stretch]
        return modes, fits, best

    def assemble_estimate(self, segments: list[range], best: list[RefinedMode | None], refine_ms: float) -> Track:
        """The stretches' best fits joined (a stretch without one keeps the forward pass's estimate), each step's
        time the forward pass's plus the refinement's `refine_ms` shared over the steps."""
        run = self.run
        parts = [
            run.graph.window(slice(steps.start, steps.stop))
            if mode is None
            else Track(
                poses=mode.poses,
                covariances=mode.covariances,
                storeys=np.full(len(steps), mode.storey),
                rooms=self.prior.room_at(mode.poses[:, :2], mode.storey),
                step_ms=np.zeros(len(steps)),
            )
            for steps, mode in zip(segments, best, strict=True)
        ]
        T = len(run.timestamps_s)
        return Track(
            poses=np.concatenate([p.poses for p in parts]),
            covariances=np.concatenate([p.covariances for p in parts]),
            storeys=np.concatenate([p.storeys for p in parts]),
            rooms=np.concatenate([p.rooms for p in parts]),
            step_ms=run.graph.step_ms + refine_ms / T,
        )


def _offline_split(steps: range, refined: list[RefinedMode], fits: list[np.ndarray], cfg: BackendConfig) -> int | None:
    """Where a stretch parts again in hindsight (None: nowhere): the step s at which one refined candidate born before s
    explaining the keyframes before it, and another born at s or later explaining those from it, gain the most
    measurement log-likelihood over the stretch's best fit, within the `cfg.refine_split_*` bounds (docs/refine.md).
    """
    if len(refined) < 2:
        return None
    n, shortest = len(steps), cfg.refine_split_min_keyframes
    cum = np.array([np.concatenate([[0.0], np.cumsum(f)]) for f in fits])  # cum[k, s]: keyframes 0 … s − 1
    best_gain, best_seam = -np.inf, None
    for a, earlier in enumerate(refined):
        for b, later in enumerate(refined):
            lo, hi = max(shortest, earlier.first_index - steps.start + 1), later.first_index - steps.start
            s = np.arange(lo, min(n - shortest, hi) + 1)
            if a == b or not len(s):
                continue
            ahead_before = (cum[a, s] - cum[b, s]) / s  # a's advantage per keyframe before s
            ahead_after = ((cum[b, -1] - cum[b, s]) - (cum[a, -1] - cum[a, s])) / (n - s)  # b's, from s on
            gain = cum[a, s] + cum[b, -1] - cum[b, s] - cum[0, -1]
            gain[np.minimum(ahead_before, ahead_after) < cfg.refine_split_min_keyframe_log_ratio] = -np.inf
            k = int(np.argmax(gain))
            if gain[k] > best_gain:
                best_gain, best_seam = float(gain[k]), steps.start + int(s[k])
    if best_gain < cfg.refine_split_min_log_ratio:
        return None
    log.debug("stretch %d…%d parted at %d: %.1f nats", steps.start, steps.stop - 1, best_seam, best_gain)
    return best_seam


def _hindsight_segments(
    segments: list[range],
    limits: list[int | None],
    best: list[RefinedMode | None],
    run: LocalizationRun,
    measure_fns: Sequence[PoseFactorFn | None] | None,
    frame_fits: Callable[[np.ndarray, int, range], np.ndarray],
    cfg: BackendConfig,
) -> list[range]:
    """The run's stretches with each seam between two stretches that have a best fit (`best`, refined over
    `segments`) searched again (`_hindsight_seam`): within `cfg.refine_seam_window` keyframes of it, after the
    previous seam (as searched: seams move in order) and the start of the earlier fit's stretch, before the next
    seam, and not after its limit (`limits`, one per seam: the step at which the filter relocalized; None: a seam
    parted offline)."""
    T = len(run.timestamps_s)
    seams = [steps.start for steps in segments]
    for j in range(1, len(segments)):
        before, after = best[j - 1], best[j]
        if before is not None and after is not None:
            lo = max(seams[j - 1] + 1, segments[j - 1].start + 1, seams[j] - cfg.refine_seam_window)
            hi = min(seams[j + 1] - 1 if j + 1 < len(seams) else T - 1, seams[j] + cfg.refine_seam_window)
            hi = hi if limits[j - 1] is None else min(hi, limits[j - 1])
            score = _hindsight_seam(seams[j], lo, hi, before, after, run, measure_fns, frame_fits)
            best_seam = lo + int(np.argmax(score))
            if score[best_seam - lo] - score[seams[j] - lo] >= cfg.refine_seam_min_log_ratio:
                seams[j] = best_seam
    return _stretches(seams, T)


def _hindsight_seam(
    seam: int,
    lo: int,
    hi: int,
    before: RefinedMode,
    after: RefinedMode,
    run: LocalizationRun,
    measure_fns: Sequence[PoseFactorFn | None] | None,
    frame_fits: Callable[[np.ndarray, int, range], np.ndarray],
) -> np.ndarray:
    """Where, in hindsight, the stretch ending with `before`'s trajectory gives way to the one starting with
    `after`'s (their seam now at `seam`): for each step s in lo … hi, the measurement log-likelihood of keyframes
    lo … s − 1 along `before` and s … hi along `after`, each trajectory carried across the present seam by odometry
    and scan matching (`track_from`). Its maximum is the change point by likelihood, with the frames themselves."""
    scans = [None] * len(run.timestamps_s) if measure_fns is None else list(measure_fns)
    odom = run.odom_increments
    ahead = track_from(before.poses[-1], odom[seam - 1 : hi], scans[seam : hi + 1], before.storey, backwards=False)
    behind = track_from(after.poses[0], odom[lo:seam], scans[lo:seam], after.storey, backwards=True)
    first = np.concatenate([before.poses[lo - before.start :], ahead])
    second = np.concatenate([behind, after.poses[: hi + 1 - seam]])
    steps = range(lo, hi + 1)
    on_first = np.concatenate([[0.0], np.cumsum(frame_fits(first, before.storey, steps))])
    on_second = np.concatenate([[0.0], np.cumsum(frame_fits(second, after.storey, steps))])
    score = on_first + (on_second[-1] - on_second)  # score[s − lo]: lo … s − 1 on the first, s … hi on the second
    return score[: hi - lo + 1]  # s ≤ hi: the later stretch keeps a keyframe of the window


def _frame_fits(
    poses: np.ndarray,
    storey: int,
    observations: Sequence[Observations],
    scans: Sequence[np.ndarray | None],
    models: Sequence[MeasurementModel],
) -> np.ndarray:
    """(T,) log P(z_t | x_t) of the filter's measurement models (semantic, door-plate and scan terms) at (T, 3)
    poses on one storey, with the T keyframes' observations and scans."""
    storeys = np.array([storey])
    fits = np.zeros(len(poses))
    for t, pose in enumerate(poses):
        frame = FrameData(observations[t], scans[t])
        for model in models:
            term = model.weigh(pose[None], storeys, frame)
            if term is not None:
                fits[t] += float(term.log_likelihood[0])
    return fits
