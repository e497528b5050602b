"""Semantic Monte Carlo localization (paper Sec. II.C): a particle filter over (x, y, yaw, storey) in the BIM.

One step (`SemanticMCL.step`) is the paper's loop:
1. predict:  move every particle by the odometry increment plus Gaussian noise (`motion`), through portals to other
             floors (`motion.PortalMotion`);
2. update:   weight ×= Π_m p_m(z | x), the measurement models' terms summed in log (`measurements`); normalise;
3. resample: when ESS < δ_ess·M (`resampling`); the recoveries (`recovery`) may redraw some particles elsewhere;
4. estimate: weighted mean x, y and circular mean yaw on the storey holding the most weight, and its room; `compact`
             when its spread and storey share pass `smcl.converged`, `converged` when every recovery also confirms it.
Recoveries act after the update (lost: spread again) and after the estimate (a challenger takes over). docs/filter.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.symmetry import Motion
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SmclConfig
from bimfactor.errors import InputError
from bimfactor.localization.measurements import FrameData, MeasurementModel, make_measurements
from bimfactor.localization.measurements.base import Term, Update
from bimfactor.localization.measurements.scan import ScanLikelihood
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.motion import PortalMotion, propagate
from bimfactor.localization.particles import FreeSpace, ParticleSampler
from bimfactor.localization.recovery import Recoveries, make_recoveries
from bimfactor.localization.resampling import make_resampler, systematic_resample
from bimfactor.localization.stats import effective_sample_size, weighted_pose_stats
from bimfactor.localization.twins import TwinEvidence
from bimfactor.progress import Laps
from bimfactor.types import Observations, wrap_angle

log = logging.getLogger(__name__)
EXIT_DRAWS = (
    5  # a particle a storey-change event moves to a portal's end is drawn up to this often onto navigable space
)


@dataclass
class PoseEstimate:
    """The filter's pose estimate: (3,) x, y, yaw in the world frame on `storey`, with its (3, 3) covariance.

    `compact`: one cluster on one storey (`smcl.converged`); `converged`: compact, and no recovery doubts it."""

    pose: np.ndarray
    storey: int
    covariance: np.ndarray
    converged: bool
    room_id: int
    position_std_m: float
    yaw_std_rad: float
    storey_share: float
    compact: bool = False


@dataclass
class StepResult:
    """One filter step: the estimate after it, the ESS before resampling, and what each part took."""

    estimate: PoseEstimate
    ess: float
    resampled: bool
    injected: int = 0  # particles the recoveries redrew at the resampling
    n_observations: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)
    n_particles: int = 0
    scan_fit: float | None = None  # the belief's predicted scan fit before the update (`Update.scan_fit`)
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


@dataclass(frozen=True)
class FilterModels:
    """What a filter weighs and draws with, built once per prior and shared with a challenger's filter."""

    prior: BimPrior
    free: FreeSpace
    semantic: SemanticLikelihood
    plates: PlateLikelihood
    scan: ScanLikelihood | None
    measurements: list[MeasurementModel]
    portals: PortalMotion | None = None

    @classmethod
    def build(cls, prior: BimPrior, visibility: VisibilityTable, cfg: SmclConfig) -> FilterModels:
        measurements = make_measurements(prior, visibility, cfg)
        by_kind = {type(m): m for m in measurements}
        return cls(
            prior,
            FreeSpace(prior),
            by_kind[SemanticLikelihood],
            by_kind[PlateLikelihood],
            by_kind.get(ScanLikelihood),
            measurements,
            PortalMotion.of_prior(prior),
        )


