"""One GTSAM pose graph per particle-filter mode, with semantic-landmark factors to matched BIM objects.

Per mode k (a `ModeGraph`), keyed by keyframe index i and BIM object id j:
1. a prior on the mode's first pose X(i0) from its cluster mean and covariance (σ floored);
2. BetweenFactorPose2 X(i−1) → X(i) per odometry increment;
3. per matched observation a robust BearingRangeFactor2D X(i) → L(j), and once per object a tight PriorFactorPoint2
   holding L(j) at its BIM position (`landmark_sigma_m`); door-plate readings likewise to the plate's landmark;
4. optionally PriorFactorPose2s: the scan matched against the BIM's walls (`scan_factors`) and a fine registrar's
   result (`add_pose_factor`).
Online, ISAM2 takes one update per keyframe; a mode whose update is indeterminate, or whose scan matched beyond the
matcher's first window, restarts its graph. Mode probability (`MultiHypothesisBackend.step`), with w_k the mode's
particle-weight share and C_k = Σ_j min(χ²_kj, `outlier_chi2`) over the step's measurements:

    p_k = w_k · exp(−C_k / (2τ)) / Σ_m w_m · exp(−C_m / (2τ)).

Offline, `batch_refine` builds the same factors for a whole trajectory and optimises with Levenberg–Marquardt.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from scipy.optimize import linear_sum_assignment

from bimfactor.backend.factors import (
    Association,
    L,
    Landmarks,
    X,
    bearing_range_noise,
    covariance_body_to_world,
    from_pose2,
    information_pose_factor,
    landmark_factors,
    landmark_prior_factor,
    odometry_factor,
    pose_prior_factor,
)
from bimfactor.config import BackendConfig, OdometryConfig
from bimfactor.localization.measurements.semantic import SemanticLikelihood, polar_coordinates
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.modes import Mode, ModeTracker, TrackedMode
from bimfactor.types import Observations, se2_compose, se2_inverse, wrap_angle

log = logging.getLogger(__name__)

# Nearer than this, a landmark's bearing from a pose is undefined for the marginals (a node is observed from beyond
# the camera's minimum range, 0.3 m; a 10° bearing σ at 0.2 m is 3.5 cm sideways).
DEGENERATE_RANGE_M = 0.2

AssociateFn = Callable[[np.ndarray, int], list[tuple[int, int]]]
"""(3,) pose, storey → (observation index, BIM object id) pairs for the current step's observations."""
PoseFactor = tuple[int, np.ndarray, np.ndarray]
"""A pose factor on X(i): keyframe index, (3,) pose, (3, 3) body-frame information."""
PoseFactorFn = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray] | None]
"""(3,) predicted pose, storey → a measured (3,) pose with (3, 3) body-frame information, or None (e.g. the current
keyframe's scan matched against the BIM from that pose; `backend.scan_factor`)."""


def floored_covariance(covariance: np.ndarray, cfg: BackendConfig) -> np.ndarray:
    """(3, 3) covariance with at least the configured prior floor's spread in every direction of (x, y, yaw): its
    eigenvalues in units of the floor's σ (`prior_min_sigma_m`, `prior_min_sigma_deg`) raised to 1, so a cluster lying
    on a line in x–yaw gets a prior GTSAM does not find indeterminate."""
    cov = 0.5 * (np.asarray(covariance, np.float64) + np.asarray(covariance, np.float64).T)
    sigma = np.array([cfg.prior_min_sigma_m, cfg.prior_min_sigma_m, np.deg2rad(cfg.prior_min_sigma_deg)])
    values, vectors = np.linalg.eigh(cov / np.outer(sigma, sigma))
    return (vectors * np.maximum(values, 1.0)) @ vectors.T * np.outer(sigma, sigma)


