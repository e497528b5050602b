"""Semantic Monte Carlo localization (paper Sec. II.C): a particle filter over (x, y, yaw, storey) in the BIM.

One step reads like the paper:
1. predict:  move every particle by the odometry increment plus Gaussian noise (`motion.propagate`);
             particles that leave navigable space keep only `off_map_weight` of their weight.
2. update:   weight ×= P(z|x) = exp(score / T), the semantic × spatial Hungarian score (`likelihood`); normalise.
             With `scan_likelihood` (beyond the paper) also × exp(score_scan / T_scan), the depth scan against the
             BIM's likelihood field (`field`), on every frame with a scan, objects in view or not.
3. resample: when ESS < δ_ess·M, systematic (low-variance) resampling from the cumulative weights; weights reset.
             With `kld_sampling` (beyond the paper; Fox 2003, AMCL's rule) the filter starts with `max_particles`
             and each resampling keeps as many as the pose bins the draws occupy need (`kld_particle_count`),
             never fewer than M: a global start over a large floor is sampled densely, a converged cloud cheaply.
4. estimate: weighted mean x, y and circular mean yaw on the storey holding the most weight; its room id.

The storey is part of the state: every particle carries a storey index (into `prior.storeys`). Initialization
spreads particles over the navigable space of all storeys in proportion to area; the motion model keeps a
particle on its storey (storey changes are not modelled), so the observations decide the storey.
Beyond the paper, `augmented: true` adds augmented MCL (Thrun et al., Probabilistic Robotics, Table 8.3):
random particles are injected with probability max(0, 1 − w_fast / w_slow) to recover from a wrong convergence.
`relocalize: true` handles the kidnapped robot, which a trickle of injected particles recovers from slowly: when the
belief stops explaining the depth scans (`LostMonitor`), the particles are spread over the building again, as at
the start, and the frame that showed it is weighed by the new cloud. Door plates read (`localization.text`) reset
the belief where weighing cannot: a reading the particles do not explain redraws `text_reset_share` of them in
front of the plates it names (`sample_from_texts`; sensor resetting, Lenser and Veloso 2000), kept from
`text_reset_oversample` times as many drawn by how well they explain the frame's depth scan (`screen_by_scan`).
`challenger: true` handles the look-alike room a belief converged in, which neither of those notices (it explains
each frame almost as well as the right room would): a small second filter drawn from the current observations runs
beside the converged belief, and when it predicts the frames decisively better somewhere else, the belief takes its
particles (`Challenger`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SmclConfig
from bimfactor.errors import InputError
from bimfactor.localization.field import ScanLikelihood
from bimfactor.localization.likelihood import SemanticLikelihood
from bimfactor.localization.motion import propagate
from bimfactor.types import Observations, TextObservations, wrap_angle

log = logging.getLogger(__name__)


@dataclass
class PoseEstimate:
    """The filter's pose estimate: (3,) x, y, yaw in the world frame on `storey`, with its (3, 3) covariance."""

    pose: np.ndarray
    storey: int
    covariance: np.ndarray
    converged: bool
    room_id: int
    position_std_m: float
    yaw_std_rad: float
    storey_share: float


class LostMonitor:
    """Tells when a belief that was tracking stops explaining the depth scans: the kidnapped robot.

    Each frame's fit is the belief's predicted scan score, Σ w_i s_i in [0, 1] (`SemanticMCL.scan_fit`): about
    0.55 while tracking (the prediction's spread and the depth noise keep it under 1), about 0.1 for a cloud
    spread over the building, 0.01–0.2 in the first frames after a kidnapping to an unlike place, and 0.3–0.45 for
    many frames after one to a place whose walls the old belief half explains. The monitor keeps a running average
    of the fit (rate `lost_fit_alpha`) and is armed once that average covers 1 / `lost_fit_alpha` frames and has
    reached `lost_min_fit` (a belief still spread or just converged after a global start is never called lost).
    Armed, two tests say lost:
    - a sudden drop: `lost_frames` consecutive frames below `lost_fit_ratio` × the average. It must be quick:
      within two or three frames of a kidnapping the motion noise finds the old belief places nearby that fit the
      new scans locally;
    - a held one, Page's CUSUM of the fit's log-ratio to the average: S ← max(0, S + min(ln(average / fit), h) −
      `lost_cusum_drift`), lost when S exceeds h = `lost_cusum_threshold`. A fit held at half the average takes
      four frames; fits above e^−drift ≈ 0.67 of it never add up (a robot nosing up to furniture the map lacks
      dips to about half for a few frames).
    No single frame says lost (a passer-by filling the view). Frames that start or continue either test stay out
    of the average. Frames with fewer than `lost_min_endpoints` scan endpoints (facing a wall at arm's length)
    leave it as it is.

    When it says lost, it also says since when: the frames of the excursion that led there, from the frame at which
    S (or the streak) last left zero. That is Page's estimate of the change point, where a kidnapped recording's
    continuous stretches part (`LocalizationRun.segments`).
    """

    def __init__(self, cfg: SmclConfig) -> None:
        self.cfg = cfg
        self.average: float | None = None
        self.frames = 0  # frames in the average
        self.streak = 0  # consecutive frames below lost_fit_ratio × the average
        self.cusum = 0.0
        self.excursion = 0  # frames, with a scan or not, since S or the streak last left zero (0: at zero)

    def reset(self) -> None:
        self.average, self.frames, self.streak, self.cusum, self.excursion = None, 0, 0, 0.0, 0

    def lost(self, fit: float | None, n_endpoints: int) -> int:
        """Feed one frame's fit (None: no scan). When the belief is lost, the number of frames (this one included)
        since it stopped explaining the scans, and the monitor starts over; otherwise 0."""
        cfg = self.cfg
        if self.excursion:
            self.excursion += 1
        if fit is None or n_endpoints < cfg.lost_min_endpoints:
            return 0
        average = self.average
        if average is not None and average >= cfg.lost_min_fit and self.frames * cfg.lost_fit_alpha >= 1:
            self.streak = self.streak + 1 if fit < cfg.lost_fit_ratio * average else 0
            surprise = min(float(np.log(average / max(fit, 1e-3))), cfg.lost_cusum_threshold)
            self.cusum = max(0.0, self.cusum + surprise - cfg.lost_cusum_drift)
            if self.streak or self.cusum > 0.0:
                self.excursion = self.excursion or 1
                if self.streak >= cfg.lost_frames or self.cusum > cfg.lost_cusum_threshold:
                    since = self.excursion
                    self.reset()
                    return since
                return 0
            self.excursion = 0
        self.frames += 1
        self.average = fit if average is None else average + cfg.lost_fit_alpha * (fit - average)
        return 0


