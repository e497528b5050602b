"""The scan term of the measurement model: the depth frame's horizontal scan against the BIM's likelihood field.

Beyond the paper. The depth image, cut to the grid's obstacle band, becomes a 2-D scan (the nearest return per
`scan.beam_deg` bin, `scan_endpoints`); each endpoint placed by a particle's pose scores exp(−d² / 2σ²), d its
distance to the nearest BIM obstacle (the likelihood field, Probabilistic Robotics Table 6.3), and the particle's
score is the mean over endpoints, so clutter costs a bounded amount: log P(z_scan|x) = score / `smcl.scan.temperature`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimfactor.bim.field import LikelihoodField
from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config, ScanConfig, ScanTermConfig, SensorConfig
from bimfactor.localization.measurements.base import FrameData, Term
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta


@dataclass(frozen=True)
class DepthPoints:
    """A depth image's returns in the robot's base frame, back-projected once a keyframe: the scan term's endpoints
    and the registrar's scan are both cut from them. `base` (N, 3) metres; `depth_m` (N,) each return's depth along
    the camera's z axis (OpenCV), which the sensor's range limits."""

    base: np.ndarray
    depth_m: np.ndarray

    @classmethod
    def of(cls, depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_base_camera: np.ndarray) -> DepthPoints:
        """The returns of an (H, W) depth image (NaN or ≤ 0: no return), in pixel order."""
        depth = np.asarray(depth_m, dtype=np.float64)
        v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
        z = depth[v, u]
        return cls(intrinsics.backproject(u, v, z) @ T_base_camera[:3, :3].T + T_base_camera[:3, 3], z)

    @classmethod
    def of_frame(cls, frame: Frame, meta: SequenceMeta) -> DepthPoints:
        return cls.of(frame.depth_m, meta.intrinsics, meta.T_base_camera)

    def within(self, max_range_m: float = np.inf) -> np.ndarray:
        """(M, 3) base-frame points whose depth is at most `max_range_m`."""
        return self.base if max_range_m == np.inf else self.base[self.depth_m <= max_range_m]


def height_band(points: np.ndarray, min_z_m: float, max_z_m: float) -> np.ndarray:
    """The (N, 3) base-frame points whose height above the floor lies in [min_z_m, max_z_m]."""
    keep = (points[:, 2] >= min_z_m) & (points[:, 2] <= max_z_m)
    return points[keep]


def scan_endpoints(
    points: DepthPoints,
    cfg: ScanConfig,
    sensor: SensorConfig,
    max_z_m: float,
) -> np.ndarray:
    """(N, 2) base-frame x, y of one endpoint per `beam_deg` bearing bin: the nearest surface's median return.

    Returns between `sensor.min_z_m` and `max_z_m` above the floor and within `sensor.max_range_m` count (NaN: none). A
    bin's surface is its returns within `surface_sigmas` σ(r) of the nearest one (clamped to `surface_min_m` …
    `surface_m`): the nearest return alone is biased short by about 3σ of the depth noise.
    """
    points = height_band(points.base, sensor.min_z_m, max_z_m)
    ranges = np.hypot(points[:, 0], points[:, 1])
    keep = ranges <= sensor.max_range_m
    points, ranges = points[keep], ranges[keep]
    if len(points) == 0:
        return np.zeros((0, 2))
    bins = np.floor(np.arctan2(points[:, 1], points[:, 0]) / np.deg2rad(cfg.beam_deg)).astype(np.int64)
    order = np.lexsort((ranges, bins))  # by bin, then nearest first
    bins, ranges = bins[order], ranges[order]
    _, first, counts = np.unique(bins, return_index=True, return_counts=True)
    # Sorted by range within each bin, the nearest surface is a prefix of the bin's run; its median is halfway.
    group = np.repeat(np.arange(len(first)), counts)
    nearest = ranges[first]
    surface = np.clip(cfg.surface_sigmas * sensor.depth_noise.sigma_m(nearest), cfg.surface_min_m, cfg.surface_m)
    on_surface = ranges <= (nearest + surface)[group]
    surface_counts = np.bincount(group, weights=on_surface, minlength=len(first)).astype(np.int64)
    return points[order[first + surface_counts // 2], :2]


def frame_endpoints(points: DepthPoints, cfg: Config) -> np.ndarray:
    """`scan_endpoints` of one frame's returns, up to the top of the configured obstacle band."""
    return scan_endpoints(points, cfg.scan, cfg.sensor, cfg.bim.grid.band_max_m)


class ScanLikelihood:
    """Scores particles' poses by how well a base-frame scan lands on the prior's obstacles."""

    name = "scan"

    def __init__(self, prior: BimPrior, cfg: ScanTermConfig) -> None:
        self.cfg = cfg
        self.field = LikelihoodField(prior, cfg.sigma_m)

    def scores(self, particles: np.ndarray, storeys: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
        """(M,) mean over the (N, 2) endpoints of exp(−d² / 2σ²) at each particle's pose; 0 for an empty scan.

        An endpoint off the grid scores 0.
        """
        values = self.field.values(particles, storeys, endpoints)
        if values.shape[1] == 0:
            return np.zeros(len(values))
        return values.mean(axis=1, dtype=np.float64) / 255.0

    def log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
        """(M,) log P(z_scan|x) = score / `temperature`."""
        return self.scores(particles, storeys, endpoints) / self.cfg.temperature

    def weigh(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> Term | None:
        """The frame's scan term, with each particle's score in [0, 1] as evidence (the belief's predicted fit,
        which the relocalization watches); None without a scan."""
        if not frame.has_scan:
            return None
        scores = self.scores(particles, storeys, frame.scan)
        return Term(scores / self.cfg.temperature, scores)