def observation_cost(
    pose: np.ndarray,
    landmark_xy: dict[int, np.ndarray],
    observations: Observations,
    association: Association,
    cfg: BackendConfig,
) -> float:
    """C = Σ_j min(χ²_j, c_out) over the step's measurements (nodes and text readings); unmatched ones cost c_out
    (see module docstring)."""
    ranges, bearings = observations.measurements()
    cost = cfg.outlier_chi2 * (len(ranges) - len(association))
    if not association:
        return float(cost)
    obs_idx = np.array([k for k, _ in association])
    points = np.array([landmark_xy[j] for _, j in association])
    d, alpha = polar_coordinates(pose, points)
    db = wrap_angle(bearings[obs_idx] - alpha) / np.deg2rad(cfg.bearing_sigma_deg)
    dr = (ranges[obs_idx] - d) / cfg.range_sigma_m
    return float(cost + np.minimum(db**2 + dr**2, cfg.outlier_chi2).sum())


def semantic_associator(
    likelihood: SemanticLikelihood, plates: PlateLikelihood, observations: Observations, min_score: float = 0.05
) -> AssociateFn:
    """An `AssociateFn` from the S-MCL score: the Hungarian assignment maximising φ at a pose (pairs scoring at most
    `min_score` left unmatched), then each door-plate reading to the plate it fits best there (measurement K + r,
    landmark `first_landmark_id` + p)."""
    K = len(observations)

    def associate(pose: np.ndarray, storey: int) -> list[tuple[int, int]]:
        read = [(K + r, plates.first_landmark_id + p) for r, p in plates.associate(pose, storey, observations.texts)]
        phi, ids = likelihood.pair_scores(np.asarray(pose, np.float64)[None], np.array([storey]), observations)
        if phi.shape[2] == 0:
            return read
        rows, cols = linear_sum_assignment(phi[0], maximize=True)
        seen = [
            (int(k), int(ids[0, c]))
            for k, c in zip(rows, cols, strict=True)
            if phi[0, k, c] > min_score and ids[0, c] >= 0
        ]
        return seen + read

    return associate


