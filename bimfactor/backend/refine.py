"""Offline refinement: each surviving mode's whole trajectory smoothed by batch Levenberg–Marquardt.

Per mode of the forward pass: an initial guess from its ISAM2 poses, tracked backwards before its birth and forwards
after its pruning (by inverse odometry, corrected by scan matches where there are scans); matches and scan factors
at that guess; `batch_refine` over all keyframes; up to `refine_rounds` rounds of re-association at the refined
poses; with scan factors, the map's own error (`scan_factor.min_sigma_m`) added to each marginal. docs/refine.md.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bimfactor.backend.factors import Landmarks
from bimfactor.backend.posegraph import (
    AssociateFn,
    BatchResult,
    ModeHistory,
    PoseFactor,
    PoseFactorFn,
    batch_refine,
)
from bimfactor.config import BackendConfig, OdometryConfig
from bimfactor.types import Observations, se2_compose, se2_inverse

log = logging.getLogger(__name__)


@dataclass
class RefinedMode:
    """One mode's refined trajectory: the batch result, its matches per keyframe, the forward-pass probability.
    The trajectory covers keyframes `start` … `start` + T − 1 (the stretch `segment` of a run the filter
    relocalized; otherwise the whole run, from 0); the mode was born at keyframe `first_index`."""

    mode_id: int
    storey: int
    probability: float
    first_index: int
    batch: BatchResult
    associations: list[list[tuple[int, int]]]
    rounds: int
    start: int = 0
    segment: int = 0

    @property
    def poses(self) -> np.ndarray:
        return self.batch.poses

    @property
    def covariances(self) -> np.ndarray:
        return self.batch.covariances


def refine_mode(
    mode: ModeHistory,
    odom_increments: np.ndarray,
    observations: Sequence[Observations],
    associate_fns: Sequence[AssociateFn],
    landmarks: Landmarks | np.ndarray,
    cfg: BackendConfig,
    odometry: OdometryConfig,
    measure_fns: Sequence[PoseFactorFn | None] | None = None,
) -> RefinedMode:
    """Smooth one mode over all T keyframes (see the module docstring).

    `odom_increments` (T−1, 3) robot-frame odometry between keyframes; `observations` and `associate_fns` one per
    keyframe (an associator maps a pose and storey to (observation index, object id) pairs for that keyframe's
    observations); `landmarks` the BIM objects by id (`factors.Landmarks`; an (N, 2) array: points); `odometry` the
    odometry noise that weighs the odometry factors; `cfg.refine_rounds` bounds the re-association; `measure_fns`,
    one per keyframe (None: no scan), match the keyframe's scan from a pose.
    """
    T = len(observations)
    i0, n = mode.first_index, len(mode.poses)
    i1 = i0 + n  # the first keyframe after the mode's
    if len(associate_fns) != T or len(odom_increments) != T - 1 or n < 1 or i1 > T:
        raise ValueError(f"mode {mode.mode_id}: keyframes {i0}…{i1 - 1} do not lie in a {T}-keyframe sequence")
    if measure_fns is not None and len(measure_fns) != T:
        raise ValueError(f"mode {mode.mode_id}: {len(measure_fns)} scan matchers for {T} keyframes")
    scans = [None] * T if measure_fns is None else list(measure_fns)
    before = track_from(mode.poses[0], odom_increments[:i0], scans[:i0], mode.storey, backwards=True)
    after = track_from(mode.poses[-1], odom_increments[i1 - 1 :], scans[i1:], mode.storey, backwards=False)
    initial = np.concatenate([before, mode.poses, after])
    own = range(i0, i1)
    associations = [
        list(mode.associations[t - i0]) if t in own else list(associate_fns[t](initial[t], mode.storey))
        for t in range(T)
    ]

    def scan_factors(poses: np.ndarray) -> list[PoseFactor]:
        if measure_fns is None:
            return list(mode.scan_factors)
        measured = [(t, fn(poses[t], mode.storey)) for t, fn in enumerate(measure_fns) if fn is not None]
        return [(t, *m) for t, m in measured if m is not None]

    def optimise(start: np.ndarray, matches: list[list[tuple[int, int]]]) -> tuple[BatchResult, bool]:
        """The batch result, and whether scan factors entered it."""
        scanned = scan_factors(start)
        batch = batch_refine(
            mode.prior_pose,
            mode.prior_covariance,
            odom_increments,
            observations,
            matches,
            landmarks,
            cfg,
            odometry,
            initial_poses=start,
            pose_factors=[*mode.pose_factors, *scanned],
            prior_index=i0,
        )
        return batch, bool(scanned)

    batch, scanned = optimise(initial, associations)
    done = 0
    for _ in range(cfg.refine_rounds):
        again = [list(associate_fns[t](batch.poses[t], mode.storey)) for t in range(T)]
        if measure_fns is None and [set(a) for a in again] == [set(a) for a in associations]:
            break  # with scans, the round still re-matches them from the refined poses
        associations, done = again, done + 1
        batch, scanned = optimise(batch.poses, associations)
    if scanned:
        map_error = np.diag([cfg.scan_factor.min_sigma_m**2, cfg.scan_factor.min_sigma_m**2, 0.0])
        batch = dataclasses.replace(batch, covariances=batch.covariances + map_error)
    log.debug(
        "mode %d refined: error %.1f → %.1f in %d iterations, %d re-association rounds",
        mode.mode_id,
        batch.error_before,
        batch.error_after,
        batch.iterations,
        done,
    )
    return RefinedMode(mode.mode_id, mode.storey, mode.probability, i0, batch, associations, done)


def track_from(
    anchor: np.ndarray,
    increments: np.ndarray,
    measure_fns: Sequence[PoseFactorFn | None],
    storey: int,
    backwards: bool,
) -> np.ndarray:
    """(n, 3) poses of the n keyframes before (after) an anchor pose, each predicted from its neighbour nearer the
    anchor by the odometry increment between them (inverted going backwards), then replaced by its scan's match
    from that prediction when one is accepted (`measure_fns[t]`; None or a rejection keeps the prediction).
    `increments[t]` leads from keyframe t to t + 1 of the (n + 1) keyframes counted from the first one before
    (from the anchor, after)."""
    n = len(measure_fns)
    poses = np.empty((n, 3))
    near = np.asarray(anchor, np.float64)
    for t in range(n - 1, -1, -1) if backwards else range(n):
        step = se2_inverse(increments[t]) if backwards else increments[t]
        predicted = se2_compose(near, step)
        measured = None if measure_fns[t] is None else measure_fns[t](predicted, storey)
        poses[t] = near = predicted if measured is None else np.asarray(measured[0], np.float64)
    return poses