@dataclass
class StepResult:
    """One filter step: the estimate after it, the ESS before resampling, and what each part took."""

    estimate: PoseEstimate
    ess: float
    resampled: bool
    injected: int = 0
    n_observations: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)
    n_particles: int = 0
    scan_fit: float | None = None  # the belief's predicted scan fit before the update (`SemanticMCL.scan_fit`)
    relocalized: bool = False  # the particles were spread over the building again at this step
    lost_frames: int = 0  # relocalized: the frames, this one included, since the belief stopped explaining the scans
    challenged: bool = False  # the belief took the particles of a challenger that explained the frames better

    @property
    def pose(self) -> np.ndarray:
        return self.estimate.pose

    @property
    def covariance(self) -> np.ndarray:
        return self.estimate.covariance

    @property
    def converged(self) -> bool:
        return self.estimate.converged

    @property
    def room_id(self) -> int:
        return self.estimate.room_id

    @property
    def storey(self) -> int:
        return self.estimate.storey


class Challenger:
    """A second, small filter that a converged belief must keep out-predicting: the look-alike room it locked onto.

    A belief that converged in the wrong one of two rooms of the same shape explains each frame almost as well as
    the right one would: its scan fit stays at its usual level (`LostMonitor` never fires) and augmented MCL's
    averages settle there too. What tells the rooms apart is evidence summed over frames, against an alternative.
    The challenger is that alternative: `challenger_particles` poses that explain the current frame's observations
    (each one observation by one BIM object, `SemanticMCL.sample_from_observations`; uniform over free space where
    those run short), drawn from `max(injection_oversample, text_reset_oversample)` times as many by the frame's
    scan (`screen_by_scan`), then run as a filter of its own on the same frames. From the next frame on, each
    frame's log predictive likelihoods ln p(z | challenger) and ln p(z | belief) (`SemanticMCL.log_evidence`, one
    measurement model for both, so their ratio is a Bayes factor) feed Page's CUSUM of their difference. When it
    exceeds `challenger_threshold_nats` while the challenger's estimate lies elsewhere, the belief takes the
    challenger's particles (`SemanticMCL.adopt`). A challenger that agrees with the belief (estimates within
    `challenger_agree_m` on one storey) for `challenger_agree_frames` frames in a row, or has not won within
    `challenger_max_frames`, is drawn again at the next frame: the belief is checked against fresh alternatives
    for as long as it is converged. The frame it is drawn from does not count (the draw was chosen to fit it).
    Its draws come from a generator spawned from the filter's, so the belief's own draws are those it would make
    without it.
    """

    def __init__(self, owner: SemanticMCL) -> None:
        self.owner = owner
        self.cfg = owner.cfg
        solo = owner.cfg.model_copy(update={"challenger": False, "relocalize": False})
        rng = owner.rng.spawn(1)[0]
        self.filter = SemanticMCL(owner.prior, owner.likelihood.visibility, solo, rng, solo.challenger_particles, owner)
        self.running = False
        self.frames = 0  # frames followed since it was drawn
        self.agreeing = 0  # consecutive frames its estimate agreed with the belief's
        self.cusum = 0.0

    def stop(self) -> None:
        """Draw a new challenger at the next converged frame (the belief was spread or handed over)."""
        self.running = False

    def start(self, observations: Observations | None, scan: np.ndarray | None) -> None:
        """Draw the challenger from this frame: poses that explain its observations, screened by its scan."""
        rival, cfg = self.filter, self.cfg
        n = cfg.challenger_particles
        drawn = max(1, cfg.injection_oversample, cfg.text_reset_oversample) * n
        poses, storeys = rival.sample_free_space(0)
        if observations is not None:
            poses, storeys = rival.sample_from_observations(drawn, observations)
        if len(poses) < drawn:
            more, more_storeys = rival.sample_free_space(drawn - len(poses))
            poses, storeys = np.concatenate([poses, more]), np.concatenate([storeys, more_storeys])
        rival.set_particles(*rival.screen_by_scan(n, poses, storeys, scan))
        self.running, self.frames, self.agreeing, self.cusum = True, 0, 0, 0.0

    def follow(
        self,
        odom_increment: np.ndarray | None,
        observations: Observations | None,
        scan: np.ndarray | None,
        estimate: PoseEstimate,
    ) -> bool:
        """One frame, after the belief's step gave `estimate`: True when the belief took the challenger's particles."""
        owner, cfg, rival = self.owner, self.cfg, self.filter
        if not self.running:
            has_data = (observations is not None and len(observations) > 0) or (scan is not None and len(scan) > 0)
            if estimate.converged and has_data:
                self.start(observations, scan)
            return False
        if odom_increment is not None:
            rival.predict(odom_increment)
        rival.update(observations, scan)
        ours, theirs = owner.log_evidence, rival.log_evidence
        rival.resample_if_needed(observations, scan)
        self.frames += 1
        if ours is not None and theirs is not None:
            self.cusum = max(0.0, self.cusum + theirs - ours)
        guess = rival.estimate()
        apart = float(np.hypot(*(guess.pose[:2] - estimate.pose[:2])))
        agree = guess.storey == estimate.storey and apart <= cfg.challenger_agree_m
        self.agreeing = self.agreeing + 1 if agree else 0
        if self.cusum > cfg.challenger_threshold_nats and not agree:
            owner.adopt(rival)
            self.running = False
            return True
        if self.agreeing >= cfg.challenger_agree_frames or self.frames >= cfg.challenger_max_frames:
            self.running = False
        return False