class ModeGraph:
    """The ISAM2 pose graph of one mode; `landmarks` are the BIM objects (an (N, 2) array: points), row = id;
    `odometry` the robot's odometry noise, which weighs the odometry factors."""

    def __init__(
        self,
        mode_id: int,
        first_index: int,
        pose: np.ndarray,
        covariance_world: np.ndarray,
        landmarks: Landmarks | np.ndarray,
        cfg: BackendConfig,
        odometry: OdometryConfig,
        storey: int = 0,
    ) -> None:
        self.mode_id = mode_id
        self.storey = storey
        self.cfg = cfg
        self.odometry = odometry
        self.landmarks = Landmarks.of(landmarks)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(cfg.relinearize_threshold)
        params.relinearizeSkip = cfg.relinearize_skip
        self.isam = gtsam.ISAM2(params)
        self.noise = bearing_range_noise(cfg)
        self.first_index = first_index
        self.last_index: int | None = None
        self.pose = np.asarray(pose, np.float64).copy()
        self.covariance = floored_covariance(covariance_world, cfg)
        self.prior_pose, self.prior_covariance = self.pose.copy(), self.covariance.copy()
        self.poses: dict[int, np.ndarray] = {}
        self.associations: dict[int, list[tuple[int, int]]] = {}
        self.pose_factors: list[PoseFactor] = []
        self.scan_factors: list[PoseFactor] = []
        self._landmarks: set[int] = set()
        self._landmark_factor_indices: dict[int, list[int]] = {}
        self._pending = gtsam.NonlinearFactorGraph()
        self._pending.add(pose_prior_factor(first_index, self.pose, self.covariance))

    # -------------------------------------------------------------------------------- online

    def predict(self, increment: np.ndarray | None) -> np.ndarray:
        """(3,) the current estimate moved by a (3,) robot-frame odometry increment (None: not moved)."""
        return self.pose.copy() if increment is None else se2_compose(self.pose, np.asarray(increment, np.float64))

    def add_keyframe(
        self,
        i: int,
        observations: Observations,
        association: Association,
        increment: np.ndarray | None = None,
        odom_covariance: np.ndarray | None = None,
    ) -> None:
        """Add X(i) (by the increment from X(i−1), or the prior at the first keyframe) and its landmark factors."""
        values = gtsam.Values()
        if self.last_index is None:
            if i != self.first_index:
                raise ValueError(f"mode {self.mode_id}: first keyframe is {self.first_index}, got {i}")
            guess = self.pose
        else:
            if increment is None or i != self.last_index + 1:
                raise ValueError(f"mode {self.mode_id}: keyframe {i} needs an increment from {self.last_index}")
            self._pending.add(odometry_factor(i, increment, self.cfg, self.odometry, odom_covariance))
            guess = self.predict(increment)
        values.insert(X(i), gtsam.Pose2(*guess))
        graph, first_landmark = self._pending, self._pending.size()
        self._pending = gtsam.NonlinearFactorGraph()
        self._add_landmarks(graph, values, i, observations, association)
        result = self.isam.update(graph, values)
        new_indices = list(result.getNewFactorsIndices())
        self._landmark_factor_indices[i] = new_indices[first_landmark : first_landmark + len(association)]
        self.associations[i] = list(association)
        self.last_index = i
        self._refresh()

    def reassociate(self, observations: Observations, associate_fn: AssociateFn, associated_at: np.ndarray) -> bool:
        """Re-run `associate_fn` at the new estimate if it moved past the thresholds from `associated_at`.

        When the matches change, the latest keyframe's landmark factors are swapped in one ISAM2 update; returns
        whether they were.
        """
        moved_m = float(np.hypot(*(self.pose[:2] - associated_at[:2])))
        turned = abs(float(wrap_angle(self.pose[2] - associated_at[2])))
        if moved_m < self.cfg.reassociate_distance_m and turned < np.deg2rad(self.cfg.reassociate_yaw_deg):
            return False
        i = self.last_index
        association = list(associate_fn(self.pose.copy(), self.storey))
        if i is None or set(association) == set(self.associations[i]):
            return False
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        self._add_landmarks(graph, values, i, observations, association)
        result = self.isam.update(graph, values, self._landmark_factor_indices[i])
        self._landmark_factor_indices[i] = list(result.getNewFactorsIndices())[: len(association)]
        self.associations[i] = association
        self._refresh()
        log.debug("mode %d keyframe %d re-associated: %d matches", self.mode_id, i, len(association))
        return True

    def add_pose_factor(self, i: int, pose: np.ndarray, information: np.ndarray, scan: bool = False) -> None:
        """A PriorFactorPose2 on X(i) at a (3,) pose with (3, 3) body-frame information: a fine registrar's result,
        or with `scan` the keyframe's scan match.

        Applied now (one ISAM2 update) when X(i) is in the graph, else with keyframe i; kept in `pose_factors` (or
        `scan_factors`) for the offline refinement.
        """
        factor = information_pose_factor(i, pose, information)
        kept = self.scan_factors if scan else self.pose_factors
        kept.append((i, np.asarray(pose, np.float64).copy(), np.asarray(information, np.float64).copy()))
        if i in self.poses:
            graph = gtsam.NonlinearFactorGraph()
            graph.add(factor)
            self.isam.update(graph, gtsam.Values())
            self._refresh()
        else:
            self._pending.add(factor)

    # -------------------------------------------------------------------------------- outputs

    def cost(self, observations: Observations, association: Association) -> float:
        """C_k of the latest keyframe at the current estimates (see `observation_cost`)."""
        landmarks = {j: self.landmark_estimate(j) for _, j in association}
        return observation_cost(self.pose, landmarks, observations, association, self.cfg)

    def landmark_estimate(self, object_id: int) -> np.ndarray:
        """(2,) the current estimate of L(object_id)."""
        return np.asarray(self.isam.calculateEstimatePoint2(L(object_id)), np.float64).reshape(2)

    def trajectory(self) -> np.ndarray:
        """(n, 3) smoothed poses of all keyframes of this mode, in keyframe order."""
        estimate = self.isam.calculateEstimate()
        return np.array([from_pose2(estimate.atPose2(X(i))) for i in sorted(self.poses)])

    def history(self, probability: float) -> ModeHistory:
        """What this mode's graph holds, as plain data: birth prior, smoothed poses, matches per keyframe, pose
        factors."""
        return ModeHistory(
            self.mode_id,
            self.storey,
            float(probability),
            self.first_index,
            self.prior_pose.copy(),
            self.prior_covariance.copy(),
            self.trajectory(),
            [list(self.associations[i]) for i in sorted(self.poses)],
            list(self.pose_factors),
            list(self.scan_factors),
        )

    # -------------------------------------------------------------------------------- helpers

    def _add_landmarks(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        i: int,
        observations: Observations,
        association: Association,
    ) -> None:
        """Bearing-range factors first (their indices are recorded), then priors + values of first-seen landmarks."""
        for factor in landmark_factors(i, observations, association, self.noise):
            graph.add(factor)
        for _, j in association:
            j = int(j)
            if j not in self._landmarks:
                self._landmarks.add(j)
                graph.add(landmark_prior_factor(j, self.landmarks, self.cfg))
                values.insert(L(j), self.landmarks.xy[j].copy())

    def _refresh(self) -> None:
        i = self.last_index
        self.pose = from_pose2(self.isam.calculateEstimatePose2(X(i)))
        self.poses[i] = self.pose
        self.covariance = covariance_body_to_world(self.isam.marginalCovariance(X(i)), float(self.pose[2]))


