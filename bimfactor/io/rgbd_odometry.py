"""RGB-D odometry: planar odometry for a recording that has none, from its colour and depth frames alone.

Each pair of consecutive frames gets a 6-DoF relative camera pose: an ORB + `cv2.solvePnPRansac` guess (or, on too
few inliers, the previous motion, turned by `START_TURNS_DEG`, and no motion), Open3D point-to-plane ICP from each
start, then Open3D's RGB-D odometry; along a horizontal direction no surface faces (`FLAT_SHARE`) the prior's
translation is kept. Poses are rounded to `POSE_DECIMALS` after each Open3D step so that a run repeats bit for bit,
chained, carried through the camera mount into the base and projected onto the floor (x, y, yaw). Method, accuracy
and the recommended α: docs/rgbd-odometry.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence as SequenceOf
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
import open3d as o3d
from scipy.optimize import nnls

from bimfactor.errors import InputError
from bimfactor.io.sequence import Sequence
from bimfactor.io.tum import MAX_TILT_DEG, planar_from_matrices
from bimfactor.odometry import odometry_increments
from bimfactor.progress import progress
from bimfactor.types import POSE_DECIMALS, CameraIntrinsics, se2_between, se2_compose, wrap_angle

log = logging.getLogger(__name__)

ORB_FEATURES = 3000  # keypoints per image: 1000 gave too few PnP inliers on slambook's 25° turn
ORB_FAST_THRESHOLD = 12  # OpenCV's default 20 finds few corners in low-contrast images
PNP_REPROJECTION_PX = 3.0  # RANSAC inlier threshold
PNP_MIN_INLIERS = 20  # fewer: no feature guess (12 let wrong guesses through on simulated walls)
PNP_ITERATIONS = 300
PNP_SEED = 0  # OpenCV's RANSAC draws from its global generator: seeded before each call, for repeatable runs
MAX_DEPTH_M = 8.0  # farther depth is left out
ICP_VOXELS_M = (0.10, 0.05)  # coarse-to-fine voxel sizes of the depth clouds
ICP_CORRESPONDENCE_VOXELS = 2.5  # a correspondence lies within this many voxels
ICP_TUKEY_VOXELS = 1.0  # Tukey loss scale, in voxels
ICP_ITERATIONS = (30, 20)
ICP_MAX_SOURCE_POINTS = (1500, 3000)  # the moving cloud is thinned (strided) to this many points per scale
NORMAL_NEIGHBOURS = 20  # points in each normal's plane fit (12 tilted wall normals and the flatness test)
MIN_CORRESPONDENCES = 50  # an ICP with fewer keeps its start
START_TURNS_DEG = (-30.0, -15.0, 15.0, 30.0)  # fall-back starts: the previous motion turned by these
START_MARGIN = 0.05  # a later start must overlap this much more of the cloud than the best so far
GOOD_OVERLAP = 0.9  # a start whose ICP overlaps this much of the cloud ends the search
ICP_MAX_JUMP = (0.75, 25.0)  # metres, degrees: an ICP moving its start further diverged (the start is kept)
DENSE_MAX_JUMP = (0.3, 10.0)  # metres, degrees: the same for the dense step and the fine ICP scale
DENSE_ITERATIONS = (20, 10, 5)  # per image-pyramid level, coarse to fine
DENSE_DEPTH_DIFF_M = 0.07  # depth differences above this are no correspondence in the dense step
MIN_OVERLAP = 0.3  # share of the current cloud within 2.5 fine voxels of the previous one; below: the prior is kept
FLAT_SHARE = 0.06  # a horizontal direction with less of the surface normals' weight is unmeasured
SAME_POSE = (0.02, 1.0)  # metres, degrees: two ICP results this close are one
FRAME_INTERVAL_S = 0.2  # frames closer in time than this to the last one used are skipped (see `odometry_frames`)
# The odometry motion model's α1..α4 measured for this odometry at keyframe spacing on the paper floor's six drives
# (docs/rgbd-odometry.md, "Noise model"); convert reports it for `--set odometry.alpha=…`.
MEASURED_ALPHA = (0.1, 0.002, 0.05, 0.05)


@dataclass(frozen=True)
class PairOdometry:
    """The relative pose of one pair of consecutive frames and how it was found.

    `T_prev_curr` (4, 4) maps the current camera's coordinates into the previous camera's. `start` is where the
    winning depth alignment started: "pnp", "previous" (the previous pair's motion, maybe turned) or "identity".
    `fitness` is the share of the current frame's cloud within 12.5 cm of the previous frame's after alignment (its
    overlap), `inlier_rmse_m` those points' RMS distance. `measured_directions` counts the horizontal directions (0–2)
    the depth measured; the prior's translation is kept along the others.
    """

    T_prev_curr: np.ndarray
    matches: int
    pnp_inliers: int
    start: str
    fitness: float
    inlier_rmse_m: float
    measured_directions: int

    @property
    def fell_back(self) -> bool:
        """True when PnP gave no guess (too few features or inliers): the pose rests on depth and the motion prior."""
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
        """(N − 1,) each pair's overlap after alignment (`PairOdometry.fitness`)."""
        return np.array([p.fitness for p in self.pairs], np.float64)


class _Alignment(NamedTuple):
    """An Open3D registration result as plain values: (4, 4) pose, overlap share, RMS distance, (K, 2) index pairs
    (current cloud, previous cloud)."""

    T: np.ndarray
    fitness: float
    inlier_rmse_m: float
    correspondences: np.ndarray


@dataclass
class PreparedFrame:
    """What a frame contributes to both of its pairs, computed once (`RgbdOdometry.prepare`)."""

    keypoints_px: np.ndarray  # (K, 2) ORB keypoints
    descriptors: np.ndarray | None  # (K, 32) uint8
    keypoints_camera: np.ndarray  # (K, 3) camera-frame points, NaN where the keypoint has no depth
    clouds: list[o3d.geometry.PointCloud]  # one per ICP_VOXELS_M, with normals towards the camera
    rgbd: o3d.geometry.RGBDImage  # intensity and depth (metres, 0: none) for the dense step


class RgbdOdometry:
    """Frame-to-frame RGB-D odometry of one camera: `prepare` each frame once, then `relative_pose` of pairs."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        T_base_camera: np.ndarray,
        *,
        max_depth_m: float = MAX_DEPTH_M,
        nonholonomic: bool = True,
    ) -> None:
        self.intrinsics = intrinsics
        self.nonholonomic = nonholonomic
        self.T_base_camera = np.asarray(T_base_camera, np.float64)
        self.max_depth_m = max_depth_m
        self._pinhole = o3d.camera.PinholeCameraIntrinsic(
            intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        )
        self._dense_option = o3d.pipelines.odometry.OdometryOption(
            o3d.utility.IntVector(list(DENSE_ITERATIONS)), DENSE_DEPTH_DIFF_M, 0.0, max_depth_m
        )
        self._orb = cv2.ORB_create(nfeatures=ORB_FEATURES, fastThreshold=ORB_FAST_THRESHOLD)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)

    def prepare(self, rgb: np.ndarray, depth_m: np.ndarray) -> PreparedFrame:
        """Features and clouds of one frame: (H, W, 3) uint8 RGB, (H, W) depth in metres (NaN or 0: no return)."""
        k = self.intrinsics
        depth = np.asarray(depth_m, np.float64)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(depth) & (depth > 0) & (depth <= self.max_depth_m)
        keypoints, descriptors = self._orb.detectAndCompute(
            cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), None
        )
        px = np.array([kp.pt for kp in keypoints], np.float64).reshape(-1, 2)
        u = np.clip(np.rint(px[:, 0]).astype(np.int64), 0, k.width - 1)
        v = np.clip(np.rint(px[:, 1]).astype(np.int64), 0, k.height - 1)
        keypoints_camera = k.backproject(px[:, 0], px[:, 1], np.where(valid[v, u], depth[v, u], np.nan))

        rows, cols = np.nonzero(valid)
        full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(k.backproject(cols, rows, depth[rows, cols])))
        clouds = []
        for voxel in ICP_VOXELS_M:
            cloud = full.voxel_down_sample(voxel)
            if len(cloud.points) >= MIN_CORRESPONDENCES:  # else the frame has no depth to align (see _icp)
                cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
                cloud.orient_normals_towards_camera_location(np.zeros(3))
            clouds.append(cloud)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb, np.uint8)),
            o3d.geometry.Image(np.where(valid, depth, 0.0).astype(np.float32)),
            depth_scale=1.0,
            depth_trunc=self.max_depth_m,
            convert_rgb_to_intensity=True,
        )
        return PreparedFrame(px, descriptors, keypoints_camera, clouds, rgbd)

    def pnp(self, prev: PreparedFrame, curr: PreparedFrame) -> tuple[np.ndarray | None, int, int]:
        """ORB matches → PnP RANSAC: (T_prev_curr or None when it failed, match count, inlier count)."""
        if prev.descriptors is None or curr.descriptors is None:
            return None, 0, 0
        matches = self._matcher.match(prev.descriptors, curr.descriptors)
        i_prev = np.array([m.queryIdx for m in matches], np.int64)
        i_curr = np.array([m.trainIdx for m in matches], np.int64)
        has_depth = np.isfinite(prev.keypoints_camera[i_prev, 2])
        i_prev, i_curr = i_prev[has_depth], i_curr[has_depth]
        if len(i_prev) < PNP_MIN_INLIERS:
            return None, len(matches), 0
        cv2.setRNGSeed(PNP_SEED)
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
        self, prev: PreparedFrame, curr: PreparedFrame, previous_motion: np.ndarray | None = None
    ) -> PairOdometry:
        """T_prev_curr of two prepared frames (steps 1–5 of the module docstring); `previous_motion` (4, 4) is the
        previous pair's T_prev_curr, None for the first pair."""
        T_pnp, n_matches, n_inliers = self.pnp(prev, curr)
        starts = [("pnp", T_pnp)] if T_pnp is not None else self._fallback_starts(previous_motion)

        # Depth alignment from each start until one overlaps well; the first best (by a margin) wins. Candidates are
        # compared with the prior's translation along the directions depth cannot measure (step 5): there a smaller
        # motion overlaps more without being any more right.
        prior_name, prior = starts[0]
        best: tuple[str, np.ndarray, float] | None = None
        seen: list[np.ndarray] = []
        for name, T_start in starts:
            T = self._icp(prev, curr, T_start, 0).T
            if any(_pose_distance(T, other) < 1.0 for other in seen):
                continue  # converged where an earlier start did
            seen.append(T)
            fine = self._icp(prev, curr, T, 1)
            T = fine.T if _pose_distance(fine.T, T_start, ICP_MAX_JUMP) <= 1.0 else T_start
            overlap = self._evaluate(prev, curr, self._keep_prior_where_flat(prev, curr, prior, T)[0]).fitness
            if best is None or overlap > best[2] + START_MARGIN:
                best = (name, T, overlap)
            if best[2] >= GOOD_OVERLAP:
                break
        assert best is not None
        name, T, _ = best

        # Photometric + depth refinement, then what depth could not measure is taken from the prior.
        T_dense = self._dense(prev, curr, T)
        if _pose_distance(T_dense, T, DENSE_MAX_JUMP) <= 1.0:
            T = T_dense
        T, measured = self._keep_prior_where_flat(prev, curr, prior, T)
        check = self._evaluate(prev, curr, T)
        if check.fitness < MIN_OVERLAP:  # nothing measured: the prior itself
            return PairOdometry(
                np.array(prior), n_matches, n_inliers, prior_name, check.fitness, check.inlier_rmse_m, 0
            )
        return PairOdometry(T, n_matches, n_inliers, name, check.fitness, check.inlier_rmse_m, measured)

    def _fallback_starts(self, previous_motion: np.ndarray | None) -> list[tuple[str, np.ndarray]]:
        """The previous motion (or none), it turned by each of START_TURNS_DEG about the base's z, and no motion."""
        name, base = ("previous", previous_motion) if previous_motion is not None else ("identity", np.eye(4))
        starts = [(name, np.asarray(base, np.float64))]
        T_camera_base = np.linalg.inv(self.T_base_camera)
        for turn_deg in START_TURNS_DEG:
            turn = T_camera_base @ _yaw_matrix(math.radians(turn_deg)) @ self.T_base_camera
            starts.append((name, turn @ starts[0][1]))
        if name != "identity":
            starts.append(("identity", np.eye(4)))
        return starts

    def _source(self, curr: PreparedFrame, scale: int) -> o3d.geometry.PointCloud:
        cloud = curr.clouds[scale]
        cap = ICP_MAX_SOURCE_POINTS[scale]
        return cloud.uniform_down_sample(math.ceil(len(cloud.points) / cap)) if len(cloud.points) > cap else cloud

    def _icp(self, prev: PreparedFrame, curr: PreparedFrame, init: np.ndarray, scale: int) -> _Alignment:
        """Point-to-plane ICP of the current cloud onto the previous one at one scale; with too few correspondences
        (no overlap, no depth) the pose stays at `init`."""
        reg = o3d.pipelines.registration
        voxel = ICP_VOXELS_M[scale]
        init = np.asarray(init, np.float64)
        source, target = self._source(curr, scale), prev.clouds[scale]
        if len(source.points) < MIN_CORRESPONDENCES or len(target.points) < MIN_CORRESPONDENCES:
            return _Alignment(init, 0.0, 0.0, np.zeros((0, 2), np.int64))
        result = reg.registration_icp(
            source,
            target,
            ICP_CORRESPONDENCE_VOXELS * voxel,
            init,
            reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=ICP_TUKEY_VOXELS * voxel)),
            reg.ICPConvergenceCriteria(max_iteration=ICP_ITERATIONS[scale]),
        )
        correspondences = np.asarray(result.correspondence_set, np.int64).reshape(-1, 2)
        T = np.round(result.transformation, POSE_DECIMALS) if len(correspondences) >= MIN_CORRESPONDENCES else init
        return _Alignment(T, float(result.fitness), float(result.inlier_rmse), correspondences)

    def _evaluate(self, prev: PreparedFrame, curr: PreparedFrame, T: np.ndarray) -> _Alignment:
        """Overlap and correspondences of the fine clouds at pose T (no alignment)."""
        scale = len(ICP_VOXELS_M) - 1
        source, target = self._source(curr, scale), prev.clouds[scale]
        if len(source.points) < MIN_CORRESPONDENCES or len(target.points) < MIN_CORRESPONDENCES:
            return _Alignment(np.asarray(T), 0.0, 0.0, np.zeros((0, 2), np.int64))
        result = o3d.pipelines.registration.evaluate_registration(
            source, target, ICP_CORRESPONDENCE_VOXELS * ICP_VOXELS_M[scale], T
        )
        correspondences = np.asarray(result.correspondence_set, np.int64).reshape(-1, 2)
        return _Alignment(np.asarray(T), float(result.fitness), float(result.inlier_rmse), correspondences)

    def _dense(self, prev: PreparedFrame, curr: PreparedFrame, init: np.ndarray) -> np.ndarray:
        """Open3D's RGB-D odometry (hybrid photometric + depth term, image pyramid) from `init`; `init` itself when it
        does not converge."""
        odometry = o3d.pipelines.odometry
        ok, T, _ = odometry.compute_rgbd_odometry(
            curr.rgbd,
            prev.rgbd,
            self._pinhole,
            np.asarray(init, np.float64),
            odometry.RGBDOdometryJacobianFromHybridTerm(),
            self._dense_option,
        )
        return np.round(T, POSE_DECIMALS) if ok else np.asarray(init)

    def _keep_prior_where_flat(
        self, prev: PreparedFrame, curr: PreparedFrame, T_prior: np.ndarray, T: np.ndarray
    ) -> tuple[np.ndarray, int]:
        """T with its base-frame translation replaced by the prior's along the horizontal directions that too few
        surface normals of the overlap face (their share of the normals' horizontal scatter below FLAT_SHARE), and the
        count of the others (0–2). With none measured the prior's rotation is kept too. A wheeled base's prior moves
        sideways only as its arc does (`nonholonomic`)."""
        correspondences = self._evaluate(prev, curr, T).correspondences
        if len(correspondences) < MIN_CORRESPONDENCES:
            return np.array(T_prior), 0
        normals_base = np.asarray(prev.clouds[-1].normals)[correspondences[:, 1]] @ self.T_base_camera[:3, :3].T
        horizontal = normals_base[:, :2]
        share, directions = np.linalg.eigh(horizontal.T @ horizontal / len(horizontal))
        flat = directions[:, share < FLAT_SHARE]
        if flat.shape[1] == 0:
            return np.asarray(T), 2
        T_camera_base = np.linalg.inv(self.T_base_camera)
        T_base = self.T_base_camera @ T @ T_camera_base
        T_base_prior = self.T_base_camera @ T_prior @ T_camera_base
        if flat.shape[1] == 2:
            T_base[:3, :3] = T_base_prior[:3, :3]
        prior_xy = T_base_prior[:2, 3].copy()
        if self.nonholonomic:  # a wheeled base moves along an arc: sideways by forward · tan(Δyaw / 2)
            prior_xy[1] = prior_xy[0] * math.tan(math.atan2(T_base[1, 0], T_base[0, 0]) / 2)
        T_base[:2, 3] += flat @ (flat.T @ (prior_xy - T_base[:2, 3]))
        return T_camera_base @ T_base @ self.T_base_camera, 2 - flat.shape[1]