# ------------------------------------------------------------------------------------------ pieces


def effective_sample_size(weights: np.ndarray) -> float:
    """ESS = 1 / Σ w² of (M,) normalised weights."""
    w = np.asarray(weights, np.float64)
    return float(1.0 / np.dot(w, w))


def kld_particle_count(bins: np.ndarray | int, epsilon: float, z: float) -> np.ndarray:
    """Particles that keep the KL divergence between the sample and the belief below ε with probability 1 − δ
    when the sample occupies k bins (Fox 2003, Eq. 13; z = z_(1−δ)):
    n = (k − 1) / (2ε) · (1 − 2 / (9(k − 1)) + √(2 / (9(k − 1))) · z)³, and 1 for a single bin."""
    k = np.asarray(bins, np.float64)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return np.where(k <= 1, 1, np.ceil(n)).astype(np.int64)


def systematic_resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) indices drawn by low-variance (systematic) sampling from the cumulative (M,) weights.

    Each particle i is drawn ⌊n·w_i⌋ or ⌈n·w_i⌉ times.
    """
    cumulative = np.cumsum(np.asarray(weights, np.float64))
    cumulative /= cumulative[-1]
    positions = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cumulative, positions, side="right"), len(cumulative) - 1)


def circular_mean(angles: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted circular mean of (N,) angles in [-π, π): atan2(Σ w sin θ, Σ w cos θ)."""
    angles = np.asarray(angles, np.float64)
    w = np.ones_like(angles) if weights is None else np.asarray(weights, np.float64)
    return float(wrap_angle(np.arctan2(np.dot(w, np.sin(angles)), np.dot(w, np.cos(angles)))))


def weighted_pose_stats(poses: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) weighted mean (circular in yaw) and (3, 3) covariance of (N, 3) poses; yaw residuals wrapped."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    mean = np.empty(3)
    mean[:2] = w @ poses[:, :2]
    mean[2] = circular_mean(poses[:, 2], w)
    return mean, _second_moment(poses, mean, w)


def weighted_geometric_median(
    points: np.ndarray, weights: np.ndarray, tol_m: float = 0.01, max_iterations: int = 50
) -> np.ndarray:
    """(2,) weighted geometric median of (N, 2) points: the position minimising Σ w ‖p − x‖, i.e. the expected
    Euclidean error under the weighted set (Weiszfeld's iteration from the weighted mean, until it moves < tol_m).

    Unlike the mean, it stays inside a cluster that holds most of the weight instead of being pulled towards
    distant minorities, and between clusters of similar weight it is no farther from the truth on average."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    w = np.asarray(weights, np.float64)
    x = w @ points / w.sum()
    for _ in range(max_iterations):
        inverse = w / np.maximum(np.hypot(*(points - x).T), 1e-6)
        moved = inverse @ points / inverse.sum()
        done = np.hypot(*(moved - x)) < tol_m
        x = moved
        if done:
            break
    return x


def local_mean_yaw(poses: np.ndarray, weights: np.ndarray, center_xy: np.ndarray, radius_m: float) -> float | None:
    """Weighted circular mean yaw of the (N, 3) poses within `radius_m` of `center_xy`; None when none holds weight.

    A position reported between or inside clusters takes the heading of the particles there, not the belief's
    global mean heading, which rival places facing elsewhere pull away."""
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    near = np.hypot(*(poses[:, :2] - np.asarray(center_xy, np.float64)).T) <= radius_m
    w = np.where(near, np.asarray(weights, np.float64), 0.0)
    return circular_mean(poses[:, 2], w) if w.sum() > 0 else None


def pose_window(poses: np.ndarray, centre: np.ndarray, radius_m: float, yaw_half_rad: float) -> np.ndarray:
    """(N,) bool: poses within the flat (position radius, wrapped yaw half-width) window around a (3,) centre."""
    near = np.hypot(poses[:, 0] - centre[0], poses[:, 1] - centre[1]) <= radius_m
    return near & (np.abs(wrap_angle(poses[:, 2] - centre[2])) <= yaw_half_rad)


def near_pose(
    poses: np.ndarray, storeys: np.ndarray, pose: np.ndarray, storey: int, radius_m: float, yaw_rad: float
) -> np.ndarray:
    """(M,) bool: which of the (M, 3) poses on their (M,) storeys lie in the `pose_window` of a (3,) pose on
    `storey`."""
    return (np.asarray(storeys) == storey) & pose_window(poses, pose, radius_m, yaw_rad)


def _second_moment(poses: np.ndarray, about: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(3, 3) Σ_k w_k δ_k δ_kᵀ of (K, 3) poses with (K,) normalised weights, δ_k = pose_k − about, yaw wrapped."""
    delta = np.asarray(poses, np.float64).reshape(-1, 3) - np.asarray(about, np.float64)
    delta[:, 2] = wrap_angle(delta[:, 2])
    return (delta * weights[:, None]).T @ delta