# ------------------------------------------------------------------------------------------ all modes


@dataclass
class ModeEstimate:
    """One mode after a step: (3,) pose, (3, 3) world-frame covariance, probability and its two ingredients, and
    the step's matches (measurement k, landmark id): `Landmarks.from_prior`'s rows, objects then door plates."""

    mode_id: int
    pose: np.ndarray
    covariance: np.ndarray
    probability: float
    particle_weight: float
    normalised_residual: float
    storey: int
    matches: list[tuple[int, int]]

    @property
    def n_matches(self) -> int:
        return len(self.matches)


@dataclass
class ModeHistory:
    """A mode's whole graph as plain data: its birth prior on X(first_index) ((3,) pose, (3, 3) world-frame
    covariance), (n, 3) ISAM2-smoothed poses of keyframes first_index … first_index + n − 1, their matches, the
    fine registrar's pose factors and the scan matches' (`PoseFactor`s)."""

    mode_id: int
    storey: int
    probability: float
    first_index: int
    prior_pose: np.ndarray
    prior_covariance: np.ndarray
    poses: np.ndarray
    associations: list[list[tuple[int, int]]]
    pose_factors: list[PoseFactor] = field(default_factory=list)
    scan_factors: list[PoseFactor] = field(default_factory=list)

    def within(self, steps: range) -> ModeHistory:
        """The mode over the keyframes `steps` (a stretch of the sequence that holds its birth), counted from the
        stretch's first keyframe: what it tracked past the stretch's end is left out."""
        i0 = self.first_index
        if i0 not in steps:
            raise ValueError(f"mode {self.mode_id} was born at keyframe {i0}, outside {steps.start}…{steps.stop - 1}")
        n = min(len(self.poses), steps.stop - i0)

        def kept(factors: list[PoseFactor]) -> list[PoseFactor]:
            return [(t - steps.start, *rest) for t, *rest in factors if i0 <= t < i0 + n]

        return dataclasses.replace(
            self,
            first_index=i0 - steps.start,
            poses=self.poses[:n],
            associations=self.associations[:n],
            pose_factors=kept(self.pose_factors),
            scan_factors=kept(self.scan_factors),
        )


@dataclass
class BackendStep:
    """One back-end step: the most probable mode, all modes (most probable first), what changed, timings."""

    index: int
    best: ModeEstimate
    modes: list[ModeEstimate]
    spawned: list[int] = field(default_factory=list)
    merged: list[tuple[int, int]] = field(default_factory=list)
    pruned: list[int] = field(default_factory=list)
    reassociated: list[int] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def pose(self) -> np.ndarray:
        return self.best.pose

    @property
    def covariance(self) -> np.ndarray:
        return self.best.covariance


