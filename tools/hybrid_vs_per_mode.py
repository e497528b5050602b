"""Experiment: a GTSAM hybrid factor graph (one discrete mode variable) against one pose graph per mode.

On the back end's synthetic loop, two hypotheses of where the robot started: the truth and the truth rotated by
60° about the loop centre (a symmetric building's twin place). Each hypothesis has its own landmark matches
(nearest BIM landmark where that hypothesis puts each observation).

1. per-mode graphs: `MultiHypothesisBackend` (one ISAM2 graph per mode, modes weighed by their residuals);
2. hybrid: one `HybridNonlinearFactorGraph` with a discrete mode m ∈ {0, 1}, the poses X(t) shared by both modes,
   the prior on X(0) and every landmark factor a `HybridNonlinearFactor` with one component per mode (an
   unmatched observation costs the constant `outlier_chi2`); Gauss–Newton on the hybrid graph (linearize,
   eliminate, MPE of the hybrid Bayes net, retract), started from one mode's dead reckoning.

The hybrid graph has one linearization point for both modes, which lie metres apart: started from the wrong
mode's poses it keeps the wrong mode, whatever the data say; the per-mode graphs linearize each mode at its own
estimate and pick the true mode every time. Run from the repository root:

    .venv/bin/python tools/hybrid_vs_per_mode.py
"""

from __future__ import annotations

import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from bimfactor.backend.factors import from_pose2, odometry_factor, pose_prior_factor
from bimfactor.backend.posegraph import MultiHypothesisBackend
from bimfactor.backend.synthetic import LoopScenario, loop_scenario, nearest_landmark_associator
from bimfactor.config import BackendConfig, OdometryConfig, load_config
from bimfactor.localization.measurements.semantic import polar_coordinates
from bimfactor.localization.modes import Mode
from bimfactor.types import se2_compose, wrap_angle

CLUSTER_COV = np.diag([0.2, 0.2, np.deg2rad(5.0)]) ** 2
TWIN_ROTATION = np.pi / 3
MODE_KEY = (gtsam.symbol("m", 0), 2)
GAUSS_NEWTON_ITERATIONS = 10


def rotate_about_origin(pose: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * pose[0] - s * pose[1], s * pose[0] + c * pose[1], wrap_angle(pose[2] + angle)])


def fixed_point_bearing_range(
    t: int, bearing_rad: float, range_m: float, point_xy: np.ndarray | None, cfg: BackendConfig
) -> gtsam.CustomFactor:
    """Bearing-range from X(t) to a fixed BIM point (so every mode's component has the same keys);
    `point_xy` None: the observation is unmatched in this mode and costs `outlier_chi2`."""
    sigmas = np.array([np.deg2rad(cfg.bearing_sigma_deg), cfg.range_sigma_m])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        pose = from_pose2(values.atPose2(this.keys()[0]))
        if point_xy is None:
            if jacobians is not None:
                jacobians[0] = np.zeros((2, 3))
            return np.sqrt(cfg.outlier_chi2 / 2) * sigmas
        d, alpha = polar_coordinates(pose, point_xy)
        if jacobians is not None:
            dx, dy = point_xy[0] - pose[0], point_xy[1] - pose[1]
            c, s = np.cos(pose[2]), np.sin(pose[2])
            bx, by = c * dx + s * dy, -s * dx + c * dy  # the point in the body frame
            r2 = bx * bx + by * by
            r = np.sqrt(r2)
            jacobians[0] = np.array([[by / r2, -bx / r2, -1.0], [-bx / r, -by / r, 0.0]])  # body tangent (dx, dy, dθ)
        return np.array([wrap_angle(alpha - bearing_rad), d - range_m])

    return gtsam.CustomFactor(gtsam.noiseModel.Diagonal.Sigmas(sigmas), [X(t)], error)