class SemanticMCL:
    """The S-MCL particle filter against one BimPrior; every random draw comes from `rng`. A given
    `num_particles` is fixed (benchmarks); otherwise `cfg.num_particles`, sized by `cfg.resampler`."""

    def __init__(
        self,
        prior: BimPrior,
        visibility: VisibilityTable,
        cfg: SmclConfig,
        rng: np.random.Generator,
        num_particles: int | None = None,
        models: FilterModels | None = None,
        twins: dict[int, Motion] | None = None,
    ) -> None:
        self.prior, self.cfg, self.rng = prior, cfg, rng
        self.min_particles = int(num_particles or cfg.num_particles)
        self.resampler = make_resampler(cfg.resampler, self.min_particles, fixed=num_particles is not None)
        self.max_particles = self.resampler.initial_count(self.min_particles)
        self.models = models or FilterModels.build(prior, visibility, cfg)
        m = self.models
        object_storey = np.asarray([o.storey_index for o in prior.objects], np.int64)
        self.sampler = ParticleSampler(m.free, m.semantic, m.plates, m.scan, cfg.motion, object_storey, rng)
        self.particles = np.zeros((self.max_particles, 3))
        self.storeys = np.zeros(self.max_particles, np.int64)
        self.weights = np.full(self.max_particles, 1.0 / self.max_particles)
        # Particles redrawn at the last resampling and not yet weighed by a measurement: left out of the estimate.
        self.fresh = np.zeros(self.max_particles, bool)
        self.recoveries: Recoveries = make_recoveries(cfg, m.plates, self.sampler, self._rival)
        # A belief on a storey with a twin place is converged only once the frames tell it from its twin.
        self.twin_evidence = TwinEvidence(twins, self._log_likelihood) if twins else None
        self._initialized = False

    def _rival(self, cfg: SmclConfig, n: int) -> SemanticMCL:
        """A filter of n particles over the same models, drawing from a generator spawned from this one's."""
        return SemanticMCL(self.prior, self.models.semantic.visibility, cfg, self.rng.spawn(1)[0], n, self.models)

    @property
    def num_particles(self) -> int:
        """The current particle count (a KLD resampler changes it at each resampling)."""
        return len(self.particles)

    # -------------------------------------------------------------------------------- the loop

    def step(
        self,
        odom_increment: np.ndarray | None,
        observations: Observations | None,
        scan: np.ndarray | None = None,
        storey_change: int = 0,
    ) -> StepResult:
        """predict (when an increment is given) → update → recover → resample → estimate → recover. `storey_change`:
        the floors the robot went up (+) or down (−) since the last step, when it was told (0: no word)."""
        if not self._initialized:
            self.initialize()
        frame = FrameData(observations, scan, storey_change)
        lap = Laps(per_second=1e3)
        # 1. Predict: the odometry increment, the motion noise and the portals.
        if odom_increment is not None:
            self.predict(odom_increment, storey_change)
        lap("predict")
        # 2. Update: weight ×= P(z | x), every measurement model's term.
        update = self.update(frame)
        # Recover, the kidnapped robot: a belief that no longer explains the data starts over, weighed by this frame.
        lost_frames = self.recoveries.lost(update, frame)
        if lost_frames:
            log.info("the belief no longer explains the frames: particles spread over the building")
            self.initialize()
            self.update(frame)
        lap("update")
        # 3. Resample when the ESS is low, redrawing what the recoveries ask for.
        ess = self.effective_sample_size()
        resampled, injected = self.resample(frame)
        lap("resample")
        # 4. Estimate.
        estimate = self.estimate()
        lap("estimate")
        # Recover, the look-alike place: take over a particle set that explains the frames decisively better.
        challenged = False
        if not lost_frames:
            taken = self.recoveries.challenge(odom_increment, frame, estimate, update.log_evidence)
            if taken is not None:
                log.info("a challenger explains the frames better: the belief moves there")
                self.adopt(*taken)
                challenged = True
            estimate = self.estimate()  # what the challenge found confirms the belief, or not
            lap("recover")
        return StepResult(
            estimate=estimate,
            ess=ess,
            resampled=resampled,
            injected=injected,
            n_observations=0 if observations is None else len(observations),
            timings_ms=lap.times,
            n_particles=self.num_particles,
            scan_fit=update.scan_fit,
            relocalized=lost_frames > 0,
            lost_frames=lost_frames,
            challenged=challenged,
        )

    def _terms(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> dict[str, Term]:
        """The terms of the measurement models that weigh this frame at the given poses, by model name."""
        terms = {}
        for model in self.models.measurements:
            term = model.weigh(particles, storeys, frame)
            if term is not None:
                terms[model.name] = term
        return terms

    def _log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> np.ndarray | None:
        """(M,) Σ_m ln p_m(z | x) of the measurement models that weigh this frame at the given poses; None if none."""
        terms = self._terms(particles, storeys, frame)
        return sum(term.log_likelihood for term in terms.values()) if terms else None

    def predict(self, odom_increment: np.ndarray, storey_change: int = 0) -> None:
        """Move the particles by a (3,) robot-frame odometry increment (dx, dy, dyaw) with the motion noise, and carry
        those that passed a portal to another floor (`motion.PortalMotion`; `storey_change` floors up or down when
        told, 0: no word)."""
        self._require_initialized()
        motion = self.cfg.motion
        before = self.particles
        self.particles = propagate(
            self.particles, odom_increment, motion.sigma_trans_m, np.deg2rad(motion.sigma_rot_deg), self.rng
        )
        portals = self.models.portals
        if portals is not None:
            self.storeys, could = portals.carry(
                before[:, :2],
                self.particles[:, :2],
                self.storeys,
                (motion.portal_share, motion.portal_cross_share),
                storey_change,
                self.rng,
            )
            if not could.all():  # they come out of a portal on the floor the event names (`PortalMotion.exits`)
                missed = np.flatnonzero(~could)
                xy, storeys = portals.exits(self.storeys[missed], storey_change, self.rng, self.on_navigable)
                placed = np.all(np.isfinite(xy), axis=1)
                yaw = self.rng.uniform(-np.pi, np.pi, int(placed.sum()))
                self.particles[missed[placed]] = np.column_stack([xy[placed], yaw])
                self.storeys[missed[placed]] = storeys[placed]
                self.weights[~could] *= motion.event_miss_weight
                self._normalise("after a storey change no particle could make")
        off_map = ~self.on_navigable(self.particles, self.storeys)
        if off_map.any():
            self.weights[off_map] *= motion.off_map_weight
            self._normalise("after leaving navigable space")

    def update(self, frame: FrameData) -> Update:
        """Weight ×= P(z | x) = Π_m p_m(z | x) over the measurement models that weigh this frame, and normalise; a
        frame with nothing to weigh by leaves the weights as they are. The recoveries watch the result."""
        self._require_initialized()
        terms = self._terms(self.particles, self.storeys, frame)
        if not terms:
            update = Update(self.weights, terms)
        else:
            if not np.all(self.weights >= 0) or self.weights.sum() <= 0:
                self.weights = np.full(self.num_particles, 1.0 / self.num_particles)
            log_likelihood = np.zeros(self.num_particles)
            for term in terms.values():
                log_likelihood += term.log_likelihood
            before = self.weights
            self.fresh[:] = False
            with np.errstate(divide="ignore"):
                log_w = np.log(before) + log_likelihood
            peak = log_w.max()
            self.weights = np.exp(log_w - peak) if np.isfinite(peak) else np.zeros_like(log_w)
            # ln Σ w_i p(z | x_i) over the (normalised) weights before the update: ln p(z | belief).
            log_evidence = float(peak + np.log(self.weights.sum())) if np.isfinite(peak) else None
            self._normalise("after the measurement update")
            update = Update(before, terms, log_evidence)
            if self.twin_evidence is not None:
                self.twin_evidence.observe(self.particles, self.storeys, before, log_likelihood, frame)
        self.recoveries.after_update(update, frame)
        return update

    def resample(self, frame: FrameData) -> tuple[bool, int]:
        """When ESS < δ_ess·M (or a recovery asks for a redraw), draw the particle set anew: the resampler keeps
        some, the injections redraw the rest (`Injection.draw`; uniformly over free space where they run short).
        Returns (resampled, particles redrawn)."""
        self._require_initialized()
        M = self.num_particles
        wanted = self._replacements(M)
        if self.effective_sample_size() >= self.cfg.ess_threshold * M and not any(wanted):
            return False, 0

        def recount(count: int) -> int:  # a resampler that changes the count asks the recoveries again
            wanted[:] = self._replacements(count, asked=list(wanted))
            return sum(wanted)

        keep = self.resampler.resample(self.weights, self.particles, self.storeys, sum(wanted), recount, self.rng)
        fresh, fresh_storeys = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
        for recovery, n in zip(self.recoveries.injections, wanted, strict=True):
            if n:
                poses, storeys = recovery.draw(n, frame)
                fresh.append(poses)
                fresh_storeys.append(storeys)
        missing = sum(wanted) - sum(len(p) for p in fresh)
        if missing > 0:
            poses, storeys = self.sampler.uniform(missing)
            fresh.append(poses)
            fresh_storeys.append(storeys)
        n_fresh = sum(len(p) for p in fresh)
        self.particles = np.concatenate([self.particles[keep], *fresh])
        self.storeys = np.concatenate([self.storeys[keep], *fresh_storeys])
        M = len(self.particles)
        self.weights = np.full(M, 1.0 / M)
        self.fresh = np.arange(M) >= M - n_fresh
        return True, n_fresh

    def _replacements(self, count: int, asked: list[int] | None = None) -> list[int]:
        """How many of `count` particles each recovery redraws at this resampling (`asked`: only those that asked
        before, for the count a resampler chose)."""
        out, room = [], count
        for k, recovery in enumerate(self.recoveries.injections):
            n = recovery.replacements(count, room) if asked is None or asked[k] else 0
            out.append(n)
            room -= n
        return out

    def estimate(self) -> PoseEstimate:
        """Weighted mean pose (circular yaw) and covariance on the storey with the most weight; its room id.

        Particles redrawn at the last resampling (`fresh`) are left out until a measurement has weighed them."""
        self._require_initialized()
        weights = self.estimation_weights()
        storey_weight = np.bincount(self.storeys, weights=weights, minlength=len(self.prior.storeys))
        storey = int(np.argmax(storey_weight))
        on_storey = (self.storeys == storey) & (weights > 0)
        mean, covariance = weighted_pose_stats(self.particles[on_storey], weights[on_storey])
        position_std = float(np.sqrt(max(np.linalg.eigvalsh(covariance[:2, :2])[-1], 0.0)))
        yaw_std = float(np.sqrt(covariance[2, 2]))
        share = float(storey_weight[storey] / storey_weight.sum())
        done = self.cfg.converged
        compact = bool(
            position_std < done.pos_std_m and yaw_std < np.deg2rad(done.yaw_std_deg) and share >= done.storey_share
        )
        converged = self._converged(compact, storey)
        room_id = int(self.prior.room_at(mean[None, :2], storey)[0])
        return PoseEstimate(mean, storey, covariance, converged, room_id, position_std, yaw_std, share, compact)

    def _converged(self, compact: bool, storey: int) -> bool:
        """A compact estimate on `storey` is converged when every recovery confirms it and the frames tell it from
        its twin place, if the storey has one."""
        settled = self.twin_evidence is None or self.twin_evidence.settled(storey)
        return compact and settled and self.recoveries.confirms()

    # -------------------------------------------------------------------------------- starting the belief

    def initialize(self, storeys: list[int] | None = None) -> None:
        """Particles (the resampler's initial count) uniform over the navigable space of the given storeys (None:
        all), equal weights. InputError for a storey the prior does not have."""
        n = self.models.free.n_storeys
        missing = sorted(set(storeys or []) - set(range(n)))
        if missing:
            raise InputError(f"storeys {missing} do not exist: the prior has storey{'s 0 …' if n > 1 else ''} {n - 1}")
        self._start(*self.sampler.uniform(self.max_particles, storeys))

    def initialize_around(self, pose: np.ndarray, storey: int, sigma_xy_m: float, sigma_yaw_rad: float) -> None:
        """M particles from a Gaussian about a (3,) pose guess on one storey (AMCL's initial pose), equal weights.

        Draws that fall off navigable space are drawn again; InputError when the storey does not exist or no draw
        lands on navigable space (a guess in another frame or unit, or inside a wall's block).
        """
        pose = np.asarray(pose, np.float64).reshape(3)
        if not 0 <= storey < self.models.free.n_storeys:
            raise InputError(
                f"initial pose: storey {storey} does not exist (the prior has {self.models.free.n_storeys})"
            )
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
        particles = particles[self.rng.integers(0, len(particles), n)] if len(particles) < n else particles[:n]
        self._start(particles, np.full(n, storey, np.int64))

    def set_particles(self, particles: np.ndarray, storeys: np.ndarray) -> None:
        """Start from the given (N, 3) poses on their (N,) storeys with equal weights."""
        particles = np.array(particles, np.float64).reshape(-1, 3)
        if len(particles) == 0:
            raise InputError("no particles to start the filter from")
        self._start(particles, np.array(storeys, np.int64))

    def adopt(self, particles: np.ndarray, storeys: np.ndarray, weights: np.ndarray) -> None:
        """Take another belief: this filter's particle count drawn from its weighted particles."""
        keep = systematic_resample(weights, self.num_particles, self.rng)
        self.set_particles(particles[keep], storeys[keep])

    def _start(self, particles: np.ndarray, storeys: np.ndarray) -> None:
        """The belief is these particles, equally weighted, none fresh; every recovery starts over."""
        self.particles, self.storeys = particles, storeys
        self.weights = np.full(len(particles), 1.0 / len(particles))
        self.fresh = np.zeros(len(particles), bool)
        self.recoveries.reset()
        if self.twin_evidence is not None:
            self.twin_evidence.reset()
        self._initialized = True

    # -------------------------------------------------------------------------------- helpers

    def effective_sample_size(self) -> float:
        return effective_sample_size(self.weights)

    def estimation_weights(self) -> np.ndarray:
        """The weights a pose estimate may use: those of the particles redrawn at the last resampling (`fresh`)
        are 0 until a measurement has weighed them (all of them stand when every particle is fresh)."""
        return np.where(self.fresh, 0.0, self.weights) if not self.fresh.all() else self.weights

    def on_navigable(self, particles: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(M,) bool: is each particle's position in navigable space of its storey?"""
        return self.models.free.contains(particles, storeys)

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