class MultiHypothesisBackend:
    """Per-mode pose graphs driven by the particle filter's modes; `step` once per keyframe. `odometry` is the
    robot's odometry noise, which weighs the graphs' odometry factors."""

    def __init__(self, landmarks: Landmarks | np.ndarray, cfg: BackendConfig, odometry: OdometryConfig) -> None:
        self.cfg = cfg
        self.odometry = odometry
        self.landmarks = Landmarks.of(landmarks)
        self.tracker = ModeTracker(cfg)
        self.graphs: dict[int, ModeGraph] = {}
        self.index = -1
        # Graphs no mode goes on with (pruned, or restarted at a scan match beyond the window) that lived
        # `refine_retired_min_keyframes` keyframes: offline refinement's other candidates.
        self.retired: list[ModeHistory] = []

    @classmethod
    def from_prior(cls, prior: Any, cfg: BackendConfig, odometry: OdometryConfig) -> MultiHypothesisBackend:
        """A back end whose landmarks are a BimPrior's objects (row = object id)."""
        return cls(Landmarks.from_prior(prior), cfg, odometry)

    def step(
        self,
        modes: list[Mode],
        odom_increment: np.ndarray | None,
        observations: Observations,
        associate_fn: AssociateFn,
        odom_covariance: np.ndarray | None = None,
        pose_factor_fn: PoseFactorFn | None = None,
    ) -> BackendStep | None:
        """Track the modes, update every mode's graph with the keyframe, weigh the modes; see the module docstring.

        `pose_factor_fn`, when given, measures each mode's keyframe pose from its predicted pose (the scan match);
        a measurement enters the mode's graph with the keyframe. Returns None when there is no mode at all (no
        cluster heavy enough to spawn one and none tracked).
        """
        self.index += 1
        i = self.index
        clock = time.perf_counter()
        # 1. Mode identities: continue / spawn / merge; graphs of absorbed modes are dropped.
        events = self.tracker.update(modes, None if i == 0 else odom_increment)
        for _, absorbed in events.merged:
            self.graphs.pop(absorbed, None)
        if not self.tracker.modes:
            return None
        t_track = time.perf_counter()
        # 2. One ISAM2 update per mode graph (new modes start a graph at this keyframe from their cluster).
        costs: dict[int, float] = {}
        reassociated: list[int] = []
        for mode in self.tracker.modes:
            update = (mode, i, odom_increment, observations, associate_fn, odom_covariance, pose_factor_fn)
            try:
                graph, moved = self._update_graph(*update)
            except RuntimeError as error:
                # GTSAM found the mode's system indeterminate: the run goes on with the mode's graph restarted
                # from its particle cluster at this keyframe, rather than stop.
                _log_restart(mode.id, i, error, "from its particle cluster")
                self.graphs.pop(mode.id, None)
                graph, moved = self._update_graph(*update)
            if moved:
                reassociated.append(mode.id)
            costs[mode.id] = graph.cost(observations, graph.associations[i])
            mode.mean, mode.covariance = graph.pose.copy(), graph.covariance.copy()
        t_graphs = time.perf_counter()
        # 3. Probabilities p_k ∝ w_k · exp(−C_k / 2τ); merge converged graphs, prune improbable modes.
        self.tracker.set_probabilities(self._probabilities(costs))
        merged = self.tracker.merge_converged()
        for _, absorbed in merged:
            self.graphs.pop(absorbed, None)
        retiring = {m.id: m.probability for m in self.tracker.modes}
        pruned = self.tracker.prune()
        for mode_id in pruned:
            self._retire(self.graphs.pop(mode_id), retiring[mode_id])
        n_measured = len(observations) + observations.n_texts
        estimates = [self._estimate(mode, costs[mode.id], n_measured) for mode in self.tracker.modes]
        estimates.sort(key=lambda e: -e.probability)
        t_end = time.perf_counter()
        timings = {
            "track": (t_track - clock) * 1e3,
            "graphs": (t_graphs - t_track) * 1e3,
            "weigh": (t_end - t_graphs) * 1e3,
            "total": (t_end - clock) * 1e3,
        }
        return BackendStep(
            i, estimates[0], estimates, events.spawned, events.merged + merged, pruned, reassociated, timings
        )

    def _update_graph(
        self,
        mode: TrackedMode,
        i: int,
        odom_increment: np.ndarray | None,
        observations: Observations,
        associate_fn: AssociateFn,
        odom_covariance: np.ndarray | None,
        pose_factor_fn: PoseFactorFn | None,
    ) -> tuple[ModeGraph, bool]:
        """Keyframe i into a mode's graph (a new mode's graph starts here from its cluster): predicted pose → scan
        measurement → landmark associations → ISAM2 update → re-association. Returns the graph and whether it
        re-associated."""
        graph = self.graphs.get(mode.id)
        if graph is None:
            graph = self._start_graph(mode, i, mode.mean, mode.covariance)
            predicted, increment = graph.pose.copy(), None
        else:
            predicted, increment = graph.predict(odom_increment), odom_increment
        measured = None if pose_factor_fn is None else pose_factor_fn(predicted, mode.storey)
        if measured is not None and increment is not None and self._beyond_window(measured[0], predicted):
            # The scan matched beyond the search window about the prediction (the matcher searched again about
            # the window's edge): the graph's history disagrees with the walls, so it starts again at the match. The
            # history it had is kept as a refine candidate, as a pruned mode's is: the robot may have been carried
            # off to a look-alike here, and offline the old graph still explains the keyframes before.
            self._retire(graph, mode.probability)
            covariance = covariance_body_to_world(np.linalg.inv(measured[1]), float(measured[0][2]))
            graph = self._start_graph(mode, i, measured[0], covariance)
            predicted, increment, measured = graph.pose.copy(), None, None
        association = list(associate_fn(predicted, mode.storey))
        if measured is not None:
            graph.add_pose_factor(i, *measured, scan=True)
        graph.add_keyframe(i, observations, association, increment, odom_covariance)
        return graph, graph.reassociate(observations, associate_fn, predicted)

    def _start_graph(self, mode: TrackedMode, i: int, pose: np.ndarray, covariance: np.ndarray) -> ModeGraph:
        """A new graph for a mode, first keyframe i with its prior at a (3,) pose and (3, 3) world-frame covariance,
        in place of any it had."""
        graph = ModeGraph(mode.id, i, pose, covariance, self.landmarks, self.cfg, self.odometry, mode.storey)
        self.graphs[mode.id] = graph
        return graph

    def _retire(self, graph: ModeGraph, probability: float) -> None:
        """A graph no mode goes on with: kept in `retired` (offline refinement's candidates) when it lived
        `refine_retired_min_keyframes` keyframes."""
        if len(graph.poses) >= self.cfg.refine_retired_min_keyframes:
            self.retired.append(graph.history(probability))

    def _beyond_window(self, pose: np.ndarray, predicted: np.ndarray) -> bool:
        """Whether a (3,) pose lies outside the scan matcher's window about a (3,) predicted pose."""
        delta = np.abs(np.asarray(pose, np.float64) - predicted)
        delta[2] = abs(wrap_angle(delta[2]))
        return bool(
            delta[:2].max() > self.cfg.scan_factor.window_m or delta[2] > np.deg2rad(self.cfg.scan_factor.window_deg)
        )

    def add_pose_factor(
        self, mode_id: int, i: int, pose: np.ndarray, information: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Feed a fine registrar's (3,) pose with (3, 3) body-frame information into one mode's graph.

        Returns the mode's updated (3,) pose and (3, 3) world-frame covariance at its latest keyframe (the tracked
        mode follows them, as after a step).
        """
        graph, mode = self.graphs[mode_id], self.tracker.get(mode_id)
        try:
            graph.add_pose_factor(i, pose, information)
        except RuntimeError as error:
            # As in a step: an indeterminate system restarts the mode's graph from its estimate at keyframe i
            # (without that keyframe's landmark factors), and the fit enters the new graph with it.
            _log_restart(mode_id, i, error, "at it, on a fine registration")
            graph = self._start_graph(mode, i, mode.mean, mode.covariance)
            graph.add_pose_factor(i, pose, information)  # pending: applied with the keyframe
            graph.add_keyframe(i, Observations(np.zeros((0, 0)), np.zeros(0), np.zeros(0)), [])
        mode.mean, mode.covariance = graph.pose.copy(), graph.covariance.copy()
        return graph.pose.copy(), graph.covariance.copy()

    def histories(self) -> list[ModeHistory]:
        """Every tracked mode's graph as a `ModeHistory`, most probable first."""
        modes = sorted(self.tracker.modes, key=lambda m: (-m.probability, m.id))
        return [self.graphs[m.id].history(m.probability) for m in modes]

    def _probabilities(self, costs: dict[int, float]) -> dict[int, float]:
        ids = [m.id for m in self.tracker.modes]
        weights = np.array([max(self.tracker.get(k).weight, 1e-300) for k in ids])
        log_p = np.log(weights) - np.array([costs[k] for k in ids]) / (2 * self.cfg.residual_temperature)
        p = np.exp(log_p - log_p.max())
        return dict(zip(ids, (p / p.sum()).tolist(), strict=True))

    def _estimate(self, mode: TrackedMode, cost: float, n_obs: int) -> ModeEstimate:
        graph = self.graphs[mode.id]
        nu = cost / (2 * n_obs) if n_obs else 0.0
        return ModeEstimate(
            mode.id,
            graph.pose.copy(),
            graph.covariance.copy(),
            mode.probability,
            mode.weight,
            nu,
            mode.storey,
            list(graph.associations[graph.last_index]),
        )


