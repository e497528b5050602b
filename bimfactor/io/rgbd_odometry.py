"""RGB-D odometry: planar odometry for a recording that has none, from its colour and depth frames alone.

Each pair of consecutive frames gets a 6-DoF relative camera pose in two steps:

1. Initial guess: ORB features of both images are matched (OpenCV's brute-force Hamming matcher, cross-checked), the
   previous frame's keypoints are lifted with its depth, and `cv2.solvePnPRansac` finds the pose that projects them
   onto the current frame's keypoints.
2. Dense refinement: Open3D point-to-plane ICP of the current frame's depth cloud onto the previous one's, coarse to
   fine over voxelised clouds. ICP starts from each of the PnP pose (when PnP found one), the previous pair's motion
   (a camera keeps moving as it moved) and no motion; the start whose coarse ICP covers the most points wins.

A pair whose PnP failed (too few matches or inliers, common in low-texture scenes) "falls back": its pose rests on
the depth geometry and the start it was given, and the result says so.

The camera poses are chained (T_cam0_camk) and carried through the camera mount into the robot base:
T_odom_base(k) = T_base_camera · T_cam0_camk · T_base_camera⁻¹, projected onto the floor plane (x, y, yaw). The
odometry frame is the base at the first frame. Measured accuracy and the noise model: docs/rgbd-odometry.md.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d

from bimfactor.io.sequence import Sequence
from bimfactor.io.tum import MAX_TILT_DEG, planar_from_matrices
from bimfactor.progress import progress
from bimfactor.types import CameraIntrinsics

log = logging.getLogger(__name__)

ORB_FEATURES = 3000  # keypoints per image
ORB_FAST_THRESHOLD = 12  # OpenCV's default 20 finds few corners on the simulator's flat-shaded walls
PNP_REPROJECTION_PX = 3.0  # RANSAC inlier threshold
PNP_MIN_INLIERS = 20  # fewer PnP inliers than this: no initial guess from features
PNP_ITERATIONS = 300
MAX_DEPTH_M = 8.0  # depth beyond this is too noisy to register (a Kinect's σ grows with z²)
ICP_VOXELS_M = (0.10, 0.05)  # coarse-to-fine voxel sizes of the dense step
ICP_CORRESPONDENCE_VOXELS = 2.5  # a correspondence lies within this many voxels
ICP_ITERATIONS = (30, 20)
ICP_MAX_SOURCE_POINTS = (5000, 5000)  # the moving cloud is thinned (strided) to at most this many points per scale
ICP_START_MARGIN = 0.05  # another start must cover this much more of the cloud than the preferred one to win
NORMAL_NEIGHBOURS = 20
MIN_CORRESPONDENCES = 50
TUKEY_VOXELS = 1.0
REMAP = True
DEDUPE = True
YAW_OF_IDENTITY = False
SELECT_LEVELS = 2
ALWAYS_OTHERS = False
ICP_MAX_CORRECTION_M = 0.75
ICP_MAX_CORRECTION_DEG = 25.0
DENSE_MAX_CORRECTION_M = 0.3
DENSE_MAX_CORRECTION_DEG = 10.0
MIN_FITNESS = 0.3
DENSE = True
IDENTITY_TOO = True
HYBRID_DEPTH_DIFF = 0.07
YAW_BASES = ("identity",)
HYBRID_ITER = (20, 10, 5)
DEGENERATE_EIGENVALUE = 0.02
FLAT_EIGENVALUE = 0.06
YAW_STARTS_DEG = (-30.0, -15.0, 15.0, 30.0)


@dataclass(frozen=True)
class PairOdometry:
    """The relative pose of one pair of consecutive frames and how it was found.

    `T_prev_curr` (4, 4) maps the current camera's coordinates into the previous camera's. `start` is the dense step's
    initial guess: "pnp", "previous" (the previous pair's motion) or "identity". `fitness` is the share of the current
    frame's cloud within the finest correspondence distance of the previous one after ICP, `inlier_rmse_m` their RMS
    point-to-point distance.
    """

    T_prev_curr: np.ndarray
    matches: int
    pnp_inliers: int
    start: str
    fitness: float
    inlier_rmse_m: float
    constrained_dofs: int = 6

    @property
    def fell_back(self) -> bool:
        """True when PnP gave no initial guess (the pose rests on the depth geometry alone)."""
        return self.start != "pnp"


@dataclass
class RgbdOdometryResult:
    """RGB-D odometry of a sequence of N frames.

    `odom_poses` (N, 3) T_odom_base as x, y, yaw (the base at frame 0 is the origin); `T_cam0_cam` (N, 4, 4) camera
    poses in the first camera's frame; `pairs` the N − 1 relative poses, frame k − 1 → k.
    """

    odom_poses: np.ndarray
    T_cam0_cam: np.ndarray
    pairs: list[PairOdometry] = field(default_factory=list)

    @property
    def fell_back(self) -> np.ndarray:
        """(N − 1,) bool: the pairs whose PnP failed."""
        return np.array([p.fell_back for p in self.pairs], bool)

    @property
    def pnp_inliers(self) -> np.ndarray:
        """(N − 1,) PnP inlier counts."""
        return np.array([p.pnp_inliers for p in self.pairs], np.int64)

    @property
    def fitness(self) -> np.ndarray:
        """(N − 1,) ICP fitness of each pair."""
        return np.array([p.fitness for p in self.pairs], np.float64)


@dataclass
class _PreparedFrame:
    """What a frame contributes to both of its pairs, computed once: ORB features and the voxelised clouds."""

    keypoints_px: np.ndarray  # (K, 2)
    descriptors: np.ndarray | None  # (K, 32) uint8
    keypoints_camera: np.ndarray  # (K, 3), NaN where the keypoint has no depth
    clouds: list[o3d.geometry.PointCloud]  # one per ICP_VOXELS_M, with normals
    rgbd: o3d.t.geometry.RGBDImage


class RgbdOdometry:
    """Frame-to-frame RGB-D odometry of one camera: feed frames in order with `add`, read the poses back."""

    def __init__(
        self, intrinsics: CameraIntrinsics, T_base_camera: np.ndarray, *, max_depth_m: float = MAX_DEPTH_M
    ) -> None:
        self.intrinsics = intrinsics
        self.T_base_camera = np.asarray(T_base_camera, np.float64)
        self.max_depth_m = max_depth_m
        self._K = o3d.core.Tensor(intrinsics.K)
        self._orb = cv2.ORB_create(nfeatures=ORB_FEATURES, fastThreshold=ORB_FAST_THRESHOLD)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)

    def prepare(self, rgb: np.ndarray, depth_m: np.ndarray) -> _PreparedFrame:
        """Features and clouds of one frame: (H, W, 3) uint8 RGB, (H, W) depth in metres (NaN or 0: no return)."""
        k = self.intrinsics
        depth = np.asarray(depth_m, np.float64)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth > 0) & (depth <= self.max_depth_m)
        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        keypoints, descriptors = self._orb.detectAndCompute(gray, None)
        px = np.array([kp.pt for kp in keypoints], np.float64).reshape(-1, 2)
        u = np.clip(np.rint(px[:, 0]).astype(np.int64), 0, k.width - 1)
        v = np.clip(np.rint(px[:, 1]).astype(np.int64), 0, k.height - 1)
        z = np.where(valid[v, u], depth[v, u], np.nan)
        keypoints_camera = np.column_stack([(px[:, 0] - k.cx) / k.fx * z, (px[:, 1] - k.cy) / k.fy * z, z])

        rows, cols = np.nonzero(valid)
        z = depth[rows, cols]
        points = np.column_stack([(cols - k.cx) / k.fx * z, (rows - k.cy) / k.fy * z, z])
        full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        clouds = []
        for voxel in ICP_VOXELS_M:
            cloud = full.voxel_down_sample(voxel)
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
            cloud.orient_normals_towards_camera_location(np.zeros(3))
            clouds.append(cloud)
        image = o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb))),
            o3d.t.geometry.Image(o3d.core.Tensor(np.where(valid, depth, 0.0).astype(np.float32))),
        )
        return _PreparedFrame(px, descriptors, keypoints_camera, clouds, image)

    def pnp(self, prev: _PreparedFrame, curr: _PreparedFrame) -> tuple[np.ndarray | None, int, int]:
        """ORB matches → PnP RANSAC: (T_prev_curr or None, matches, inliers)."""
        if prev.descriptors is None or curr.descriptors is None:
            return None, 0, 0
        matches = self._matcher.match(prev.descriptors, curr.descriptors)
        i_prev = np.array([m.queryIdx for m in matches], np.int64)
        i_curr = np.array([m.trainIdx for m in matches], np.int64)
        has_depth = np.isfinite(prev.keypoints_camera[i_prev, 2])
        i_prev, i_curr = i_prev[has_depth], i_curr[has_depth]
        if len(i_prev) < PNP_MIN_INLIERS:
            return None, len(matches), 0
        cv2.setRNGSeed(0)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            prev.keypoints_camera[i_prev],
            curr.keypoints_px[i_curr],
            self.intrinsics.K,
            None,
            iterationsCount=PNP_ITERATIONS,
            reprojectionError=PNP_REPROJECTION_PX,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        n_inliers = 0 if inliers is None else len(inliers)
        if not ok or n_inliers < PNP_MIN_INLIERS:
            return None, len(matches), n_inliers
        T_curr_prev = np.eye(4)
        T_curr_prev[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_curr_prev[:3, 3] = np.ravel(tvec)
        return np.linalg.inv(T_curr_prev), len(matches), n_inliers

    def relative_pose(
        self, prev: _PreparedFrame, curr: _PreparedFrame, previous_motion: np.ndarray | None = None
    ) -> PairOdometry:
        """T_prev_curr of two prepared frames; `previous_motion` (4, 4) is the previous pair's, when there is one."""
        T_pnp, n_matches, n_inliers = self.pnp(prev, curr)
        if T_pnp is not None and not ALWAYS_OTHERS:
            starts = [("pnp", T_pnp)]
        elif T_pnp is not None:
            starts = (
                [("pnp", T_pnp)]
                + ([("previous", previous_motion)] if previous_motion is not None else [])
                + [("identity", np.eye(4))]
            )
        else:
            if YAW_OF_IDENTITY:
                starts = ([("previous", previous_motion)] if previous_motion is not None else []) + [
                    ("identity", np.eye(4))
                ]
                for d in YAW_STARTS_DEG:
                    turn = np.linalg.inv(self.T_base_camera) @ _yaw_matrix(math.radians(d)) @ self.T_base_camera
                    starts.append(("turn", turn))
            else:
                base_name, base = (
                    ("previous", previous_motion) if previous_motion is not None else ("identity", np.eye(4))
                )
                starts = [(base_name, base)]
                for d in YAW_STARTS_DEG:
                    turn = np.linalg.inv(self.T_base_camera) @ _yaw_matrix(math.radians(d)) @ self.T_base_camera
                    starts.append((base_name, turn @ base))
                if base_name != "identity" and IDENTITY_TOO:
                    starts.append(("identity", np.eye(4)))
        best = None
        converged: list[np.ndarray] = []
        for name, T0 in starts:
            result = self._icp(prev, curr, T0, 0)
            T = np.asarray(result.transformation)
            if DEDUPE and any(_close(T, other) for other in converged):
                continue
            converged.append(T)
            for scale in range(1, SELECT_LEVELS):
                result = self._icp(prev, curr, T, scale)
                T = np.asarray(result.transformation)
            fitness = result.fitness
            if not _within(T, T0, ICP_MAX_CORRECTION_M, ICP_MAX_CORRECTION_DEG):
                T, fitness = T0, 0.0
            if best is None or fitness > best[3] + ICP_START_MARGIN:
                best = (name, T0, T, fitness)
        name, T0, T, icp_fitness = best
        for scale in range(SELECT_LEVELS, len(ICP_VOXELS_M)):
            result = self._icp(prev, curr, T, scale)
            if _within(np.asarray(result.transformation), T, DENSE_MAX_CORRECTION_M, DENSE_MAX_CORRECTION_DEG):
                T = np.asarray(result.transformation)
        fitness, rmse = icp_fitness, 0.0
        if DENSE:
            T_dense, fitness, rmse = self._dense(prev, curr, T)
            if _within(T_dense, T, DENSE_MAX_CORRECTION_M, DENSE_MAX_CORRECTION_DEG):
                T = T_dense
        n_constrained = 6
        check = self._evaluate(prev, curr, T)
        if check.fitness < MIN_FITNESS:
            return PairOdometry(np.asarray(T0).copy(), n_matches, n_inliers, name, check.fitness, rmse, 0)
        if REMAP:
            T, n_constrained = self._keep_prior_where_flat(prev, T0, T, check)
        return PairOdometry(T, n_matches, n_inliers, name, check.fitness, check.inlier_rmse, n_constrained)

    def _keep_prior_where_flat(self, prev, T_prior, T, check):
        """Planar remap: along a horizontal base direction that no surface faces, keep the prior's translation."""
        corr = np.asarray(check.correspondence_set)
        Tbc = self.T_base_camera
        inv = np.linalg.inv(Tbc)
        if len(corr) < MIN_CORRESPONDENCES:
            return np.asarray(T_prior).copy(), 0
        scale = len(ICP_VOXELS_M) - 1
        n = np.asarray(prev.clouds[scale].normals)[corr[:, 1]] @ Tbc[:3, :3].T
        H = n[:, :2].T @ n[:, :2] / len(n)
        eigenvalues, V = np.linalg.eigh(H)
        weak = V[:, eigenvalues < FLAT_EIGENVALUE]
        if weak.shape[1] == 0:
            return T, 2
        Tb = Tbc @ T @ inv
        Tb0 = Tbc @ T_prior @ inv
        Tb[:2, 3] += weak @ (weak.T @ (Tb0[:2, 3] - Tb[:2, 3]))
        if weak.shape[1] == 2:
            Tb[:3, :3] = Tb0[:3, :3]
        return inv @ Tb @ Tbc, 2 - weak.shape[1]

    def _evaluate(self, prev, curr, T):
        reg = o3d.pipelines.registration
        scale = len(ICP_VOXELS_M) - 1
        source = curr.clouds[scale]
        cap = ICP_MAX_SOURCE_POINTS[scale]
        if len(source.points) > cap:
            source = source.uniform_down_sample(math.ceil(len(source.points) / cap))
        return reg.evaluate_registration(source, prev.clouds[scale], ICP_CORRESPONDENCE_VOXELS * ICP_VOXELS_M[scale], T)

    def _dense(self, prev, curr, init):
        todo = o3d.t.pipelines.odometry
        criteria = [todo.OdometryConvergenceCriteria(m) for m in HYBRID_ITER]
        try:
            r = todo.rgbd_odometry_multi_scale(
                curr.rgbd,
                prev.rgbd,
                self._K,
                o3d.core.Tensor(np.asarray(init, np.float64)),
                1.0,
                self.max_depth_m,
                criteria,
                todo.Method.Hybrid,
                todo.OdometryLossParams(HYBRID_DEPTH_DIFF, 0.05, 0.1),
            )
        except RuntimeError:
            return np.asarray(init), 0.0, 0.0
        return r.transformation.numpy(), float(r.fitness), float(r.inlier_rmse)

    def _keep_start_where_degenerate(self, prev, curr, T_start, T_icp, result) -> tuple[np.ndarray, int]:
        corr = np.asarray(result.correspondence_set)
        if len(corr) < MIN_CORRESPONDENCES:
            return np.asarray(T_start).copy(), 0
        scale = len(ICP_VOXELS_M) - 1
        source = curr.clouds[scale]
        if len(source.points) > ICP_MAX_SOURCE_POINTS:
            source = source.uniform_down_sample(math.ceil(len(source.points) / ICP_MAX_SOURCE_POINTS))
        p = np.asarray(source.points)[corr[:, 0]] @ T_icp[:3, :3].T + T_icp[:3, 3]
        n = np.asarray(prev.clouds[scale].normals)[corr[:, 1]]
        length = float(np.sqrt(np.mean(np.sum(p**2, axis=1))))
        J = np.hstack([np.cross(p, n) / length, n])
        H = J.T @ J / len(J)
        eigenvalues, V = np.linalg.eigh(H)
        constrained = V[:, eigenvalues >= DEGENERATE_EIGENVALUE]
        delta = T_icp @ np.linalg.inv(T_start)
        rotvec = cv2.Rodrigues(delta[:3, :3])[0].ravel()
        y = np.concatenate([rotvec * length, delta[:3, 3]])
        y = constrained @ (constrained.T @ y)
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(y[:3] / length)[0]
        T[:3, 3] = y[3:]
        return T @ T_start, constrained.shape[1]

    def _hybrid(self, prev, curr, init):
        k = self.intrinsics
        pin = o3d.camera.PinholeCameraIntrinsic(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
        opt = o3d.pipelines.odometry.OdometryOption()
        opt.depth_max = self.max_depth_m
        opt.depth_diff_max = HYBRID_DEPTH_DIFF
        opt.iteration_number_per_pyramid_level = o3d.utility.IntVector(list(HYBRID_ITER))
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            curr.rgbd, prev.rgbd, pin, init, o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), opt
        )
        return np.asarray(T) if ok else init

    def _icp(self, prev: _PreparedFrame, curr: _PreparedFrame, init: np.ndarray, scale: int):
        reg = o3d.pipelines.registration
        source = curr.clouds[scale]
        cap = ICP_MAX_SOURCE_POINTS[scale]
        if len(source.points) > cap:
            source = source.uniform_down_sample(math.ceil(len(source.points) / cap))
        result = reg.registration_icp(
            source,
            prev.clouds[scale],
            ICP_CORRESPONDENCE_VOXELS * ICP_VOXELS_M[scale],
            np.asarray(init, np.float64),
            reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=TUKEY_VOXELS * ICP_VOXELS_M[scale])),
            reg.ICPConvergenceCriteria(max_iteration=ICP_ITERATIONS[scale]),
        )
        if len(result.correspondence_set) < MIN_CORRESPONDENCES:
            result.transformation = np.asarray(init, np.float64)
        return result