def per_mode_graphs(sc: LoopScenario, cfg: BackendConfig, odometry: OdometryConfig) -> tuple[int, np.ndarray, float]:
    """Most probable mode id (0: the truth), its last pose, and the milliseconds of all steps."""
    backend = MultiHypothesisBackend(sc.landmark_xy, cfg, odometry)
    started = time.perf_counter()
    for t in range(len(sc.true_poses)):
        clusters = [
            Mode(sc.true_poses[t], CLUSTER_COV, 0.5),
            Mode(rotate_about_origin(sc.true_poses[t], TWIN_ROTATION), CLUSTER_COV, 0.5),
        ]
        associate = nearest_landmark_associator(sc.landmark_xy, sc.observations[t])
        step = backend.step(clusters, None if t == 0 else sc.increments[t - 1], sc.observations[t], associate)
        assert step is not None
    return step.best.mode_id, step.best.pose, (time.perf_counter() - started) * 1e3


def hybrid_graph(
    sc: LoopScenario, cfg: BackendConfig, odometry: OdometryConfig, start_mode: int
) -> tuple[int, np.ndarray, float]:
    """MPE mode, last pose and milliseconds of Gauss–Newton on the hybrid graph started at `start_mode`'s poses."""
    T = len(sc.true_poses)
    firsts = [sc.true_poses[0], rotate_about_origin(sc.true_poses[0], TWIN_ROTATION)]
    dead_reckoned = []
    for first in firsts:
        poses = [first]
        for increment in sc.increments:
            poses.append(se2_compose(poses[-1], increment))
        dead_reckoned.append(np.array(poses))
    matches = [
        [
            dict(nearest_landmark_associator(sc.landmark_xy, sc.observations[t])(dead_reckoned[m][t], 0))
            for t in range(T)
        ]
        for m in range(2)
    ]
    graph = gtsam.HybridNonlinearFactorGraph()
    graph.push_back(gtsam.HybridNonlinearFactor(MODE_KEY, [pose_prior_factor(0, f, CLUSTER_COV) for f in firsts]))
    for t in range(T):
        if t:
            graph.push_back(odometry_factor(t, sc.increments[t - 1], cfg, odometry))
        obs = sc.observations[t]
        for k in range(len(obs)):
            points = [sc.landmark_xy[matches[m][t][k]] if k in matches[m][t] else None for m in range(2)]
            components = [fixed_point_bearing_range(t, obs.bearing_rad[k], obs.range_m[k], p, cfg) for p in points]
            graph.push_back(gtsam.HybridNonlinearFactor(MODE_KEY, components))
    values = gtsam.Values()
    for t in range(T):
        values.insert(X(t), gtsam.Pose2(*dead_reckoned[start_mode][t]))
    started = time.perf_counter()
    mode = start_mode
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        solution = graph.linearize(values).eliminateSequential().optimize()
        mode = solution.atDiscrete(MODE_KEY[0])
        values = values.retract(solution.continuous())
    return int(mode), from_pose2(values.atPose2(X(T - 1))), (time.perf_counter() - started) * 1e3


def main() -> None:
    # The sensor of the back end's tests: σ_r 15 cm, σ_b 3°, BIM σ 10 cm.
    default = load_config()
    cfg = default.backend.model_copy(update={"range_sigma_m": 0.15, "bearing_sigma_deg": 3.0, "landmark_sigma_m": 0.1})
    odometry = default.odometry
    for seed in range(3):
        sc = loop_scenario(np.random.default_rng(seed), cfg, odometry)
        truth = sc.true_poses[-1, :2]
        best, pose, ms = per_mode_graphs(sc, cfg, odometry)
        print(f"seed {seed}  per-mode graphs: mode {best}, error {np.linalg.norm(pose[:2] - truth):.3f} m, {ms:.0f} ms")
        for start in (0, 1):
            mode, pose, ms = hybrid_graph(sc, cfg, odometry, start)
            print(
                f"        hybrid from mode {start}'s poses: MPE mode {mode}, "
                f"error {np.linalg.norm(pose[:2] - truth):.3f} m, {ms:.0f} ms"
            )


if __name__ == "__main__":
    main()