# ------------------------------------------------------------------------------------------ offline


@dataclass
class BatchResult:
    """Levenberg–Marquardt refinement of a trajectory: (T, 3) poses, (T, 3, 3) world-frame covariances."""

    poses: np.ndarray
    covariances: np.ndarray
    error_before: float
    error_after: float
    iterations: int


def dead_reckoning(anchor_pose: np.ndarray, anchor_index: int, increments: np.ndarray) -> np.ndarray:
    """(T, 3) poses chained from a (3,) pose at keyframe `anchor_index` by (T−1, 3) robot-frame increments, forwards
    after the anchor and backwards (inverse increments) before it."""
    increments = np.asarray(increments, np.float64).reshape(-1, 3)
    poses = np.empty((len(increments) + 1, 3))
    poses[anchor_index] = anchor_pose
    for t in range(anchor_index + 1, len(poses)):
        poses[t] = se2_compose(poses[t - 1], increments[t - 1])
    for t in range(anchor_index - 1, -1, -1):
        poses[t] = se2_compose(poses[t + 1], se2_inverse(increments[t]))
    return poses


def batch_refine(
    first_pose: np.ndarray,
    first_covariance: np.ndarray,
    increments: np.ndarray,
    observations: Sequence[Observations],
    associations: Sequence[Association],
    landmarks: Landmarks | np.ndarray,
    cfg: BackendConfig,
    odometry: OdometryConfig,
    initial_poses: np.ndarray | None = None,
    odom_covariances: np.ndarray | None = None,
    pose_factors: Sequence[PoseFactor] = (),
    prior_index: int = 0,
) -> BatchResult:
    """Full graph of a T-keyframe trajectory optimised with Levenberg–Marquardt.

    `first_pose` / `first_covariance` are the pose prior on X(prior_index) (default: the first keyframe);
    `increments` (T−1, 3) robot-frame odometry; `observations` / `associations` one per keyframe; `landmarks`
    the BIM objects by id (an (N, 2) array: point landmarks); `odometry` the odometry noise that weighs the
    odometry factors; `initial_poses` (T, 3) (default: dead reckoning from the prior); `odom_covariances` (T−1, 3, 3)
    optional (in place of `odometry`'s); `pose_factors` (i, (3,) pose, (3, 3) body information) from a fine
    registrar.
    """
    increments = np.asarray(increments, np.float64).reshape(-1, 3)
    T = len(increments) + 1
    if len(observations) != T or len(associations) != T:
        raise ValueError(f"{T} keyframes need {T} observations and associations")
    if not 0 <= prior_index < T:
        raise ValueError(f"prior index {prior_index} is outside the {T} keyframes")
    landmarks = Landmarks.of(landmarks)
    if initial_poses is None:
        initial_poses = dead_reckoning(first_pose, prior_index, increments)
    # The motion part (pose prior, odometry, fine-registration pose factors) on its own also gives the fallback
    # covariances; the landmark factors and their priors complete the graph.
    motion = gtsam.NonlinearFactorGraph()
    motion.add(
        pose_prior_factor(prior_index, np.asarray(first_pose, np.float64), floored_covariance(first_covariance, cfg))
    )
    for t in range(1, T):
        cov = None if odom_covariances is None else odom_covariances[t - 1]
        motion.add(odometry_factor(t, increments[t - 1], cfg, odometry, cov))
    for i, pose, information in pose_factors:
        motion.add(information_pose_factor(i, pose, information))
    graph, values = gtsam.NonlinearFactorGraph(), _pose_values(initial_poses)
    graph.push_back(motion)
    noise = bearing_range_noise(cfg)
    seen: set[int] = set()
    for t in range(T):
        for factor in landmark_factors(t, observations[t], associations[t], noise):
            graph.add(factor)
        for _, j in associations[t]:
            if int(j) not in seen:
                seen.add(int(j))
                graph.add(landmark_prior_factor(int(j), landmarks, cfg))
                values.insert(L(int(j)), landmarks.xy[int(j)].copy())
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.lm_max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    error_before = graph.error(values)
    result = optimizer.optimize()
    poses = np.array([from_pose2(result.atPose2(X(t))) for t in range(T)])
    try:
        covariances = _pose_covariances(gtsam.Marginals(_without_degenerate_bearings(graph, result), result), poses)
    except RuntimeError as error:
        # Still indeterminate at the optimum: report the wider, always defined covariance of the motion part alone
        # rather than fail the whole trajectory.
        log.warning("pose marginals failed (%s); covariances from prior and odometry only", str(error).split(".")[0])
        covariances = _pose_covariances(gtsam.Marginals(motion, _pose_values(poses)), poses)
    return BatchResult(poses, covariances, float(error_before), float(graph.error(result)), optimizer.iterations())