def _within(a: np.ndarray, b: np.ndarray, metres: float, degrees: float) -> bool:
    D = np.linalg.inv(a) @ b
    angle = np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))
    return bool(np.linalg.norm(D[:3, 3]) <= metres and angle <= math.radians(degrees))


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    D = np.linalg.inv(a) @ b
    return np.linalg.norm(D[:3, 3]) < 0.02 and np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)) < 0.02


def _yaw_matrix(yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    return T


def chain_relative_poses(T_prev_curr: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """(N, 4, 4) T_cam0_camk from N − 1 relative poses T_cam(k−1)_camk (frame 0 is the identity)."""
    poses = [np.eye(4)]
    for T in T_prev_curr:
        poses.append(poses[-1] @ np.asarray(T, np.float64))
    return np.stack(poses)


def planar_odometry(
    T_cam0_cam: np.ndarray, T_base_camera: np.ndarray, *, max_tilt_deg: float = MAX_TILT_DEG
) -> np.ndarray:
    """(N, 3) T_odom_base (x, y, yaw) of (N, 4, 4) camera poses T_cam0_camk seen through the camera mount.

    T_odom_base(k) = T_base_camera · T_cam0_camk · T_base_camera⁻¹: the odometry frame is the base at frame 0. The
    projection drops the roll and pitch a planar robot cannot have (logged when above `max_tilt_deg`).
    """
    T_base_camera = np.asarray(T_base_camera, np.float64)
    T_odom_base = T_base_camera @ np.asarray(T_cam0_cam, np.float64) @ np.linalg.inv(T_base_camera)
    return planar_from_matrices(T_odom_base, what="RGB-D odometry", max_tilt_deg=max_tilt_deg)


def rgbd_odometry(
    sequence: Sequence, *, max_depth_m: float = MAX_DEPTH_M, show_progress: bool = True
) -> RgbdOdometryResult:
    """RGB-D odometry of every frame of `sequence`, with its intrinsics and camera mount (see the module docstring).

    Frames should lie about a keyframe apart (0.5 m or 15°) or closer; pairs up to about 0.7 m and 25° apart work.
    """
    odometry = RgbdOdometry(sequence.meta.intrinsics, sequence.meta.T_base_camera, max_depth_m=max_depth_m)
    pairs: list[PairOdometry] = []
    prev = None
    frames = range(len(sequence))
    for i in progress(frames, desc="RGB-D odometry", unit="frame") if show_progress else frames:
        frame = sequence[i]
        curr = odometry.prepare(frame.rgb, frame.depth_m)
        if prev is not None:
            pair = odometry.relative_pose(prev, curr, pairs[-1].T_prev_curr if pairs else None)
            pairs.append(pair)
            if pair.fell_back:
                log.debug(
                    "%s frame %d: PnP failed (%d inliers), ICP from %s", sequence, i, pair.pnp_inliers, pair.start
                )
        prev = curr
    T_cam0_cam = chain_relative_poses([p.T_prev_curr for p in pairs])
    poses = planar_odometry(T_cam0_cam, sequence.meta.T_base_camera)
    n_fell_back = sum(p.fell_back for p in pairs)
    if n_fell_back:
        log.info(
            "%s: %d of %d pairs without a PnP guess (ICP from the previous motion or none)",
            sequence,
            n_fell_back,
            len(pairs),
        )
    return RgbdOdometryResult(poses, T_cam0_cam, pairs)