def _pose_distance(a: np.ndarray, b: np.ndarray, scale: tuple[float, float] = SAME_POSE) -> float:
    """How far apart two (4, 4) poses are in units of `scale` (metres, degrees): the larger of the translation and
    rotation ratios, so ≤ 1 means within both limits."""
    D = np.linalg.inv(a) @ b
    angle_deg = math.degrees(math.acos(float(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0))))
    return max(float(np.linalg.norm(D[:3, 3])) / scale[0], angle_deg / scale[1])


def _yaw_matrix(yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    return T


# ------------------------------------------------------------------------------------------ sequences


def chain_relative_poses(T_prev_curr: SequenceOf[np.ndarray] | np.ndarray) -> np.ndarray:
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


def odometry_frames(timestamps: np.ndarray, min_interval_s: float = FRAME_INTERVAL_S) -> np.ndarray:
    """Indices of the frames the odometry runs on: the first, then each frame at least `min_interval_s` after the last
    one taken. A 30 Hz recording is processed at 5 Hz: pairs 0.2 s apart move a few tens of centimetres at walking
    speed, well within what a pair can take (0.7 m, 30°), and fewer pairs drift less and cost a sixth of the time."""
    timestamps = np.asarray(timestamps, np.float64)
    keep, last = [], -math.inf
    for i, t in enumerate(timestamps):
        if t - last >= min_interval_s - 1e-3:  # stamps near 1.7e9 s are good to 1e-7 s only
            keep.append(i)
            last = t
    return np.asarray(keep, np.int64)


def rgbd_odometry(
    sequence: Sequence, *, max_depth_m: float = MAX_DEPTH_M, nonholonomic: bool = True, show_progress: bool = True
) -> RgbdOdometryResult:
    """RGB-D odometry of every frame of `sequence`, with its intrinsics and camera mount (module docstring); made for
    keyframes up to about 0.7 m and 30° apart. `nonholonomic=False` for a handheld camera. Give the sequence its
    odometry with `sequence.with_odometry(result.odom_poses)`."""
    odometry = RgbdOdometry(
        sequence.meta.intrinsics, sequence.meta.T_base_camera, max_depth_m=max_depth_m, nonholonomic=nonholonomic
    )
    pairs: list[PairOdometry] = []
    prev = None
    rows = range(len(sequence))
    for i in progress(rows, desc="RGB-D odometry", unit="frame") if show_progress else rows:
        frame = sequence[i]
        curr = odometry.prepare(frame.rgb, frame.depth_m)
        if prev is not None:
            pairs.append(odometry.relative_pose(prev, curr, pairs[-1].T_prev_curr if pairs else None))
        prev = curr
    T_cam0_cam = chain_relative_poses([p.T_prev_curr for p in pairs])
    result = RgbdOdometryResult(planar_odometry(T_cam0_cam, sequence.meta.T_base_camera), T_cam0_cam, pairs)
    log.info(
        "%s: RGB-D odometry of %d frames; %d of %d pairs without a PnP guess, %d with low overlap",
        sequence.meta.name,
        len(sequence),
        int(result.fell_back.sum()),
        len(pairs),
        int((result.fitness < MIN_OVERLAP).sum()),
    )
    return result


# ------------------------------------------------------------------------------------------ noise model


@dataclass(frozen=True)
class OdometryNoise:
    """Per-step error of planar odometry against ground truth, and the odometry motion model's α that it implies.

    `trans_err_ratio`: RMS error of the step length over its true length (steps ≥ `MIN_STEP_M`); `yaw_err_deg`: RMS
    heading error per step; `yaw_err_deg_per_m`: RMS heading error per metre over straight steps (turn < 5°);
    `yaw_err_per_turn`: RMS heading error over the turn's size (turns ≥ 5°). `alpha` (4,) is α1..α4 (Thrun et al.,
    Table 5.6) fitted to the squared errors by non-negative least squares; `drift_pct` the final position error as a
    share of the path length, per sequence.
    """

    steps: int
    trans_err_ratio: float
    yaw_err_deg: float
    yaw_err_deg_per_m: float
    yaw_err_per_turn: float
    alpha: np.ndarray
    drift_pct: list[float]


MIN_STEP_M = 0.1  # shorter steps are left out of the per-length ratios
STRAIGHT_TURN_RAD = math.radians(5.0)


def odometry_noise(odometry: SequenceOf[np.ndarray], ground_truth: SequenceOf[np.ndarray]) -> OdometryNoise:
    """Compare (N, 3) odometry poses with (N, 3) ground-truth poses (x, y, yaw), one pair of arrays per sequence.

    Per step, the increments (δrot1, δtrans, δrot2) of both (`bimfactor.odometry.odometry_increments`) are compared:
    heading error e_yaw = Δ(δrot1 + δrot2), length error e_trans = Δδtrans. The model's variances, with the true
    increments, are var(e_yaw) = α1 (δrot1² + δrot2²) + 2 α2 δtrans² and var(e_trans) = α3 δtrans² + α4 (δrot1² +
    δrot2²); α comes from a non-negative least-squares fit of the squared errors to these (so failures count fully).
    """
    rows, drift = [], []
    for est, gt in zip(odometry, ground_truth, strict=True):
        est, gt = np.asarray(est, np.float64), np.asarray(gt, np.float64)
        inc_est, inc_gt = odometry_increments(est), odometry_increments(gt)
        e_yaw = wrap_angle(np.diff(est[:, 2]) - np.diff(gt[:, 2]))
        rows.append(np.column_stack([inc_gt, e_yaw, inc_est[:, 1] - inc_gt[:, 1]]))
        path = float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum())
        aligned = _align_start(est, gt[0])
        drift.append(100.0 * float(np.hypot(*(aligned[-1, :2] - gt[-1, :2]))) / max(path, 1e-9))
    rot1, trans, rot2, e_yaw, e_trans = np.concatenate(rows).T
    turn_sq = rot1**2 + rot2**2
    a12, _ = nnls(np.column_stack([turn_sq, 2 * trans**2]), e_yaw**2)
    a34, _ = nnls(np.column_stack([trans**2, turn_sq]), e_trans**2)
    moving = np.abs(trans) >= MIN_STEP_M
    turn = np.abs(wrap_angle(rot1 + rot2))
    straight = moving & (turn < STRAIGHT_TURN_RAD)
    turning = turn >= STRAIGHT_TURN_RAD
    return OdometryNoise(
        steps=len(trans),
        trans_err_ratio=_rms(e_trans[moving] / np.abs(trans[moving])),
        yaw_err_deg=math.degrees(_rms(e_yaw)),
        yaw_err_deg_per_m=math.degrees(_rms(e_yaw[straight] / np.abs(trans[straight]))),
        yaw_err_per_turn=_rms(e_yaw[turning] / turn[turning]),
        alpha=np.array([a12[0], a12[1], a34[0], a34[1]]),
        drift_pct=drift,
    )


def benchmark_rgbd_odometry(
    sequences: SequenceOf[Sequence], *, max_depth_m: float = MAX_DEPTH_M, show_progress: bool = False
) -> tuple[OdometryNoise, list[RgbdOdometryResult]]:
    """RGB-D odometry of each sequence (with ground truth on every frame, e.g. simulated) and its `odometry_noise`."""
    results, truths = [], []
    for sequence in sequences:
        gt = sequence.ground_truth()
        if gt is None or np.isnan(gt).any():
            raise InputError(f"{sequence.meta.name}: the benchmark needs ground truth on every frame")
        results.append(rgbd_odometry(sequence, max_depth_m=max_depth_m, show_progress=show_progress))
        truths.append(gt)
    return odometry_noise([r.odom_poses for r in results], truths), results


def _align_start(odometry: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(N, 3) odometry poses moved rigidly so that the first lies on `start` (3,)."""
    return se2_compose(start, se2_between(odometry[0], odometry))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else float("nan")
