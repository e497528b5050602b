"""Correlative scan matching of the 2-D scan against the BIM's faces: a pose factor with a wide basin.

After Olson, "Real-time correlative scan matching" (ICRA 2009): an exhaustive search over a window of poses around a
mode's predicted pose, scored by

    log P(z | x) = (min(N, N_eff) / N) · Σ_n log(f_n(x) + ε),    f_n = exp(−d_n² / 2σ²),

with d_n the distance of endpoint n to the nearest face (`face_distances`), ε (`outlier`) bounding what an endpoint
on clutter costs, and N_eff (`effective_endpoints`) the most endpoints that count as independent. An endpoint whose
ray was inside a wall `clear_before_m` before it scores as an outlier (a sensor cannot see a wall's far face).

1. Coarse: the whole window (± `window_m`, ± `window_deg`) in `step_m` / `step_deg` steps, in a smoother field
   (σ = `coarse_sigma_m`) so that no peak falls between the steps;
2. fine: around each of the `candidates` best coarse poses, ± one coarse step in `fine_step_m` / `fine_step_deg`;
3. the mean of exp(log P) over the fine cells, its covariance the Laplace approximation at the peak, or the coarse
   distribution's over the whole window where the peak is too flat (a corridor); floors `min_sigma_m`, `min_sigma_deg`.

An optimum on the window's edge is searched again about that edge pose, up to `recentre` times. A match is rejected,
with the reason, for fewer than `min_endpoints` endpoints, fewer than `min_inliers` on the BIM's faces, or an optimum
still on the edge after the last search. How the pose graphs use it: docs/pose-graphs.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bimfactor.backend.factors import covariance_world_to_body
from bimfactor.bim.field import LikelihoodField, face_distances
from bimfactor.bim.prior import BimPrior
from bimfactor.config import ScanFactorConfig
from bimfactor.types import wrap_angle

LAPLACE_DEPTH = 8.0  # the quadratic is fitted to the fine cells within this much log-likelihood of the peak


@dataclass
class ScanMatch:
    """A correlative match: (3,) mean pose and (3, 3) world-frame covariance of the matched distribution, how many
    endpoints lie on a wall at the best pose, and whether it is accepted (the reason when not)."""

    pose: np.ndarray
    covariance: np.ndarray
    inliers: int
    accepted: bool
    reason: str = ""

    @property
    def information_body(self) -> np.ndarray:
        """(3, 3) information in GTSAM's body frame at the matched pose (for a PriorFactorPose2)."""
        return np.linalg.inv(covariance_world_to_body(self.covariance, float(self.pose[2])))


def _axis(half_width: float, step: float) -> np.ndarray:
    """Offsets −half_width … +half_width in `step`s, always including 0 (an odd count)."""
    n = int(np.floor(half_width / step + 1e-9))
    return step * np.arange(-n, n + 1, dtype=np.float64)


class _SearchGrid:
    """The poses of a search window as offsets: (T, 2) x, y and (Y,) yaw; `offsets` (Y·T, 3) in the order of
    `LikelihoodField.grid_values` (yaw outer, x, y inner)."""

    def __init__(self, half_m: float, step_m: float, half_rad: float, step_rad: float) -> None:
        xy = _axis(half_m, step_m)
        self.dxy = np.stack(np.meshgrid(xy, xy, indexing="ij"), axis=-1).reshape(-1, 2)
        self.dyaw = _axis(half_rad, step_rad)
        self.offsets = np.column_stack([np.tile(self.dxy, (len(self.dyaw), 1)), np.repeat(self.dyaw, len(self.dxy))])


