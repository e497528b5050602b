"""Fine registrars: align a base-frame scan with a storey's BIM surface model, starting from a planar pose.

Every registrar returns an SE(2) pose (x, y, yaw) at the storey's floor height. `PlanarIcp` ("planar") solves
point-to-plane Gauss–Newton directly over (x, y, yaw); `Open3dIcp` runs one of Open3D's 6-DoF registrations and
projects onto SE(2) after every scale, with a virtual floor pinning z, roll and pitch (docs/registration.md).
Both see only surface samples facing the initial position (`SurfaceModel.facing`), so a scan of a wall's near face
cannot lock onto its far face. Every result carries the same diagnostics, computed at the final pose by
`evaluate_planar`: fitness, point-to-plane inlier RMSE and the planar information matrix JᵀJ / σ² (Open3D's own
information matrix models point-to-point residuals and cannot see that a corridor leaves its axis unconstrained).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from bimfactor.config import RegistrationConfig
from bimfactor.errors import ConfigError
from bimfactor.registration.scan import voxel_downsample
from bimfactor.registration.surface import CROP_CELL_M, SurfaceModel, to_point_cloud
from bimfactor.types import POSE_DECIMALS, matrix_to_se2, se2_to_matrix, wrap_angle

log = logging.getLogger(__name__)

# A final pose is a fixed point of the planar point-to-plane problem when one more Gauss–Newton step is this small.
CONVERGED_STEP_M = 0.005
CONVERGED_STEP_RAD = np.deg2rad(0.1)
# Fewer scan or surface points than this: nothing to register (the result fails the gate).
MIN_POINTS = 10
# Gauss–Newton stops a stage when its step falls below these.
_STEP_TOL_M = 1e-4
_STEP_TOL_RAD = 1e-5


@dataclass
class RegistrationResult:
    """One registration: `pose` (3,) T_world_base as x, y, yaw; `T` (4, 4) at the storey's floor height.

    `information` (3, 3) is over world-frame (x, y, yaw) increments, JᵀJ / σ² of the point-to-plane
    residuals; `iterations` is -1 for Open3D registrars (Open3D does not report it).
    """

    method: str
    pose: np.ndarray
    T: np.ndarray
    fitness: float
    inlier_rmse: float
    n_correspondences: int
    information: np.ndarray
    iterations: int
    time_ms: float
    converged: bool


class Registrar(Protocol):
    """Aligns a base-frame scan (N, 3) with a surface model from an initial planar pose (3,)."""

    name: str

    def register(
        self,
        scan_base: np.ndarray,
        surface: SurfaceModel,
        T_world_base_init: np.ndarray,
        storey_elevation: float | None = None,
    ) -> RegistrationResult: ...


# ------------------------------------------------------------------------------------ planar point-to-plane


@dataclass
class PlanarTerms:
    """Point-to-plane terms at a pose: residuals (K,), Jacobian (K, 3) over x, y, yaw, and which scan rows matched."""

    residuals: np.ndarray
    jacobian: np.ndarray
    matched: np.ndarray
    n_scan: int


def planar_terms(
    scan_base: np.ndarray,
    surface: SurfaceModel,
    pose: np.ndarray,
    z_m: float,
    max_dist_m: float,
) -> PlanarTerms:
    """Correspondences of the scan at `pose` with the nearest surface samples within `max_dist_m`, linearised."""
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    q = np.empty_like(scan_base)
    q[:, 0] = c * scan_base[:, 0] - s * scan_base[:, 1] + x
    q[:, 1] = s * scan_base[:, 0] + c * scan_base[:, 1] + y
    q[:, 2] = scan_base[:, 2] + z_m
    dist, idx = surface.nn_tree.query(q, distance_upper_bound=max_dist_m)
    matched = np.isfinite(dist)
    q, idx = q[matched], idx[matched]
    n = surface.normals[idx]
    residuals = np.einsum("ij,ij->i", n, q - surface.points[idx])
    # ∂r/∂yaw = nᵀ · (dR/dyaw · s) = n_x·(−(q_y − y)) + n_y·(q_x − x)
    dyaw = -n[:, 0] * (q[:, 1] - y) + n[:, 1] * (q[:, 0] - x)
    return PlanarTerms(residuals, np.column_stack([n[:, 0], n[:, 1], dyaw]), matched, len(scan_base))


def _gauss_newton_step(terms: PlanarTerms, robust_k_m: float | None) -> np.ndarray:
    """The damped Gauss–Newton step (3,) of the (optionally Huber-weighted) planar point-to-plane problem."""
    r, J = terms.residuals, terms.jacobian
    w = np.ones_like(r)
    if robust_k_m is not None:
        big = np.abs(r) > robust_k_m
        w[big] = robust_k_m / np.abs(r[big])
    H = J.T @ (J * w[:, None])
    g = J.T @ (w * r)
    # A tiny Levenberg damping keeps a degenerate corridor from producing a wild step along its axis.
    H += 1e-6 * max(np.trace(H), 1.0) * np.eye(3)
    return -np.linalg.solve(H, g)


@dataclass
class PlanarEvaluation:
    """Diagnostics of a planar pose against the surface (see `evaluate_planar`)."""

    fitness: float
    inlier_rmse: float
    n_correspondences: int
    information: np.ndarray
    step: np.ndarray


def evaluate_planar(
    scan_base: np.ndarray,
    surface: SurfaceModel,
    pose: np.ndarray,
    z_m: float,
    max_dist_m: float,
    sigma_m: float,
) -> PlanarEvaluation:
    """Fitness (share of scan points matched within `max_dist_m`), point-to-plane RMSE, JᵀJ/σ² (3, 3), next GN step."""
    terms = planar_terms(scan_base, surface, pose, z_m, max_dist_m)
    k = len(terms.residuals)
    if k < 3:
        return PlanarEvaluation(k / max(terms.n_scan, 1), float("inf"), k, np.zeros((3, 3)), np.zeros(3))
    J = terms.jacobian
    return PlanarEvaluation(
        fitness=k / terms.n_scan,
        inlier_rmse=float(np.sqrt(np.mean(terms.residuals**2))),
        n_correspondences=k,
        information=J.T @ J / sigma_m**2,
        step=_gauss_newton_step(terms, None),
    )


def evaluate_pose(
    scan_base: np.ndarray, surface: SurfaceModel, pose: np.ndarray, cfg: RegistrationConfig
) -> PlanarEvaluation:
    """`evaluate_planar` of the (N, 3) scan at a (3,) pose against the storey surface as seen from there."""
    visible = surface.facing_near(scan_in_world(scan_base, pose), 1, pose[:2])
    return evaluate_planar(scan_base, visible, pose, surface.elevation_m, cfg.final_correspondence_m, cfg.noise_sigma_m)


def registration_result(
    method: str,
    scan_base: np.ndarray,
    surface: SurfaceModel,
    pose: np.ndarray,
    z_m: float,
    cfg: RegistrationConfig,
    iterations: int,
    t0: float,
    start_xy: np.ndarray,
    visible: SurfaceModel | None = None,
) -> RegistrationResult:
    """A registrar's final (3,) pose with the shared diagnostics (`evaluate_planar` against the storey's `surface`
    as seen from the start `start_xy`, back faces culled, as the registrars' crops are) and the time since `t0`.
    `visible`: a crop of it that already holds every sample within reach of the scan at `pose` (`PlanarIcp`'s)."""
    pose = np.array([pose[0], pose[1], wrap_angle(pose[2])], dtype=np.float64)
    dist, sigma = cfg.final_correspondence_m, cfg.noise_sigma_m
    # Nearest among the facing samples (a crop with its own KD-tree): a storey-wide tree with back faces rejected
    # after the query lost the points near corners, whose nearest sample is the other face. The crop is the cells
    # the scan at its final pose touches and their neighbours (a match lies within `dist` < one cell), not the disc
    # of the scan's reach: a third of the samples or fewer, and the KD-tree built over them is the stage's largest.
    if visible is None:
        visible = surface.facing_near(scan_in_world(scan_base, pose), 1, start_xy)
    ev = evaluate_planar(scan_base, visible, pose, z_m, dist, sigma)
    converged = bool(
        ev.n_correspondences >= 3
        and np.hypot(ev.step[0], ev.step[1]) < CONVERGED_STEP_M
        and abs(ev.step[2]) < CONVERGED_STEP_RAD
    )
    return RegistrationResult(
        method=method,
        pose=pose,
        T=se2_to_matrix(pose, z_m),
        fitness=ev.fitness,
        inlier_rmse=ev.inlier_rmse,
        n_correspondences=ev.n_correspondences,
        information=ev.information,
        iterations=iterations,
        time_ms=(time.perf_counter() - t0) * 1000,
        converged=converged,
    )


def planar_multistart(
    scan_base: np.ndarray,
    surface: SurfaceModel,
    starts: np.ndarray,
    z_m: float,
    cfg: RegistrationConfig,
    tolerance: float = 1.0,
) -> np.ndarray:
    """(P, 3) poses of the planar Gauss–Newton solver (`PlanarIcp`'s schedule: the correspondence distance halving from
    `max_correspondence_m` to `final_correspondence_m` each time a start settles) run from each of the (P, 3)
    `starts` at once against one `surface` (already cropped; one KD-tree, one query per iteration for every start).
    A start settles when its step is below `tolerance` × `PlanarIcp`'s (a probe needs its end to a millimetre)."""
    scan = np.asarray(scan_base, dtype=np.float64)
    poses = np.array(starts, dtype=np.float64).reshape(-1, 3)
    n_starts, n = len(poses), len(scan)
    if n_starts == 0 or n < 3 or len(surface) < 3:
        return poses
    final = cfg.final_correspondence_m
    dist = np.full(n_starts, max(cfg.max_correspondence_m, final))
    active = np.ones(n_starts, dtype=bool)
    for _ in range(cfg.max_iterations):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        p = poses[idx]
        c, s = np.cos(p[:, 2])[:, None], np.sin(p[:, 2])[:, None]
        qx = (c * scan[:, 0] - s * scan[:, 1] + p[:, 0:1]).ravel()
        qy = (s * scan[:, 0] + c * scan[:, 1] + p[:, 1:2]).ravel()
        qz = np.tile(scan[:, 2] + z_m, len(idx))
        limit = np.repeat(dist[idx], n)
        d, nearest = surface.nn_tree.query(np.column_stack([qx, qy, qz]), distance_upper_bound=float(limit.max()))
        hit = np.flatnonzero(d <= limit)
        owner, m = hit // n, nearest[hit]
        normal, target = surface.normals[m], surface.points[m]
        rx, ry = qx[hit] - p[owner, 0], qy[hit] - p[owner, 1]
        r = normal[:, 0] * (qx[hit] - target[:, 0]) + normal[:, 1] * (qy[hit] - target[:, 1])
        r += normal[:, 2] * (qz[hit] - target[:, 2])
        J = np.column_stack([normal[:, 0], normal[:, 1], -normal[:, 0] * ry + normal[:, 1] * rx])
        # per-start normal equations: the six entries of JᵀJ and the three of Jᵀr, summed by start
        upper = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        sums = [np.bincount(owner, J[:, i] * J[:, j], minlength=len(idx)) for i, j in upper]
        H = np.empty((len(idx), 3, 3))
        for (i, j), total in zip(upper, sums, strict=True):
            H[:, i, j] = H[:, j, i] = total
        g = np.stack([np.bincount(owner, J[:, i] * r, minlength=len(idx)) for i in range(3)], axis=1)
        H += 1e-6 * np.maximum(np.trace(H, axis1=1, axis2=2), 1.0)[:, None, None] * np.eye(3)
        few = np.bincount(owner, minlength=len(idx)) < 3
        step = -np.linalg.solve(H, g[..., None])[..., 0]
        step[few] = 0.0
        poses[idx] += step
        settled = (np.hypot(step[:, 0], step[:, 1]) < tolerance * _STEP_TOL_M) & (
            np.abs(step[:, 2]) < tolerance * _STEP_TOL_RAD
        )
        done = few | (settled & (dist[idx] <= final))
        dist[idx[settled]] = np.maximum(dist[idx[settled]] / 2, final)
        active[idx[done]] = False
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


class PlanarIcp:
    """Point-to-plane ICP solved over SE(2) by Gauss–Newton (the default registrar, "planar").

    The correspondence distance halves from `max_correspondence_m` to `final_correspondence_m` each time
    Gauss–Newton settles; `robust_k_m` (optional) adds Huber weights.
    """

    def __init__(
        self,
        cfg: RegistrationConfig,
        name: str = "planar",
        robust_k_m: float | None = None,
        near_cells: int | None = None,
    ):
        self.cfg = cfg
        self.name = name
        self.robust_k_m = robust_k_m
        # None: the facing disc of the scan's reach; a count: the cells the scan touches and that many around them
        # (`SurfaceModel.facing_near`), for a start already within a cell of the answer (`Polished`).
        self.near_cells = near_cells

    def register(
        self,
        scan_base: np.ndarray,
        surface: SurfaceModel,
        T_world_base_init: np.ndarray,
        storey_elevation: float | None = None,
    ) -> RegistrationResult:
        t0 = time.perf_counter()
        z = surface.elevation_m if storey_elevation is None else storey_elevation
        pose = np.asarray(T_world_base_init, dtype=np.float64).copy()
        start, storey = pose.copy(), surface
        full_scan = np.asarray(scan_base, float)
        scan = thin(full_scan, self.cfg.max_scan_points)
        dist = max(self.cfg.max_correspondence_m, self.cfg.final_correspondence_m)
        if self.near_cells is None:
            surface = surface.facing(pose[:2], scan_reach(scan) + dist + self.cfg.crop_margin_m)
        else:
            # the cells of the whole scan, so that the final diagnostics can read the same crop
            surface = surface.facing_near(scan_in_world(full_scan, pose), self.near_cells, pose[:2])
        iterations = 0
        while iterations < self.cfg.max_iterations:
            iterations += 1
            terms = planar_terms(scan, surface, pose, z, dist)
            if len(terms.residuals) < 3:
                break
            step = _gauss_newton_step(terms, self.robust_k_m)
            pose += step
            if np.hypot(step[0], step[1]) < _STEP_TOL_M and abs(step[2]) < _STEP_TOL_RAD:
                if dist <= self.cfg.final_correspondence_m:
                    break
                dist = max(dist / 2, self.cfg.final_correspondence_m)
        # The crop still holds every sample within reach of the scan when the pose moved less than the cells it grew
        # by, less the final correspondence distance.
        moved = float(np.hypot(*(pose[:2] - start[:2]))) + scan_reach(full_scan) * abs(wrap_angle(pose[2] - start[2]))
        reach = (self.near_cells or 0) * CROP_CELL_M - self.cfg.final_correspondence_m
        visible = surface if self.near_cells and moved < reach else None
        return registration_result(self.name, full_scan, storey, pose, z, self.cfg, iterations, t0, start[:2], visible)


# ------------------------------------------------------------------------------------ Open3D 6-DoF + projection


def scan_in_world(scan_base: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N, 2) world x, y of the (N, 3) base-frame scan at the planar `pose` (3,)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    x, y = scan_base[:, 0], scan_base[:, 1]
    return np.column_stack([c * x - s * y + pose[0], s * x + c * y + pose[1]])


def scan_reach(scan: np.ndarray) -> float:
    """How far the (N, 3) base-frame scan reaches in the xy-plane."""
    return float(np.sqrt(np.max(np.sum(scan[:, :2] ** 2, axis=1)))) if len(scan) else 0.0


def thin(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most `max_points` of the (N, 3) points, evenly strided (deterministic)."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).astype(int)]


# The 6-DoF registrars align with a random TARGET_SHARE of the storey's samples: their per-call KD-tree and
# correspondence search scale with the target; the diagnostics and the gate keep every sample.
TARGET_SHARE = 0.5
# Every FLOOR_STRIDE-th point's copy is dropped to the floor: the floor only pins z, roll and pitch, and a tenth of
# the points does that as well as all of them at a fraction of the correspondences.
FLOOR_STRIDE = 10
# Open3D's ICP stops a scale when fitness and RMSE change by less than this share (its default 1e-6 ran every fit
# to max_iterations for sub-micrometre changes).
ICP_RELATIVE_CHANGE = 1e-4


def target_stride(voxel_m: float, finest_voxel_m: float) -> int:
    """Every how many target samples a scale of scan voxel `voxel_m` keeps: √(voxel_m / finest_voxel_m)."""
    return max(int(np.sqrt(voxel_m / finest_voxel_m) + 1e-9), 1)


def with_virtual_floor(points: np.ndarray, normals: np.ndarray | None, floor_z_m: float, covariances: bool = False):
    """Open3D cloud of the (N, 3) points plus a copy of every `FLOOR_STRIDE`-th one dropped to `floor_z_m` (normal
    +z): pins z, roll and pitch. `covariances` adds GICP's plane covariances from the normals."""
    floor = points[::FLOOR_STRIDE].copy()
    floor[:, 2] = floor_z_m
    both = np.concatenate([points, floor])
    if normals is None:
        return to_point_cloud(both)
    up = np.zeros_like(floor)
    up[:, 2] = 1.0
    return to_point_cloud(both, np.concatenate([normals, up]), planar_covariance=covariances)


@dataclass(frozen=True)
class Scale:
    """One stage of an Open3D registrar: scan voxel size and max correspondence distance (metres)."""

    voxel_m: float
    max_correspondence_m: float


class CentredRegistrar:
    """The frame every 6-DoF registrar works in; subclasses implement `align`. The target is the surface cropped around
    the initial pose to the scan's reach, in a frame centred on that pose (the libraries linearise rotations about the
    origin; lever arms of tens of metres made Open3D diverge); the result is projected onto (x, y, yaw)."""

    name: str
    cfg: RegistrationConfig

    def reach_m(self) -> float:
        """How far beyond the scan's reach the target is cropped (before `crop_margin_m`)."""
        return self.cfg.max_correspondence_m

    def register(
        self,
        scan_base: np.ndarray,
        surface: SurfaceModel,
        T_world_base_init: np.ndarray,
        storey_elevation: float | None = None,
    ) -> RegistrationResult:
        t0 = time.perf_counter()
        z = surface.elevation_m if storey_elevation is None else storey_elevation
        full_scan = np.asarray(scan_base, dtype=np.float64)
        start = np.asarray(T_world_base_init, dtype=np.float64)
        pose, iterations = self.fit(full_scan, surface, start, z)
        return registration_result(self.name, full_scan, surface, pose, z, self.cfg, iterations, t0, start[:2])

    def fit(
        self, scan_base: np.ndarray, surface: SurfaceModel, start: np.ndarray, z_m: float
    ) -> tuple[np.ndarray, int]:
        """The (3,) planar pose of the fit from the (3,) `start` and its iteration count, without the diagnostics
        (`register` adds them; `Polished` has its polish add them instead)."""
        scan = thin(scan_base, self.cfg.max_scan_points)
        target = surface.thinned(TARGET_SHARE)
        local = target.facing(start[:2], scan_reach(scan) + self.reach_m() + self.cfg.crop_margin_m)
        if len(scan) < MIN_POINTS or len(local) < MIN_POINTS:
            return start.copy(), 0
        center = np.array([start[0], start[1], 0.0])
        T, iterations = self.align(scan, local, center, se2_to_matrix(start - center, z_m), z_m)
        # Projection onto SE(2): keep x, y and the heading; drop z, roll and pitch.
        return matrix_to_se2(T) + center, iterations

    def align(
        self, scan: np.ndarray, local: SurfaceModel, center: np.ndarray, T_init: np.ndarray, z_m: float
    ) -> tuple[np.ndarray, int]:
        """(4, 4) T_centred_base of the (N, 3) scan against `local` (world frame; subtract `center`), from
        `T_init`, and the iteration count (-1: not reported)."""
        raise NotImplementedError


class Open3dIcp(CentredRegistrar):
    """Open3D's 6-DoF ICP (`kind`: point_to_point, point_to_plane, robust, gicp), projected onto SE(2) per scale."""

    def __init__(self, cfg: RegistrationConfig, kind: str, scales: list[Scale] | None = None, name: str | None = None):
        if kind not in ("point_to_point", "point_to_plane", "robust", "gicp"):
            raise ConfigError(f"unknown Open3D ICP kind '{kind}'")
        self.cfg = cfg
        self.kind = kind
        # By default the correspondence distance shrinks as the planar solver's does: a wide basin, then a tight fit.
        self.scales = scales or [
            Scale(cfg.scan_voxel_m, cfg.max_correspondence_m),
            Scale(cfg.scan_voxel_m, cfg.final_correspondence_m),
        ]
        self.name = name if name is not None else kind

    def reach_m(self) -> float:
        return max(s.max_correspondence_m for s in self.scales)

    def _estimation(self):
        import open3d as o3d

        reg = o3d.pipelines.registration
        if self.kind == "point_to_point":
            return reg.TransformationEstimationPointToPoint()
        if self.kind == "point_to_plane":
            return reg.TransformationEstimationPointToPlane()
        if self.kind == "robust":
            loss = (
                reg.TukeyLoss(self.cfg.robust_k_m)
                if self.cfg.robust_kernel == "tukey"
                else reg.HuberLoss(self.cfg.robust_k_m)
            )
            return reg.TransformationEstimationPointToPlane(loss)
        return reg.TransformationEstimationForGeneralizedICP()

    def align(
        self, scan: np.ndarray, local: SurfaceModel, center: np.ndarray, T_init: np.ndarray, z_m: float
    ) -> tuple[np.ndarray, int]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        estimation = self._estimation()
        criteria = reg.ICPConvergenceCriteria(
            relative_fitness=ICP_RELATIVE_CHANGE,
            relative_rmse=ICP_RELATIVE_CHANGE,
            max_iteration=self.cfg.max_iterations,
        )
        T = T_init
        for scale in self.scales:
            coarse = scale.voxel_m > self.cfg.scan_voxel_m
            source_points = voxel_downsample(scan, scale.voxel_m) if coarse else scan
            source = with_virtual_floor(source_points, None, 0.0)
            # A coarser scale needs a target no denser than its scan: every k-th sample of the crop (a random share
            # already), k the ratio of the voxel sizes, so the per-call KD-tree shrinks with the scale.
            stride = target_stride(scale.voxel_m, self.cfg.scan_voxel_m)
            points, normals = local.points[::stride] - center, local.normals[::stride]
            target = with_virtual_floor(points, normals, z_m, covariances=self.kind == "gicp")
            distance = scale.max_correspondence_m
            if self.kind == "gicp":
                source.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(20))
                out = reg.registration_generalized_icp(source, target, distance, T, estimation, criteria)
            else:
                out = reg.registration_icp(source, target, distance, T, estimation, criteria)
            # Back onto SE(2) after every scale, so z, roll and pitch never carry over; rounded, so a run repeats.
            T = se2_to_matrix(np.round(matrix_to_se2(np.asarray(out.transformation)), POSE_DECIMALS), z_m)
        return T, -1


class Polished:
    """A registrar whose result the planar solver polishes at `final_correspondence_m` (`PlanarIcp`): the 6-DoF fit
    projected onto SE(2) is not the SE(2) optimum, and the polish is."""

    def __init__(self, cfg: RegistrationConfig, coarse: CentredRegistrar) -> None:
        self.cfg = cfg
        self.name = coarse.name
        self._coarse = coarse
        self._polish = PlanarIcp(
            cfg.model_copy(update={"max_correspondence_m": cfg.final_correspondence_m}), near_cells=1
        )

    def register(
        self,
        scan_base: np.ndarray,
        surface: SurfaceModel,
        T_world_base_init: np.ndarray,
        storey_elevation: float | None = None,
    ) -> RegistrationResult:
        t0 = time.perf_counter()
        z = surface.elevation_m if storey_elevation is None else storey_elevation
        scan = np.asarray(scan_base, dtype=np.float64)
        pose, _ = self._coarse.fit(scan, surface, np.asarray(T_world_base_init, dtype=np.float64), z)
        result = self._polish.register(scan, surface, pose, storey_elevation)
        result.method = self.name
        result.time_ms = (time.perf_counter() - t0) * 1000
        return result


# ------------------------------------------------------------------------------------ registry


def _small_gicp(cfg: RegistrationConfig) -> Registrar:
    from bimfactor.registration.external import SmallGicp

    return SmallGicp(cfg)


def _kiss_icp(cfg: RegistrationConfig) -> Registrar:
    from bimfactor.registration.external import KissIcp

    return KissIcp(cfg)


REGISTRARS: dict[str, Callable[[RegistrationConfig], Registrar]] = {
    "planar": lambda cfg: PlanarIcp(cfg),
    # Open3D point-to-plane, coarse to fine (the default): the widest basin and the fastest fit in compare-registrars
    "point_to_plane": lambda cfg: Polished(
        cfg,
        Open3dIcp(
            cfg,
            "point_to_plane",
            [Scale(v, d) for v, d in zip(cfg.multiscale_voxels_m, cfg.multiscale_correspondence_m, strict=True)],
        ),
    ),
    "point_to_point": lambda cfg: Open3dIcp(cfg, "point_to_point"),
    "robust": lambda cfg: Open3dIcp(cfg, "robust"),
    "gicp": lambda cfg: Open3dIcp(cfg, "gicp"),
    # Optional libraries (`pip install 'bimfactor[registrars]'`); see `available_registrars`.
    "small_gicp": _small_gicp,
    "kiss_icp": _kiss_icp,
}


def available_registrars() -> list[str]:
    """The names in `REGISTRARS` that can run here: the built-in ones and the optional ones that are installed."""
    from bimfactor.registration.external import OPTIONAL_MODULES, is_available

    return [name for name in REGISTRARS if name not in OPTIONAL_MODULES or is_available(name)]


def make_registrar(cfg: RegistrationConfig, method: str | None = None) -> Registrar:
    """The registrar named `method` (default: `cfg.method`); names are the keys of `REGISTRARS`."""
    method = cfg.method if method is None else method
    if method not in REGISTRARS:
        raise ConfigError(f"unknown registrar '{method}' (known: {', '.join(REGISTRARS)})")
    return REGISTRARS[method](cfg)
