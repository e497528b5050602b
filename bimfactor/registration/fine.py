"""The coarse-to-fine stage: refine one mode's pose against the BIM walls, gate it, and hand the back end a factor.

Per keyframe the scan is built once (`FineRegistration.scan`, stitching `registration.submap_keyframes` − 1 recent
keyframes by odometry) and registered from a mode's pose (`register_scan`), gated (fit, correction size, degeneracy,
consistency with the mode's covariance, ambiguity probes) and returned with a body-frame information matrix for a
PriorFactorPose2. Bad sensor data gives a result that is not accepted, with the reason, never an exception. ICP's
JᵀJ/σ² is about 40 times too confident in σ, so the factor's covariance is ICP's plus a floor (`factor_min_sigma_m`,
`factor_min_sigma_deg`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimfactor.backend.factors import covariance_world_to_body
from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config, RegistrationConfig, SensorConfig
from bimfactor.errors import InputError
from bimfactor.localization.measurements.scan import DepthPoints
from bimfactor.registration.gate import GateDecision, gate_with_probes
from bimfactor.registration.icp import Registrar, RegistrationResult, make_registrar
from bimfactor.registration.scan import MIN_SCAN_POINTS, frame_scan, stitch_submap
from bimfactor.registration.surface import SurfaceModel, build_surface_models
from bimfactor.types import Frame, SequenceMeta

log = logging.getLogger(__name__)

# Surface models kept in memory, per (IFC file, sampling settings, seed): a run needs one, a benchmark a few.
_SURFACE_CACHE_SIZE = 4
_surface_cache: dict[tuple, list[SurfaceModel]] = {}


@dataclass
class FineResult:
    """The fine stage's answer for one mode at one keyframe.

    `pose` (3,) is the registered T_world_base (x, y, yaw; the start pose when no registration ran);
    `information_body` (3, 3) is its information in GTSAM's body frame at `pose`, for
    `MultiHypothesisBackend.add_pose_factor` (zeros when no registration ran); use both only when `accepted`.
    `reasons` says why not. `registration` and `gate` hold the details (None when no registration ran);
    `time_ms` covers registration and gate.
    """

    accepted: bool
    reasons: list[str]
    pose: np.ndarray
    information_body: np.ndarray
    start_pose: np.ndarray
    storey: int
    scan_points: int
    time_ms: float
    registration: RegistrationResult | None = None
    gate: GateDecision | None = None

    @property
    def reason(self) -> str:
        """The reasons in one line ("" when accepted)."""
        return "; ".join(self.reasons)


def factor_information(information_world: np.ndarray, yaw: float, cfg: RegistrationConfig) -> np.ndarray:
    """(3, 3) body-frame information of a fine factor from ICP's (3, 3) world-frame JᵀJ/σ² at heading `yaw`.

    The covariance is ICP's plus the floor F = diag(σ_m², σ_m², σ_yaw²); written as F⁻¹ − F⁻¹(H + F⁻¹)⁻¹F⁻¹, the
    inverse of (H⁻¹ + F) stays defined when H is singular (a corridor's free axis gets no information).
    """
    H = np.asarray(information_world, dtype=np.float64)
    floor_inv = np.diag(
        1.0 / np.array([cfg.factor_min_sigma_m, cfg.factor_min_sigma_m, np.deg2rad(cfg.factor_min_sigma_deg)]) ** 2
    )
    info = floor_inv - floor_inv @ np.linalg.solve(H + floor_inv, floor_inv)
    info = 0.5 * (info + info.T)
    # Information rotates like covariance under the orthogonal world → body map of the Pose2 tangent.
    return covariance_world_to_body(info, yaw)


def surface_models_for(prior: BimPrior, cfg: Config) -> list[SurfaceModel]:
    """The storeys' surface models of `prior`'s building (list index = storey index), sampled from the prior's wall
    meshes once per building and seed, and cached."""
    if prior.walls is None:
        raise InputError("the prior holds no wall meshes; rebuild it with `bimfactor prior`")
    key = (prior.source_sha256, cfg.registration.surface_density_per_m2, cfg.seed)
    if key not in _surface_cache:
        t0 = time.perf_counter()
        surfaces = build_surface_models(prior.walls, cfg.registration, cfg.seed)
        log.info("surface models of %s sampled in %.2f s", Path(prior.source_file).name, time.perf_counter() - t0)
        while len(_surface_cache) >= _SURFACE_CACHE_SIZE:
            _surface_cache.pop(next(iter(_surface_cache)))
        _surface_cache[key] = surfaces
    return _surface_cache[key]


class FineRegistration:
    """The fine stage over one building: its storeys' surface models, the configured registrar, and the gate; the
    scans keep the `sensor`'s band of depth (`frame_scan`)."""

    def __init__(
        self,
        surfaces: list[SurfaceModel],
        cfg: RegistrationConfig,
        sensor: SensorConfig,
        registrar: Registrar | None = None,
    ) -> None:
        self.surfaces = surfaces
        self.cfg = cfg
        self.sensor = sensor
        self.registrar = registrar if registrar is not None else make_registrar(cfg)
        self._scans: dict[tuple[int, float], np.ndarray] = {}

    @classmethod
    def for_prior(cls, prior: BimPrior, cfg: Config) -> FineRegistration:
        """The fine stage of `prior`'s building with `cfg.registration` and `cfg.sensor` (surface models from the
        cache)."""
        return cls(surface_models_for(prior, cfg), cfg.registration, cfg.sensor)

    def scan(
        self,
        frame: Frame,
        meta: SequenceMeta,
        recent: Sequence[Frame] = (),
        recent_poses: np.ndarray | None = None,
        points: DepthPoints | None = None,
    ) -> np.ndarray:
        """(N, 3) registration scan of `frame` in its base frame; (0, 3) when the depth has no usable return.

        With `submap_keyframes` = K > 1, the last K − 1 frames of `recent` (oldest first) are stitched in;
        `recent_poses` ((len(recent) + 1, 3), the frame's own last) places them, default their `odom_pose`.
        `points`: the frame's returns, when the keyframe has them already.
        """
        k = self.cfg.submap_keyframes - 1
        used = list(recent)[-k:] if k > 0 else []
        if not used:
            return self._frame_scan(frame, meta, points)
        if recent_poses is None:
            poses = np.stack([f.odom_pose for f in [*used, frame]])
        else:
            poses = np.asarray(recent_poses, dtype=np.float64).reshape(-1, 3)[-(len(used) + 1) :]
        scans = [*(self._frame_scan(f, meta) for f in used), self._frame_scan(frame, meta, points)]
        nonempty = [i for i, s in enumerate(scans) if len(s)]
        if not nonempty:
            return np.zeros((0, 3))
        return stitch_submap([scans[i] for i in nonempty], poses[nonempty], self.cfg.scan_voxel_m)

    def _frame_scan(self, frame: Frame, meta: SequenceMeta, points: DepthPoints | None = None) -> np.ndarray:
        """One frame's scan, kept for the next `submap_keyframes` calls (a submap re-uses its frames)."""
        key = (frame.index, frame.timestamp_s)
        if key not in self._scans:
            depth = np.asarray(frame.depth_m)
            usable = depth.ndim == 2 and depth.size > 0
            scan = frame_scan(frame, meta, self.cfg, self.sensor, points=points) if usable else np.zeros((0, 3))
            self._scans[key] = scan
            while len(self._scans) > self.cfg.submap_keyframes:
                self._scans.pop(next(iter(self._scans)))
        return self._scans[key]

    def register_scan(
        self,
        scan_base: np.ndarray,
        pose: np.ndarray,
        storey: int = 0,
        covariance_world: np.ndarray | None = None,
    ) -> FineResult:
        """Register an (N, 3) base-frame scan from the mode's (3,) world pose on `storey`, and gate it.

        `covariance_world` (3, 3), the mode's world-frame covariance, adds the consistency test and rules out
        ambiguity alternatives the mode excludes.
        """
        t0 = time.perf_counter()
        start = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        scan_base = np.asarray(scan_base, dtype=np.float64).reshape(-1, 3)

        def rejected(reason: str) -> FineResult:
            log.debug("fine registration not run: %s", reason)
            ms = (time.perf_counter() - t0) * 1000
            return FineResult(False, [reason], start, np.zeros((3, 3)), start, storey, len(scan_base), ms)

        if not 0 <= storey < len(self.surfaces):
            return rejected(f"no surface model for storey {storey} (the building has {len(self.surfaces)})")
        if not np.all(np.isfinite(start)):
            return rejected("the start pose is not finite")
        scan_base = scan_base[np.all(np.isfinite(scan_base), axis=1)]
        if len(scan_base) < MIN_SCAN_POINTS:
            return rejected(f"scan has {len(scan_base)} points (< {MIN_SCAN_POINTS})")
        surface = self.surfaces[storey]
        result = self.registrar.register(scan_base, surface, start)
        decision = gate_with_probes(scan_base, surface, result, start, self.cfg, covariance_world)
        information = factor_information(result.information, float(result.pose[2]), self.cfg)
        if not decision.accepted:
            log.debug("fine registration rejected: %s", "; ".join(decision.reasons))
        return FineResult(
            accepted=decision.accepted,
            reasons=list(decision.reasons),
            pose=result.pose.copy(),
            information_body=information,
            start_pose=start,
            storey=storey,
            scan_points=len(scan_base),
            time_ms=(time.perf_counter() - t0) * 1000,
            registration=result,
            gate=decision,
        )

    def register(
        self,
        frame: Frame,
        meta: SequenceMeta,
        pose: np.ndarray,
        storey: int = 0,
        covariance_world: np.ndarray | None = None,
        recent: Sequence[Frame] = (),
        recent_poses: np.ndarray | None = None,
    ) -> FineResult:
        """`scan` then `register_scan`: the fine stage for one (3,) pose of one frame."""
        return self.register_scan(self.scan(frame, meta, recent, recent_poses), pose, storey, covariance_world)
