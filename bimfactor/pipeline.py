"""The localizer: runs the stages frame by frame (perception → online scene graph → semantic MCL).

`Localizer.step` reads like the method: perceive the frame and update the online graph at the odometry
pose, take the odometry increment since the last frame, predict, weigh the particles by the semantic and
spatial match of the nodes in view against the BIM, resample when the ESS is low, estimate.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from bimfactor.embed.text import TextEmbedder, make_text_embedder
from bimfactor.localization.motion import odometry_increment
from bimfactor.localization.smcl import SemanticMCL, StepResult
from bimfactor.perception.pipeline import make_perception
from bimfactor.progress import progress
from bimfactor.types import Frame, SequenceMeta

log = logging.getLogger(__name__)


@dataclass
class LocalizationRun:
    """What a localized sequence produced, one row per frame; `snapshots` maps step → (particles, weights)."""

    timestamps_s: np.ndarray
    poses: np.ndarray
    storeys: np.ndarray
    rooms: np.ndarray
    covariances: np.ndarray
    converged: np.ndarray
    ess: np.ndarray
    n_observations: np.ndarray
    filter_ms: np.ndarray
    perception_ms: np.ndarray
    gt_poses: np.ndarray | None = None
    gt_rooms: np.ndarray | None = None
    snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


class Localizer:
    """Coarse global localization of one sequence against one prior."""

    def __init__(
        self, prior: BimPrior, meta: SequenceMeta, cfg: Config, seed: int, text_embedder: TextEmbedder | None = None
    ) -> None:
        self.prior = prior
        self.cfg = cfg
        embedder = text_embedder or make_text_embedder(cfg.embed)
        self.perception = make_perception(cfg, meta, embedder, seed=seed)
        visibility = prior.visibility or VisibilityTable.build(prior, cfg.smcl)
        self.filter = SemanticMCL(prior, visibility, cfg.smcl, np.random.default_rng([seed, 0x5CC1]))
        self.filter.initialize()
        self._last_odom: np.ndarray | None = None

    def step(self, frame: Frame) -> tuple[StepResult, float]:
        """One frame: returns the filter's step and the perception time in ms."""
        started = time.perf_counter()
        seen = self.perception.step(frame)
        perception_ms = (time.perf_counter() - started) * 1000
        increment = None if self._last_odom is None else odometry_increment(self._last_odom, frame.odom_pose)
        self._last_odom = np.asarray(frame.odom_pose, float)
        return self.filter.step(increment, seen.observations), perception_ms


def localize_sequence(
    prior: BimPrior,
    meta: SequenceMeta,
    frames: Iterable[Frame],
    cfg: Config,
    seed: int,
    snapshot_steps: Iterable[int] = (),
    text_embedder: TextEmbedder | None = None,
    show_progress: bool = True,
) -> LocalizationRun:
    """Localize every frame of a sequence; ground truth, when the frames have it, is carried along."""
    localizer = Localizer(prior, meta, cfg, seed, text_embedder)
    frames = list(frames)
    snapshot_steps = set(snapshot_steps)
    rows: list[StepResult] = []
    perception_ms, snapshots = [], {}
    if 0 in snapshot_steps:
        snapshots[-1] = (localizer.filter.particles.copy(), localizer.filter.weights.copy())
    iterator = progress(frames, desc="localize", unit="frame") if show_progress else frames
    for i, frame in enumerate(iterator):
        result, ms = localizer.step(frame)
        rows.append(result)
        perception_ms.append(ms)
        if i in snapshot_steps:
            snapshots[i] = (localizer.filter.particles.copy(), localizer.filter.weights.copy())
    gt = [f.gt_pose for f in frames]
    has_gt = all(g is not None for g in gt)
    gt_poses = np.asarray(gt, float) if has_gt else None
    gt_storeys = [f.gt_storey or 0 for f in frames]
    gt_rooms = (
        np.asarray([prior.room_at(p[None, :2], s)[0] for p, s in zip(gt_poses, gt_storeys, strict=True)])
        if gt_poses is not None
        else None
    )
    return LocalizationRun(
        timestamps_s=np.asarray([f.timestamp_s for f in frames]),
        poses=np.asarray([r.pose for r in rows]),
        storeys=np.asarray([r.storey for r in rows]),
        rooms=np.asarray([r.room_id for r in rows]),
        covariances=np.asarray([r.covariance for r in rows]),
        converged=np.asarray([r.converged for r in rows]),
        ess=np.asarray([r.ess for r in rows]),
        n_observations=np.asarray([r.n_observations for r in rows]),
        filter_ms=np.asarray([sum(r.timings_ms.values()) for r in rows]),
        perception_ms=np.asarray(perception_ms),
        gt_poses=gt_poses,
        gt_rooms=gt_rooms,
        snapshots=snapshots,
    )