def _moments(poses: np.ndarray, log_p: np.ndarray, about: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the distribution ∝ exp(log_p) over (K, 3) poses; yaw taken relative to `about`."""
    p = np.exp(log_p - log_p.max())
    p /= p.sum()
    delta = poses - about
    delta[:, 2] = wrap_angle(delta[:, 2])
    mean = p @ delta
    centred = delta - mean
    covariance = (centred * p[:, None]).T @ centred
    pose = about + mean
    pose[2] = wrap_angle(pose[2])
    return pose, covariance


def _laplace_covariance(poses: np.ndarray, log_p: np.ndarray, about: np.ndarray, depth: float) -> np.ndarray | None:
    """(3, 3) inverse of −H, H the Hessian of a quadratic fitted (least squares) to log_p over the (K, 3) poses within
    `depth` of its maximum; None when the fit is not a peak (H not negative definite) or too few poses are in it."""
    keep = log_p >= log_p.max() - depth
    if keep.sum() < 10:
        return None
    d = poses[keep] - about
    d[:, 2] = wrap_angle(d[:, 2])
    x, y, t = d.T
    design = np.column_stack([np.ones_like(x), x, y, t, x * x, y * y, t * t, x * y, x * t, y * t])
    coef, *_ = np.linalg.lstsq(design, log_p[keep], rcond=None)
    hessian = np.array(
        [[2 * coef[4], coef[7], coef[8]], [coef[7], 2 * coef[5], coef[9]], [coef[8], coef[9], 2 * coef[6]]]
    )
    eigenvalues, vectors = np.linalg.eigh(-hessian)
    if eigenvalues[0] <= 1e-9 * max(eigenvalues[-1], 0.0) or eigenvalues[-1] <= 0.0:
        return None
    return (vectors / eigenvalues) @ vectors.T  # the inverse, positive definite by construction


class CorrelativeMatcher:
    """Matches base-frame 2-D scans (`localization.field.scan_endpoints`) against one prior's likelihood field."""

    def __init__(self, prior: BimPrior, cfg: ScanFactorConfig) -> None:
        distance = face_distances(prior)
        self.field = LikelihoodField(prior, cfg.sigma_m, distance)
        self.coarse_field = LikelihoodField(prior, cfg.coarse_sigma_m, distance)
        self.cfg = cfg
        window_rad, coarse_rad = np.deg2rad(cfg.window_deg), np.deg2rad(cfg.step_deg)
        self._coarse_grid = _SearchGrid(cfg.window_m, cfg.step_m, window_rad, coarse_rad)
        self._fine_grid = _SearchGrid(cfg.step_m, cfg.fine_step_m, coarse_rad, np.deg2rad(cfg.fine_step_deg))
        self._coarse, self._fine = self._coarse_grid.offsets, self._fine_grid.offsets
        self._edge = np.any(np.abs(self._coarse) >= np.abs(self._coarse).max(axis=0), axis=1)
        self._fine_half = np.abs(self._fine).max(axis=0)
        scale = np.array([cfg.window_m, cfg.window_m, window_rad])
        self._tie_break = 1e-6 * ((self._coarse / scale) ** 2).sum(axis=1)
        # The coarse grid's quantisation, step² / 12 per axis, is part of the whole window's spread.
        self._coarse_floor = np.diag([cfg.step_m, cfg.step_m, coarse_rad]) ** 2 / 12.0
        self._min_cov = np.diag([cfg.min_sigma_m, cfg.min_sigma_m, np.deg2rad(cfg.min_sigma_deg)]) ** 2

    def factor_fn(
        self, endpoints: np.ndarray, recentre: int | None = None
    ) -> Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray] | None]:
        """A `backend.posegraph.PoseFactorFn` for one keyframe's (N, 2) endpoints: the accepted match from a pose as
        (pose, body-frame information), None when rejected. Matches are kept by start pose: the offline refinement asks
        again from the very same poses."""
        found: dict[tuple[bytes, int], ScanMatch] = {}

        def measure(pose: np.ndarray, storey: int) -> tuple[np.ndarray, np.ndarray] | None:
            key = (np.asarray(pose, np.float64).tobytes(), int(storey))
            if key not in found:
                found[key] = self.match(pose, storey, endpoints, recentre)
            match = found[key]
            return (match.pose.copy(), match.information_body) if match.accepted else None

        return measure

    def log_likelihood(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K,) log P(z | x) from (K, N) uint8 field values of N endpoints at K poses, and (K,) how many endpoints lie
        on the BIM (field value ≥ 1/2: within 1.18 σ of a face)."""
        cfg = self.cfg
        f = values.astype(np.float32) / np.float32(255.0)
        scale = cfg.effective_endpoints / max(f.shape[1], cfg.effective_endpoints)
        log_p = scale * np.log(f + np.float32(cfg.outlier)).sum(axis=1, dtype=np.float64)
        return log_p, (f >= np.float32(0.5)).sum(axis=1)

    def _search(
        self, grid: _SearchGrid, pose: np.ndarray, storey: int, endpoints: np.ndarray, coarse: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """`log_likelihood` at every pose of a search grid around `pose` (`coarse`: in the smoother field)."""
        field = self.coarse_field if coarse else self.field
        values = field.grid_values(pose, grid.dxy, grid.dyaw, storey, endpoints, self.cfg.clear_before_m)
        return self.log_likelihood(values)

    def _candidates(self, log_c: np.ndarray) -> list[int]:
        """Indices of the `candidates` best coarse poses, each more than one coarse step from the others."""
        cfg = self.cfg
        step = np.array([cfg.step_m, cfg.step_m, np.deg2rad(cfg.step_deg)]) * 1.5
        picked: list[int] = []
        for i in np.argsort(-log_c):
            if all(np.any(np.abs(self._coarse[i] - self._coarse[j]) > step) for j in picked):
                picked.append(int(i))
                if len(picked) == cfg.candidates:
                    break
        return picked

    def match(self, pose: np.ndarray, storey: int, endpoints: np.ndarray, recentre: int | None = None) -> ScanMatch:
        """Search the window around a (3,) pose on a storey for the (N, 2) base-frame endpoints (see the module
        docstring); a rejected match carries the start pose and the reason."""
        pose = np.asarray(pose, np.float64).reshape(3)
        endpoints = np.asarray(endpoints, np.float64).reshape(-1, 2)
        cfg = self.cfg
        if len(endpoints) < cfg.min_endpoints:
            return ScanMatch(pose, np.full((3, 3), np.nan), 0, False, f"{len(endpoints)} endpoints")
        centre = pose
        for _ in range(1 + (cfg.recentre if recentre is None else recentre)):
            coarse = centre + self._coarse
            log_c, _ = self._search(self._coarse_grid, centre, storey, endpoints, coarse=True)
            # Ties (a flat direction: one wall, a corridor) go to the pose nearest the start, not to the window's edge.
            candidates = self._candidates(log_c - self._tie_break)
            scored = [
                (c, coarse[c] + self._fine, *self._search(self._fine_grid, coarse[c], storey, endpoints))
                for c in candidates
            ]
            best, fine, log_f, on_wall = max(scored, key=lambda item: item[2].max())
            if not self._edge[best]:
                break
            # The optimum lies beyond the window: search again about the edge pose that led towards it.
            centre = coarse[best].copy()
            centre[2] = wrap_angle(centre[2])
        else:
            return ScanMatch(pose, np.full((3, 3), np.nan), 0, False, "optimum on the window edge")
        inliers = int(on_wall[np.argmax(log_f)])
        if inliers < cfg.min_inliers:
            return ScanMatch(pose, np.full((3, 3), np.nan), inliers, False, f"{inliers} endpoints on the BIM")
        mean, _ = _moments(fine, log_f, coarse[best])
        # The peak's curvature (the Laplace approximation) is the covariance; a peak too flat for the fine cells, a
        # corridor or a single wall, takes the whole window's spread.
        covariance = _laplace_covariance(fine, log_f, mean, LAPLACE_DEPTH)
        if covariance is None or np.any(np.sqrt(np.diag(covariance)) > self._fine_half):
            _, covariance = _moments(coarse, log_c, coarse[best])
            covariance += self._coarse_floor
        covariance = covariance + np.diag(np.maximum(np.diag(self._min_cov) - np.diag(covariance), 0.0))
        return ScanMatch(mean, covariance, inliers, True)
