"""The scan term of the measurement model: the depth frame's horizontal scan against the BIM's likelihood field.

Beyond the paper, whose measurement model is semantic only. The depth image is cut to the obstacle band of the
occupancy grid and turned into a 2-D scan like a laser's: per bearing bin of `scan_beam_deg`, the nearest return
(`scan_endpoints`). A particle's scan score is the likelihood-field model (Thrun et al., Probabilistic Robotics,
Table 6.3) with the prior's clearance layer as the field: each endpoint, placed in the world by the particle's
pose, scores exp(−d² / 2σ²) with d its distance to the nearest BIM obstacle (walls and furniture), and the
particle's score is the mean over the endpoints, in [0, 1]. The mean, not the product, keeps clutter and moved
furniture (endpoints far from any BIM obstacle) at a bounded cost and puts the term on the semantic score's
scale: log P(z_scan|x) = score / `scan_temperature`.

Walls constrain yaw and position wherever the robot looks, also when no object is in view; the semantic term
tells places of the same shape apart.
"""

from __future__ import annotations

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config, SmclConfig
from bimfactor.registration.scan import backproject_depth, height_band
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta


def scan_endpoints(
    depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_base_camera: np.ndarray, cfg: SmclConfig, max_z_m: float
) -> np.ndarray:
    """(N, 2) base-frame x, y of the nearest return per bearing bin among the depth points in the scan band.

    Points are kept between `scan_min_z_m` and `max_z_m` (the top of the grid's obstacle band) above the floor
    and within `scan_max_range_m` (horizontal); bins are `scan_beam_deg` wide. NaN depth is no return.
    """
    points = backproject_depth(depth_m, intrinsics, T_base_camera)
    points = height_band(points, cfg.scan_min_z_m, max_z_m)
    ranges = np.hypot(points[:, 0], points[:, 1])
    keep = ranges <= cfg.scan_max_range_m
    points, ranges = points[keep], ranges[keep]
    if len(points) == 0:
        return np.zeros((0, 2))
    bins = np.floor(np.arctan2(points[:, 1], points[:, 0]) / np.deg2rad(cfg.scan_beam_deg)).astype(np.int64)
    order = np.lexsort((ranges, bins))  # by bin, then nearest first
    _, first = np.unique(bins[order], return_index=True)
    return points[order[first], :2]


def frame_endpoints(frame: Frame, meta: SequenceMeta, cfg: Config) -> np.ndarray:
    """`scan_endpoints` of one frame's depth image, up to the top of the configured obstacle band."""
    return scan_endpoints(frame.depth_m, meta.intrinsics, meta.T_base_camera, cfg.smcl, cfg.bim.grid.band_max_m)


class ScanLikelihood:
    """Scores particles' poses by how well a base-frame scan lands on the prior's obstacles."""

    def __init__(self, prior: BimPrior, cfg: SmclConfig) -> None:
        self.grid = prior.grid
        self.cfg = cfg
        # The field itself, exp(−d² / 2σ²) per cell of every storey in 1/255 steps (a quarter of float32's memory:
        # the lookups are random, so cache misses are their cost), flattened, with one 0 appended for "off grid".
        clearance = np.stack([layers.clearance_m for layers in prior.storeys]).astype(np.float32)
        field = np.rint(255.0 * np.exp(-0.5 * (clearance / cfg.scan_sigma_m) ** 2)).astype(np.uint8)
        self._field = np.append(field.ravel(), np.uint8(0))

    def scores(self, particles: np.ndarray, storeys: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
        """(M,) mean over the (N, 2) endpoints of exp(−d² / 2σ²) at each particle's pose; 0 for an empty scan.

        An endpoint off the grid scores 0.
        """
        particles = np.asarray(particles, np.float64).reshape(-1, 3)
        endpoints = np.asarray(endpoints, np.float64).reshape(-1, 2)
        M, N = len(particles), len(endpoints)
        if N == 0:
            return np.zeros(M)
        grid = self.grid
        # Endpoints in grid units relative to the grid origin, for every particle: (M, N) column and row.
        c = np.cos(particles[:, 2])[:, None] / grid.resolution_m
        s = np.sin(particles[:, 2])[:, None] / grid.resolution_m
        x0 = ((particles[:, 0] - grid.origin_x) / grid.resolution_m)[:, None]
        y0 = ((particles[:, 1] - grid.origin_y) / grid.resolution_m)[:, None]
        col = np.floor(x0 + c * endpoints[None, :, 0] - s * endpoints[None, :, 1]).astype(np.int64)
        row = np.floor(y0 + s * endpoints[None, :, 0] + c * endpoints[None, :, 1]).astype(np.int64)
        inside = (row >= 0) & (row < grid.rows) & (col >= 0) & (col < grid.cols)
        flat = (np.asarray(storeys, np.int64)[:, None] * grid.rows + row) * grid.cols + col
        flat = np.where(inside, flat, len(self._field) - 1)
        return self._field[flat].mean(axis=1, dtype=np.float64) / 255.0

    def log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
        """(M,) log P(z_scan|x) = score / `scan_temperature`."""
        return self.scores(particles, storeys, endpoints) / self.cfg.scan_temperature