def _without_degenerate_bearings(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.NonlinearFactorGraph:
    """The graph without the bearing-range factors whose landmark sits within `DEGENERATE_RANGE_M` of its pose at
    `values`. There the bearing's Jacobian grows as 1 / range (10⁵ at 0.1 mm, seen on duplex when the optimiser
    parks a mismatched landmark on the pose): its linearisation claims a near-exact bearing that no camera
    measured, and the Cholesky factorisation behind the marginals breaks down (an indeterminate system)."""
    kept = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, gtsam.BearingRangeFactor2D):
            pose_key, landmark_key = factor.keys()
            pose, landmark = values.atPose2(pose_key), values.atPoint2(landmark_key)
            if np.hypot(landmark[0] - pose.x(), landmark[1] - pose.y()) < DEGENERATE_RANGE_M:
                log.debug("marginals leave out %s: its landmark is on the pose", factor.keys())
                continue
        kept.add(factor)
    return kept


def _pose_values(poses: np.ndarray) -> gtsam.Values:
    """Values holding X(t) = poses[t]."""
    values = gtsam.Values()
    for t, pose in enumerate(poses):
        values.insert(X(t), gtsam.Pose2(*pose))
    return values


def _pose_covariances(marginals: gtsam.Marginals, poses: np.ndarray) -> np.ndarray:
    """(T, 3, 3) world-frame marginal covariances of X(0..T−1)."""
    return np.array(
        [covariance_body_to_world(marginals.marginalCovariance(X(t)), float(p[2])) for t, p in enumerate(poses)]
    )


def _log_restart(mode_id: int, keyframe: int, error: RuntimeError, how: str) -> None:
    """One warning for a mode graph that GTSAM found indeterminate and that was restarted (`how`)."""
    reason = str(error).strip().split("\n")[0]
    log.warning("mode %d: its pose graph failed at keyframe %d (%s); restarted %s", mode_id, keyframe, reason, how)