def mixture_pose_covariance(
    about: np.ndarray, means: np.ndarray, covariances: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """(3, 3) second moment about the (3,) pose `about` of a mixture of K Gaussians: (K, 3) means, (K, 3, 3)
    covariances, (K,) weights (normalised here); Σ_k w_k (Σ_k + δ_k δ_kᵀ) with δ_k = μ_k − about, yaw wrapped.

    The uncertainty of reporting one component's pose when the belief holds the others too (law of total
    covariance, taken about the reported pose instead of the mixture's mean)."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    within = np.einsum("k,kij->ij", w, np.asarray(covariances, np.float64).reshape(-1, 3, 3))
    return within + _second_moment(means, about, w)


# ------------------------------------------------------------------------------------------ the filter


class SemanticMCL:
    """The S-MCL particle filter against one BimPrior; every random draw comes from `rng`."""

    def __init__(
        self,
        prior: BimPrior,
        visibility: VisibilityTable,
        cfg: SmclConfig,
        rng: np.random.Generator,
        num_particles: int | None = None,
        shared: SemanticMCL | None = None,
    ) -> None:
        self.prior = prior
        self.cfg = cfg
        self.rng = rng
        # A given count is fixed (benchmarks); otherwise M, or M … max_particles with KLD-sampling.
        self.min_particles = int(num_particles or cfg.num_particles)
        adaptive = num_particles is None and cfg.kld_sampling
        self.max_particles = int(cfg.max_particles) if adaptive else self.min_particles
        if shared is not None:  # a second filter over the same prior and models (the challenger)
            self.likelihood, self.scan_likelihood = shared.likelihood, shared.scan_likelihood
            self.navigable, self._free_cells = shared.navigable, shared._free_cells
        else:
            self.likelihood = SemanticLikelihood(prior, visibility, cfg)
            self.scan_likelihood = ScanLikelihood(prior, cfg) if cfg.scan_likelihood else None
            self.navigable = np.stack([layers.navigable.astype(bool) for layers in prior.storeys])  # (S, rows, cols)
            self._free_cells = np.flatnonzero(self.navigable).astype(np.int64)  # flat (storey, row, col) indices
        self._object_storey = np.asarray([o.storey_index for o in prior.objects], np.int64)
        if len(self._free_cells) == 0:
            raise InputError("the prior has no navigable space to spread particles over")
        self.particles = np.zeros((self.max_particles, 3))
        self.storeys = np.zeros(self.max_particles, np.int64)
        self.weights = np.full(self.max_particles, 1.0 / self.max_particles)
        # Particles injected at the last resampling and not yet weighed by a measurement: left out of the estimate.
        self.fresh = np.zeros(self.max_particles, bool)
        self.w_slow: float | None = None
        self.w_fast: float | None = None
        self.scan_fit: float | None = None  # the last update's Σ w_i s_i over the prior weights (None: no scan)
        self.unexplained_texts: list[int] = []  # the last update's readings the belief did not explain (text resets)
        self.log_evidence: float | None = None  # the last update's ln p(z | belief), the predictive likelihood
        self.lost_monitor = LostMonitor(cfg)
        self.challenger = Challenger(self) if cfg.challenger else None
        self._initialized = False

    @property
    def num_particles(self) -> int:
        """The current particle count (KLD-sampling changes it at each resampling)."""
        return len(self.particles)

    # -------------------------------------------------------------------------------- sampling

    def sample_free_space(self, n: int, storeys: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """n poses uniform over the navigable space of the given storeys (all: None) and uniform in yaw.

        Returns (n, 3) x, y, yaw and (n,) storey indices.
        """
        cells = self._free_cells
        if storeys is not None:
            per_storey = self.navigable[0].size
            cells = cells[np.isin(cells // per_storey, np.asarray(storeys, np.int64))]
            if len(cells) == 0:
                raise InputError(f"no navigable space on storeys {list(storeys)}")
        picked = cells[self.rng.integers(0, len(cells), n)]
        s, r, c = np.unravel_index(picked, self.navigable.shape)
        grid = self.prior.grid
        jitter = self.rng.random((n, 2))
        poses = np.empty((n, 3))
        poses[:, 0] = grid.origin_x + (c + jitter[:, 0]) * grid.resolution_m
        poses[:, 1] = grid.origin_y + (r + jitter[:, 1]) * grid.resolution_m
        poses[:, 2] = self.rng.uniform(-np.pi, np.pi, n)
        return poses, s.astype(np.int64)

    def sample_from_observations(self, n: int, observations: Observations) -> tuple[np.ndarray, np.ndarray]:
        """Up to n poses drawn from the measurement model: each explains one observation by one BIM object.

        A pair (observation j, object k) is drawn in proportion to φ_sem among the pairs that pass the semantic
        screen; the robot is put at j's observed range from k in a uniformly drawn direction and turned so k
        appears at j's observed bearing, with the motion noise (σ_trans, σ_rot) added. Poses off navigable space
        or from which k is not in the visibility table's list are dropped (five rounds of draws at most), so
        fewer than n may come back. Returns (n', 3) poses and (n',) storeys.
        """
        empty = np.zeros((0, 3)), np.zeros(0, np.int64)
        if n <= 0 or len(observations) == 0:
            return empty
        scorer = self.likelihood
        sem = scorer.semantic(observations)
        sem = np.where(sem >= self.cfg.semantic_threshold, sem, 0.0).ravel().astype(np.float64)
        if sem.sum() <= 0:
            return empty
        n_objects = sem.size // len(observations)
        ranges = np.asarray(observations.range_m, np.float64)
        bearings = np.asarray(observations.bearing_rad, np.float64)

        def draw(m: int) -> tuple[np.ndarray, np.ndarray]:
            j, k = np.divmod(self.rng.choice(sem.size, size=m, p=sem / sem.sum()), n_objects)
            direction = self.rng.uniform(-np.pi, np.pi, m)
            drawn = np.empty((m, 3))
            drawn[:, 0] = scorer.object_xy[k, 0] + ranges[j] * np.cos(direction)
            drawn[:, 1] = scorer.object_xy[k, 1] + ranges[j] * np.sin(direction)
            drawn[:, 2] = direction + np.pi - bearings[j]
            self._add_motion_noise(drawn)
            storey = self._object_storey[k]
            ok = self.on_navigable(drawn, storey)
            offsets, ids = scorer.visibility.candidates(drawn[ok, :2], storey[ok])
            owner = np.repeat(np.arange(int(ok.sum())), np.diff(offsets))
            sees = np.zeros(len(drawn), bool)
            sees[np.flatnonzero(ok)] = np.bincount(owner[ids == k[ok][owner]], minlength=int(ok.sum())) > 0
            return drawn[sees], storey[sees]

        return self._draw_in_rounds(n, draw)

    def sample_from_texts(
        self, n: int, observations: Observations, readings: list[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Up to n poses that explain the door-plate readings `readings` of `observations` (sensor resetting): each
        drawn in front of a plate a reading names (`PlateLikelihood.sample_poses`), with the motion noise added;
        poses off navigable space are dropped (five rounds of draws at most). Returns (n', 3) and (n',)."""
        texts, plates = observations.texts, self.likelihood.plates

        def draw(m: int) -> tuple[np.ndarray, np.ndarray]:
            k = self.rng.choice(readings, size=m)
            poses, storeys = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
            for reading in np.unique(k):
                count = int(np.sum(k == reading))
                text, r, b = texts.texts[reading], float(texts.range_m[reading]), float(texts.bearing_rad[reading])
                drawn, storey = plates.sample_poses(text, r, b, count, self.rng)
                self._add_motion_noise(drawn)
                ok = self.on_navigable(drawn, storey)
                poses.append(drawn[ok])
                storeys.append(storey[ok])
            return np.concatenate(poses), np.concatenate(storeys)

        return self._draw_in_rounds(n, draw)

    @staticmethod
    def _draw_in_rounds(n: int, draw: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
        """Up to n poses and their storeys from `draw(m)` (the poses kept of m drawn): five rounds at most, each
        drawing four times as many as are still missing."""
        poses, storeys = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
        for _ in range(5):
            kept, kept_storeys = draw(4 * (n - sum(len(p) for p in poses)))
            poses.append(kept)
            storeys.append(kept_storeys)
            if sum(len(p) for p in poses) >= n:
                break
        return np.concatenate(poses)[:n], np.concatenate(storeys)[:n]

    def screen_by_scan(
        self, n: int, poses: np.ndarray, storeys: np.ndarray, scan: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """n of the drawn (N, 3) poses, chosen without replacement in proportion to the frame's scan likelihood
        exp(score / T_scan) (`text_reset_oversample` and `injection_oversample` draw more than are needed, so that
        the walls in view pick among them); the first n when there is no scan term or scan. Returns (n', 3) and
        (n',), n' = min(n, N)."""
        if self.scan_likelihood is None or scan is None or not len(scan) or len(poses) <= n:
            return poses[:n], storeys[:n]
        log_p = self.scan_likelihood.log_likelihood(poses, storeys, scan)
        odds = np.exp(log_p - log_p.max())
        keep = self.rng.choice(len(poses), size=n, replace=False, p=odds / odds.sum())
        return poses[keep], storeys[keep]

    def _add_motion_noise(self, poses: np.ndarray) -> None:
        """Perturb (n, 3) drawn poses in place by the motion model's σ_trans and σ_rot."""
        noise = self.rng.standard_normal(poses.shape)
        poses[:, :2] += self.cfg.sigma_trans_m * noise[:, :2]
        poses[:, 2] = wrap_angle(poses[:, 2] + np.deg2rad(self.cfg.sigma_rot_deg) * noise[:, 2])

    def on_navigable(self, particles: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(M,) bool: is each particle's position in navigable space of its storey?"""
        rc = self.prior.grid.world_to_cell(particles[:, :2])
        ok = self.prior.grid.contains(rc)
        out = np.zeros(len(rc), bool)
        out[ok] = self.navigable[storeys[ok], rc[ok, 0], rc[ok, 1]]
        return out

    # -------------------------------------------------------------------------------- the cycle

    def initialize(self, storeys: list[int] | None = None) -> None:
        """M (KLD-sampling: `max_particles`) particles uniform over the navigable space of the given storeys (None:
        all), equal weights. InputError for a storey the prior does not have."""
        n = self.navigable.shape[0]
        missing = sorted(set(storeys or []) - set(range(n)))
        if missing:
            raise InputError(f"storeys {missing} do not exist: the prior has storey{'s 0 …' if n > 1 else ''} {n - 1}")
        self.particles, self.storeys = self.sample_free_space(self.max_particles, storeys)
        self.weights = np.full(self.num_particles, 1.0 / self.num_particles)
        self.fresh = np.zeros(self.max_particles, bool)
        self.w_slow = self.w_fast = None
        self.lost_monitor.reset()
        if self.challenger is not None:
            self.challenger.stop()
        self._initialized = True

    def initialize_around(self, pose: np.ndarray, storey: int, sigma_xy_m: float, sigma_yaw_rad: float) -> None:
        """M particles from a Gaussian about a (3,) pose guess on one storey (AMCL's initial pose), equal weights.

        Draws that fall off navigable space are drawn again; InputError when the storey does not exist or no draw
        lands on navigable space (a guess in another frame or unit, or inside a wall's block).
        """
        pose = np.asarray(pose, np.float64).reshape(3)
        if not 0 <= storey < self.navigable.shape[0]:
            raise InputError(f"initial pose: storey {storey} does not exist (the prior has {self.navigable.shape[0]})")
        n = self.min_particles
        kept: list[np.ndarray] = []
        for _ in range(5):
            drawn = pose + self.rng.standard_normal((4 * n, 3)) * [sigma_xy_m, sigma_xy_m, sigma_yaw_rad]
            drawn[:, 2] = wrap_angle(drawn[:, 2])
            kept.append(drawn[self.on_navigable(drawn, np.full(len(drawn), storey))])
            if sum(len(k) for k in kept) >= n:
                break
        particles = np.concatenate(kept)
        if len(particles) == 0:
            raise InputError(
                f"initial pose ({pose[0]:.2f} m, {pose[1]:.2f} m) on storey {storey}: no navigable space within "
                f"about {3 * sigma_xy_m:g} m of it (the BIM's world frame, metres)"
            )
        self.particles = particles[self.rng.integers(0, len(particles), n)] if len(particles) < n else particles[:n]
        self.storeys = np.full(n, storey, np.int64)
        self.weights = np.full(n, 1.0 / n)
        self.fresh = np.zeros(n, bool)
        self.w_slow = self.w_fast = None
        self.lost_monitor.reset()
        if self.challenger is not None:
            self.challenger.stop()
        self._initialized = True

    def set_particles(self, particles: np.ndarray, storeys: np.ndarray) -> None:
        """Start from the given (N, 3) poses on their (N,) storeys with equal weights (none fresh); augmented MCL's
        averages and the lost monitor start over."""
        self.particles, self.storeys = np.array(particles, np.float64).reshape(-1, 3), np.array(storeys, np.int64)
        if len(self.particles) == 0:
            raise InputError("no particles to start the filter from")
        self.weights = np.full(len(self.particles), 1.0 / len(self.particles))
        self.fresh = np.zeros(len(self.particles), bool)
        self.w_slow = self.w_fast = None
        self.lost_monitor.reset()
        self._initialized = True

    def adopt(self, other: SemanticMCL) -> None:
        """Take another filter's belief: this filter's particle count drawn from its weighted particles."""
        keep = systematic_resample(other.weights, self.num_particles, self.rng)
        self.set_particles(other.particles[keep], other.storeys[keep])

    def predict(self, odom_increment: np.ndarray) -> None:
        """Move the particles by a (3,) robot-frame odometry increment (dx, dy, dyaw) with the motion noise."""
        self._require_initialized()
        self.particles = propagate(
            self.particles, odom_increment, self.cfg.sigma_trans_m, np.deg2rad(self.cfg.sigma_rot_deg), self.rng
        )
        off_map = ~self.on_navigable(self.particles, self.storeys)
        if off_map.any():
            self.weights[off_map] *= self.cfg.off_map_weight
            self._normalise("after leaving navigable space")

    def update(self, observations: Observations | None, scan: np.ndarray | None = None) -> None:
        """Weight ×= P(z|x) for every particle and normalise; nothing to weigh by leaves the weights as they are.

        P(z|x) is the semantic term for the observations (with the door-plate term for text read) and, with
        `scan_likelihood`, the scan term for the (N, 2) base-frame `scan` endpoints (`field.scan_endpoints`); either
        may be empty or None. With the missed-detection
        term (`detection_probability` > 0) an empty `observations` (a frame that detected nothing) still weighs.
        With a scan, `scan_fit` becomes the belief's predicted scan score Σ w_i s_i (weights before the update).
        """
        self._require_initialized()
        self.scan_fit = None
        self.log_evidence = None
        has_observations = observations is not None and len(observations) > 0
        # With the missed-detection term a frame that detected nothing still says which places it did not see.
        weighs_misses = observations is not None and self.cfg.detection_probability > 0.0
        has_scan = self.scan_likelihood is not None and scan is not None and len(scan) > 0
        has_texts = observations is not None and observations.n_texts > 0
        if not (has_observations or has_scan or weighs_misses or has_texts):
            return
        if not np.all(self.weights >= 0) or self.weights.sum() <= 0:
            self.weights = np.full(self.num_particles, 1.0 / self.num_particles)
        log_likelihood = np.zeros(self.num_particles)
        if has_observations or weighs_misses:
            semantic, missed = self.likelihood.log_likelihood_terms(self.particles, self.storeys, observations)
            log_likelihood += semantic + missed
        if has_observations and self.cfg.augmented:
            # Augmented MCL watches the semantic term alone: a wrong place of the same shape fits the scan
            # as well as the right one. Average likelihood on an absolute scale (a perfect match = 1) of the
            # mean matched score, whatever the number of observations (`count_scale`).
            mean_term = semantic / self.likelihood.count_scale(len(observations))
            w_avg = float(np.dot(self.weights, np.exp(mean_term - 1.0 / self.cfg.temperature)))
            rate_slow, rate_fast = self.cfg.alpha_slow, self.cfg.alpha_fast
            self.w_slow = w_avg if self.w_slow is None else self.w_slow + rate_slow * (w_avg - self.w_slow)
            self.w_fast = w_avg if self.w_fast is None else self.w_fast + rate_fast * (w_avg - self.w_fast)
        self.unexplained_texts = []
        if has_texts:
            per_reading = self.likelihood.plates.reading_likelihoods(self.particles, self.storeys, observations.texts)
            log_likelihood += np.log(per_reading).sum(axis=0)
            if self.cfg.text_reset_share > 0:
                self.unexplained_texts = self._unexplained_readings(per_reading, observations.texts)
        if has_scan:
            scores = self.scan_likelihood.scores(self.particles, self.storeys, scan)
            self.scan_fit = float(np.dot(self.weights, scores) / self.weights.sum())
            log_likelihood += scores / self.cfg.scan_temperature
        self.fresh[:] = False
        with np.errstate(divide="ignore"):
            log_w = np.log(self.weights) + log_likelihood
        peak = log_w.max()
        self.weights = np.exp(log_w - peak) if np.isfinite(peak) else np.zeros_like(log_w)
        if np.isfinite(peak):  # ln Σ w_i p(z | x_i) of the weights before the update (normalised): ln p(z | belief)
            self.log_evidence = float(peak + np.log(self.weights.sum()))
        self._normalise("after the measurement update")

    def _unexplained_readings(self, per_reading: np.ndarray, texts: TextObservations) -> list[int]:
        """The readings (indices) that name a plate and that the belief explains poorly: of the most that P(t | x)
        rises above ε for the reading's text (a particle right before its best-matching plate), the particles'
        weighted average holds less than `text_reset_below`. A look-alike misread is judged as the text it reads."""
        plates, eps = self.likelihood.plates, self.cfg.text_unexplained
        explained = per_reading @ (self.weights / self.weights.sum())
        out = []
        for k, text in enumerate(texts.texts):
            if not len(plates.named_plates(text)):
                continue
            most = (1.0 - eps) * float(plates.text_match(text).max())
            if (explained[k] - eps) < self.cfg.text_reset_below * most:
                out.append(k)
        return out

    def effective_sample_size(self) -> float:
        return effective_sample_size(self.weights)

    def estimation_weights(self) -> np.ndarray:
        """The weights a pose estimate may use: those of the particles injected at the last resampling (`fresh`)
        are 0 until a measurement has weighed them (all of them stand when every particle is fresh)."""
        return np.where(self.fresh, 0.0, self.weights) if not self.fresh.all() else self.weights

    def injection_probability(self) -> float:
        """Augmented MCL: max(0, 1 − w_fast / w_slow), w_slow floored at exp((s − 1) / T) when
        `injection_reference_score` s > 0; 0 for the paper's filter."""
        if not self.cfg.augmented or not self.w_slow or self.w_fast is None:
            return 0.0
        w_slow = self.w_slow
        if self.cfg.injection_reference_score > 0:
            w_slow = max(w_slow, np.exp((self.cfg.injection_reference_score - 1.0) / self.cfg.temperature))
        return max(0.0, 1.0 - self.w_fast / w_slow)

    def resample_if_needed(
        self, observations: Observations | None = None, scan: np.ndarray | None = None
    ) -> tuple[bool, int]:
        """Systematic resampling when ESS < δ_ess·M (or random particles are due); returns (resampled, injected).

        With KLD-sampling the new count is `kld_resample`'s, and the random particles are drawn for it.
        Random particles come from `observations` (`injection: observations`, see `sample_from_observations`;
        uniform where they yield too few) or uniformly over free space (`injection: uniform`). Particles drawn
        from door-plate readings or from the observations are screened by the frame's `scan` (`screen_by_scan`,
        per `text_reset_oversample` and `injection_oversample`)."""
        self._require_initialized()
        M = self.num_particles
        n_random = int(self.rng.binomial(M, self.injection_probability())) if self.cfg.augmented else 0
        resets = self.unexplained_texts if observations is not None and observations.n_texts else []
        n_reset = round(self.cfg.text_reset_share * M) if resets else 0
        if self.effective_sample_size() >= self.cfg.ess_threshold * M and n_random == 0 and n_reset == 0:
            return False, 0
        if self.max_particles > self.min_particles:
            keep = self.kld_resample()
            M = len(keep)
            n_random = int(self.rng.binomial(M, self.injection_probability())) if n_random else 0
            n_reset = min(round(self.cfg.text_reset_share * M), M - n_random) if resets else 0
            keep = keep[: M - n_random - n_reset]
        else:
            keep = systematic_resample(self.weights, M - n_random - n_reset, self.rng)
        particles, storeys = self.particles[keep], self.storeys[keep]
        fresh, fresh_storeys = np.zeros((0, 3)), np.zeros(0, np.int64)
        if n_reset:
            k = self.cfg.text_reset_oversample
            fresh, fresh_storeys = self.screen_by_scan(
                n_reset, *self.sample_from_texts(k * n_reset, observations, resets), scan
            )
        if n_random and self.cfg.injection == "observations" and observations is not None:
            k = self.cfg.injection_oversample
            more, more_storeys = self.screen_by_scan(
                n_random, *self.sample_from_observations(k * n_random, observations), scan
            )
            fresh, fresh_storeys = np.concatenate([fresh, more]), np.concatenate([fresh_storeys, more_storeys])
        if len(fresh) < n_random + n_reset:
            more, more_storeys = self.sample_free_space(n_random + n_reset - len(fresh))
            fresh, fresh_storeys = np.concatenate([fresh, more]), np.concatenate([fresh_storeys, more_storeys])
        self.particles = np.concatenate([particles, fresh])
        self.storeys = np.concatenate([storeys, fresh_storeys])
        self.weights = np.full(M, 1.0 / M)
        self.fresh = np.arange(M) >= M - len(fresh)
        return True, len(fresh)

    def kld_resample(self) -> np.ndarray:
        """Indices of a KLD-sized resample: `max_particles` systematic draws in random order, cut at the first n
        that reaches both M and `kld_particle_count` of the (storey, x, y, yaw) bins the first n draws occupy."""
        cfg = self.cfg
        draws = systematic_resample(self.weights, self.max_particles, self.rng)
        draws = draws[self.rng.permutation(len(draws))]
        poses = self.particles[draws]
        cells = np.floor(poses[:, :2] / cfg.kld_bin_m).astype(np.int64)
        cells -= cells.min(axis=0)
        yaw = np.floor((wrap_angle(poses[:, 2]) + np.pi) / np.deg2rad(cfg.kld_bin_deg)).astype(np.int64)
        span = cells.max(axis=0) + 1
        keys = ((self.storeys[draws] * span[0] + cells[:, 0]) * span[1] + cells[:, 1]) * (yaw.max() + 1) + yaw
        first_in_bin = np.zeros(len(draws), bool)
        first_in_bin[np.unique(keys, return_index=True)[1]] = True
        need = np.maximum(kld_particle_count(np.cumsum(first_in_bin), cfg.kld_epsilon, cfg.kld_z), self.min_particles)
        enough = np.flatnonzero(np.arange(1, len(draws) + 1) >= need)
        return draws[: enough[0] + 1] if len(enough) else draws

    def estimate(self) -> PoseEstimate:
        """Weighted mean pose (circular yaw) and covariance on the storey with the most weight; its room id.

        Particles injected at the last resampling (`fresh`) are left out until a measurement has weighed them."""
        self._require_initialized()
        weights = self.estimation_weights()
        storey_weight = np.bincount(self.storeys, weights=weights, minlength=len(self.prior.storeys))
        storey = int(np.argmax(storey_weight))
        on_storey = (self.storeys == storey) & (weights > 0)
        mean, covariance = weighted_pose_stats(self.particles[on_storey], weights[on_storey])
        position_std = float(np.sqrt(max(np.linalg.eigvalsh(covariance[:2, :2])[-1], 0.0)))
        yaw_std = float(np.sqrt(covariance[2, 2]))
        share = float(storey_weight[storey] / storey_weight.sum())
        converged = (
            position_std < self.cfg.converged_pos_std_m
            and yaw_std < np.deg2rad(self.cfg.converged_yaw_std_deg)
            and share >= self.cfg.converged_storey_share
        )
        room_id = int(self.prior.room_at(mean[None, :2], storey)[0])
        return PoseEstimate(mean, storey, covariance, bool(converged), room_id, position_std, yaw_std, share)

    def step(
        self, odom_increment: np.ndarray | None, observations: Observations | None, scan: np.ndarray | None = None
    ) -> StepResult:
        """predict (when an increment is given) → update (by the observations and scan given) → resample → estimate."""
        if not self._initialized:
            self.initialize()
        timings: dict[str, float] = {}
        clock = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timings[name] = (now - clock) * 1e3
            clock = now

        if odom_increment is not None:
            self.predict(odom_increment)
        lap("predict")
        n_obs = 0 if observations is None else len(observations)
        self.update(observations, scan)
        fit = self.scan_fit
        lost_frames = self.lost_monitor.lost(fit, 0 if scan is None else len(scan)) if self.cfg.relocalize else 0
        if lost_frames:  # the kidnapped robot: start over from the whole building, weighed by this frame
            log.info("the belief no longer explains the scans (fit %.2f): particles spread over the building", fit)
            self.initialize()
            self.update(observations, scan)
        lap("update")
        ess = self.effective_sample_size()
        resampled, injected = self.resample_if_needed(observations, scan)
        lap("resample")
        estimate = self.estimate()
        lap("estimate")
        challenged = False
        if self.challenger is not None and not lost_frames:
            challenged = self.challenger.follow(odom_increment, observations, scan, estimate)
            if challenged:
                log.info("a challenger drawn from the observations explains the frames better: the belief moves there")
                estimate = self.estimate()
            lap("challenger")
        return StepResult(
            estimate,
            ess,
            resampled,
            injected,
            n_obs,
            timings,
            self.num_particles,
            fit,
            lost_frames > 0,
            lost_frames,
            challenged,
        )

    # -------------------------------------------------------------------------------- helpers

    def _normalise(self, when: str) -> None:
        total = self.weights.sum()
        if not np.isfinite(total) or total <= 0:
            log.warning("all particle weights are zero %s; resetting them to uniform", when)
            self.weights = np.full(self.num_particles, 1.0 / self.num_particles)
        else:
            self.weights /= total

    def _require_initialized(self) -> None:
        if not self._initialized:
            raise RuntimeError("SemanticMCL.initialize() must run before the filter is used")
