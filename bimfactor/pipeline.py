"""The localizer: runs the stages frame by frame (perception → online scene graph → semantic MCL → pose graphs).

`Localizer.step` reads like the method: perceive the frame and update the online graph at the odometry pose, take
the odometry increment, predict, weigh, resample, estimate; with `smcl+graph` each of the filter's modes updates its
own pose graph and the output is a mode's graph pose (`localization.output`); `full` also registers the keyframe's
depth scan against the BIM walls from the most probable mode only (a registration costs about the rest of the step,
docs/speed.md) and feeds an accepted fit into its graph. The offline pass is `bimfactor.refine.refine_run`.

Implausible frames are skipped (`FrameSkip`): depth with no return or all returns at one depth beyond the farthest
read (a stuck sensor), and odometry that moved faster than `MAX_ODOMETRY_SPEED_MPS`. A skipped frame still steps,
predicting without weighing. Across an odometry jump the step carries the previous increment; when the next frame
agrees with the last trusted one again (a glitch) its increment makes up the difference, and when it agrees only
with the jumped frame (a reset) the new odometry frame is mapped onto the old one.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import time
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, Self

import numpy as np
from scipy.special import expit

from bimfactor.active import Hypothesis, Suggester, Suggestion
from bimfactor.active.suggest import SEEN_VIEWS
from bimfactor.backend.posegraph import (
    BackendStep,
    ModeEstimate,
    ModeHistory,
    MultiHypothesisBackend,
    semantic_associator,
)
from bimfactor.backend.scan_factor import CorrelativeMatcher
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.symmetry import Motion, twin_motions
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from bimfactor.embed.text import TextEmbedder, make_text_embedder, text_model_name
from bimfactor.errors import ConfigError, InputError
from bimfactor.io.sequence import Sequence as SequenceFolder
from bimfactor.localization.filter import SemanticMCL, StepResult
from bimfactor.localization.measurements.scan import DepthPoints, frame_endpoints
from bimfactor.localization.modes import extract_modes
from bimfactor.localization.stats import (
    local_mean_yaw,
    mixture_pose_covariance,
    near_pose,
    weighted_geometric_median,
)
from bimfactor.odometry import keyframe_due, odometry_increment
from bimfactor.perception.base import Detection, TextReading
from bimfactor.perception.detections import DetectionsTable
from bimfactor.perception.ocr import plate_columns
from bimfactor.perception.pipeline import make_perception
from bimfactor.progress import progress
from bimfactor.registration.fine import FineRegistration, FineResult
from bimfactor.types import (
    Frame,
    Observations,
    SequenceMeta,
    se2_between,
    se2_compose,
    se2_inverse,
)

log = logging.getLogger(__name__)

GRAPH_VARIANTS = ("smcl+graph", "full")
"""Localizer variants that run the pose-graph back end (and so can be refined offline)."""
FINE_VARIANTS = ("full",)
"""Localizer variants that register each keyframe against the BIM walls and feed the fit back into the graph."""
TWIN_YAW_DEG = 45.0
"""A particle is at the output pose's twin within `localization.output_mode_radius_m` of it and this of its heading."""
MAX_ODOMETRY_SPEED_MPS = 5.0
"""Odometry that moved faster than this between two frames jumped: a ground robot indoors drives at up to about
2 m/s (a fast walk), so 5 m/s leaves room for wheel slip and timestamp jitter and still catches any glitch or reset."""
ODOMETRY_JUMP_SLACK_M = 0.5
"""Travel allowed between two frames on top of `MAX_ODOMETRY_SPEED_MPS` × their interval: frames with (nearly) the
same timestamp, or stamped late, still move a keyframe's spacing."""
SKIP_KINDS = ("empty_depth", "saturated_depth", "odometry_jump")
"""Why a frame is skipped, in the order the summary lists them."""
DEPTH_PART = "depth points and scan"
"""The keyframe's part of `LocalizerStep.perception_parts` that is not perception: its depth returns, back-projected
once for the scan term, the scan factors and the registrar, and the scan endpoints."""
PLATE_FORECAST_PARTICLES = 256
"""A real frame's text is read only in the image columns where one of this many particles, drawn from the belief by
weight, holds a door plate in reading range: a spread belief reads wherever plates can be, a settled one only where
its place has one (`Localizer._plate_columns`); a particle with 1/256 of the weight is drawn for sure."""


class _PerStep:
    """A dataclass whose every field holds one entry per step of a sequence."""

    def window(self, steps: slice) -> Self:
        """The same record over some of its steps."""
        return type(self)(*(getattr(self, f.name)[steps] for f in dataclasses.fields(self)))


@dataclass
class Track(_PerStep):
    """One estimator's output over a sequence: (T, 3) poses, (T, 3, 3) world-frame covariances, (T,) storeys and
    room ids, (T,) milliseconds per step that the estimator took."""

    poses: np.ndarray
    covariances: np.ndarray
    storeys: np.ndarray
    rooms: np.ndarray
    step_ms: np.ndarray


@dataclass
class FineTrack(_PerStep):
    """The fine stage over a run (variant full), one entry per step: (T,) whether it ran (a mode existed) and
    whether the fit was accepted, the gate's reasons when not, and (T,) milliseconds it took."""

    ran: np.ndarray
    accepted: np.ndarray
    reasons: list[list[str]]
    time_ms: np.ndarray

    def rejection_counts(self) -> dict[str, int]:
        """How often each kind of reason rejected a fit (`rejection_kind`), most frequent first."""
        counts = Counter(rejection_kind(r) for reasons in self.reasons for r in reasons)
        return dict(counts.most_common())

    def summary(self) -> dict:
        """Steps registered, accepted and rejected (they add up), and the rejection reasons by kind, which count
        reasons, not steps: a rejected fit can fail several gates (for metrics.json)."""
        registered, accepted = int(self.ran.sum()), int(self.accepted.sum())
        return {
            "steps_registered": registered,
            "steps_accepted": accepted,
            "steps_rejected": registered - accepted,
            "rejection_reasons": self.rejection_counts(),
        }


def rejection_kind(reason: str) -> str:
    """The kind of a gate reason, its words before the first number or colon ("fitness 0.71 < 0.90" → "fitness")."""
    return re.split(r"[:(<>]|\s[-+]?(?:\d|inf\b|nan\b)", reason, maxsplit=1)[0].strip()


@dataclass(frozen=True)
class FrameSkip:
    """Why the localizer skipped a frame: `kind` one of `SKIP_KINDS`; for an odometry jump `jump_m`, how far the
    odometry moved from the previous frame. `str()` is the reason as steps.csv's skipped column gives it."""

    kind: str
    jump_m: float = float("nan")

    def __str__(self) -> str:
        if self.kind == "odometry_jump":
            return f"odometry jump of {_metres(self.jump_m)} m"
        return self.kind.replace("_", " ")


def _metres(value: float) -> str:
    """A distance for people: 1.2, 350, 1e6."""
    if value >= 1e4:
        mantissa, exponent = f"{value:.1e}".split("e")
        return f"{mantissa.removesuffix('.0')}e{int(exponent)}"
    return f"{value:.3g}" if value < 100 else f"{value:.0f}"


def depth_problem(depth_m: np.ndarray, cfg: Config) -> FrameSkip | None:
    """Whether a depth image (metres, NaN / 0 = no return) is unusable: no return at all (`empty_depth`), or every
    return at one and the same depth, at or beyond the farthest depth the localizer reads (`perception.max_depth_m`,
    the scan ranges): a saturated or stuck sensor (`saturated_depth`; a real scene is never one depth everywhere,
    and a wall straight ahead is at one depth only within those ranges). None: usable."""
    depth = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        valid = depth[np.isfinite(depth) & (depth > 0)]
    if not valid.size:
        return FrameSkip("empty_depth")
    farthest = max(cfg.perception.max_depth_m, cfg.sensor.max_range_m)
    low, high = float(valid.min()), float(valid.max())
    if low == high and low >= farthest:
        return FrameSkip("saturated_depth")
    return None


def plausible_odometry_step(increment: np.ndarray, dt_s: float) -> bool:
    """Whether a ground robot can travel an odometry `increment` (dx, dy, dyaw) in `dt_s` seconds: at most
    `MAX_ODOMETRY_SPEED_MPS` × dt + `ODOMETRY_JUMP_SLACK_M`. (A turn cannot be told from its wrapped angle.)"""
    travel = float(np.hypot(increment[0], increment[1]))
    return travel <= MAX_ODOMETRY_SPEED_MPS * max(float(dt_s), 0.0) + ODOMETRY_JUMP_SLACK_M


@dataclass
class Keyframe:
    """One frame as every stage reads it, derived once (`Localizer.keyframe`): the frame (its odometry pose continuous
    with the earlier frames'), the odometry increment since the last trusted frame (None: the first), why the frame
    is skipped (None: it is not), its depth returns in the base frame, the scan endpoints cut from them (None
    without a scan term or scan factors), and what perception made of it (no node, no text when skipped): the nodes
    in view, and the image's detections and text readings behind them."""

    frame: Frame
    increment: np.ndarray | None
    skipped: FrameSkip | None
    points: DepthPoints | None
    scan: np.ndarray | None
    observations: Observations
    perception_ms: float
    perception_parts: dict[str, float]
    detections: list[Detection] = field(default_factory=list)
    readings: list[TextReading] = field(default_factory=list)

    @property
    def seen(self) -> Observations | None:
        """What the filter weighs: a skipped frame brings no observation, not an empty one."""
        return self.observations if self.skipped is None else None


@dataclass
class LocalizerStep:
    """One frame through the localizer: the filter's step, the back end's (None: smcl, or no mode yet), the
    output pose on its storey with its covariance and room, and what the frame brought."""

    filtered: StepResult
    graph: BackendStep | None
    pose: np.ndarray
    covariance: np.ndarray
    storey: int
    room_id: int
    observations: Observations
    odom_increment: np.ndarray | None
    perception_ms: float
    scan: np.ndarray | None = None
    graph_ms: float = 0.0
    fine: FineResult | None = None
    fine_ms: float = 0.0
    twin_pose: np.ndarray | None = None
    twin_share: float = float("nan")
    skipped: FrameSkip | None = None
    perception_parts: dict[str, float] = field(default_factory=dict)
    """How `perception_ms` divides: `plate forecast` (`Localizer._plate_columns`), `FrameResult.timing_ms` and
    `DEPTH_PART`."""

    @classmethod
    def of(cls, key: Keyframe, filtered: StepResult) -> LocalizerStep:
        """The step as the filter leaves it: its estimate is the output until a later stage reports another."""
        return cls(
            filtered,
            None,
            filtered.pose,
            filtered.covariance,
            filtered.storey,
            filtered.room_id,
            key.observations,
            key.increment,
            key.perception_ms,
            key.scan,
            skipped=key.skipped,
            perception_parts=key.perception_parts,
        )


@dataclass
class LocalizationRun:
    """What a localized sequence produced, one row per frame.

    `filter` is the particle filter's own estimate (every variant runs the filter); `graph` the most probable
    mode's (smcl+graph variants; where no mode exists yet, the filter's). `output` is the variant's estimate.
    `modes` lists every mode after each step (most probable first), `final_modes` the surviving modes' graphs,
    `retired_modes` the graphs of modes pruned after `backend.refine_retired_min_keyframes` keyframes,
    `odom_increments` (T−1, 3), `observations` and `scans` (the (N, 2) base-frame scan endpoints per step, None
    where no scan was taken) what the refinement re-uses; `fine` the fine stage per step (variant full);
    `snapshots` maps step → (particles, weights). On a building with twin storeys (`bim.symmetry.twin_motions`;
    otherwise None), `twin_poses` (T, 3) is where each step's twin motion carries the output pose and `twin_share`
    (T,) the belief's weight there (`TWIN_YAW_DEG`, `localization.output_mode_radius_m`); NaN on storeys without a
    twin. `skipped` (T,) says why each step's frame was skipped (`FrameSkip`; None: used); a run built without it
    (empty) skipped nothing. `suggestion`: where to look next after the last frame (`Localizer.suggest`), when asked.
    """

    variant: str
    timestamps_s: np.ndarray
    filter: Track
    converged: np.ndarray
    ess: np.ndarray
    n_observations: np.ndarray
    perception_ms: np.ndarray
    n_particles: np.ndarray
    scan_fit: np.ndarray  # (T,) the belief's predicted scan fit before each update; NaN without a scan
    lost_frames: np.ndarray  # (T,) int: where the filter spread its particles again, the frames it had been lost
    challenged: np.ndarray  # (T,) bool: where the belief took a challenger's particles (`smcl.challenger.enabled`)
    odom_increments: np.ndarray
    observations: list[Observations]
    scans: list[np.ndarray | None] = field(default_factory=list)
    graph: Track | None = None
    modes: list[list[ModeEstimate]] = field(default_factory=list)
    final_modes: list[ModeHistory] = field(default_factory=list)
    retired_modes: list[ModeHistory] = field(default_factory=list)
    fine: FineTrack | None = None
    gt_poses: np.ndarray | None = None
    gt_rooms: np.ndarray | None = None
    snapshots: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    twin_poses: np.ndarray | None = None
    twin_share: np.ndarray | None = None
    skipped: list[FrameSkip | None] = field(default_factory=list)
    suggestion: Suggestion | None = None

    @property
    def output(self) -> Track:
        return self.graph if self.graph is not None else self.filter

    @property
    def skip_reasons(self) -> list[str]:
        """(T,) why each step's frame was skipped ("empty depth", "odometry jump of 1e6 m"), "" where it was used."""
        reasons = ["" if skip is None else str(skip) for skip in self.skipped]
        return reasons + [""] * (len(self.timestamps_s) - len(reasons))

    @property
    def relocalized(self) -> np.ndarray:
        """(T,) bool: the filter spread its particles over the building again at this step (`smcl.relocalize`)."""
        return self.lost_frames > 0

    def segments(self) -> list[range]:
        """The run's continuous stretches, in order and covering every step: a relocalization at step k after the
        belief had been lost for n frames parts them before step k − n + 1, where the scans stopped fitting (the
        lost monitor's change point). A robot carried off, or whose wheels slipped away, is on another stretch of
        odometry there; a single trajectory cannot be smoothed across the seam."""
        T = len(self.timestamps_s)
        seams = [0]
        for k in np.flatnonzero(self.lost_frames):
            seams.append(max(int(k - self.lost_frames[k] + 1), seams[-1] + 1))
        return _stretches(seams, T)

    @property
    def poses(self) -> np.ndarray:
        return self.output.poses

    @property
    def covariances(self) -> np.ndarray:
        return self.output.covariances

    @property
    def storeys(self) -> np.ndarray:
        return self.output.storeys

    @property
    def rooms(self) -> np.ndarray:
        return self.output.rooms


def scan_matcher(prior: BimPrior, cfg: Config) -> CorrelativeMatcher | None:
    """The matcher of the graphs' scan factors (`backend.scan_factor`; None when off). Building it takes about a
    second on the paper floor (distance transforms of the whole grid), so a forward pass and its refinement share
    one."""
    return CorrelativeMatcher(prior, cfg.backend.scan_factor) if cfg.backend.scan_factor.enabled else None


def visibility_of(prior: BimPrior, cfg: Config) -> VisibilityTable:
    """The prior's stored visible-object table, or one built now for priors saved without it."""
    return prior.visibility or VisibilityTable.build(prior, cfg.bim.visibility)


class StepObserver(Protocol):
    """Watches a localizer's steps (`Localizer.watch`), e.g. to record them: called after each step's last stage with
    the localizer (its belief now), the keyframe and the step."""

    def on_step(self, localizer: Localizer, key: Keyframe, out: LocalizerStep) -> None: ...


class Localizer:
    """Global localization of one sequence against one prior, in the configured variant. `matcher` (graph variants'
    scan factors), `twins` (`bim.symmetry.twin_motions`) and `detections` (for the detections backend) are built or
    found when not given.
    """

    def __init__(
        self,
        prior: BimPrior,
        meta: SequenceMeta,
        cfg: Config,
        seed: int,
        text_embedder: TextEmbedder | None = None,
        matcher: CorrelativeMatcher | None = None,
        twins: dict[int, Motion] | None = None,
        detections: DetectionsTable | None = None,
    ) -> None:
        self.prior = prior
        self.twins = twin_motions(prior) if twins is None else twins
        self.meta = meta
        self.cfg = cfg
        self.variant = cfg.localization.variant
        embedding = text_embedder.name if text_embedder is not None else text_model_name(cfg.embed)
        if embedding != prior.embedding_model:
            raise ConfigError(
                f"the prior's objects are embedded with {prior.embedding_model}, but this run embeds with {embedding}: "
                "localize with the embed.* settings the prior was built with, or rebuild the prior with these"
            )
        embedder = text_embedder or make_text_embedder(cfg.embed)
        # The flag waits for evidence against look-alike places: the challenger's search, and the twin places the
        # building's symmetry names (with the challenger off, as in `paper`, the flag is the spread test alone).
        self.filter = SemanticMCL(
            prior,
            visibility_of(prior, cfg),
            cfg.smcl,
            np.random.default_rng([seed, 0x5CC1]),
            twins=self.twins if cfg.smcl.challenger.enabled else None,
        )
        # Door plates are read wherever the prior has room numbers to match them to (no OCR cost elsewhere).
        has_plates = bool(len(self.filter.models.plates))
        if cfg.perception.text.enabled and not has_plates:
            log.info("no door plates are read: the prior has no numbered rooms (IfcSpace Name beside a LongName)")
        self.perception = make_perception(
            cfg, meta, embedder, seed=seed, detections=detections, read_text=cfg.perception.text.enabled and has_plates
        )
        start = cfg.smcl.start
        self._start_belief(None if start.pose is None else [*start.pose[:2], np.deg2rad(start.pose[2])], start.storey)
        self.backend = (
            MultiHypothesisBackend.from_prior(prior, cfg.backend, cfg.odometry)
            if self.variant in GRAPH_VARIANTS
            else None
        )
        self.matcher = (matcher or scan_matcher(prior, cfg)) if self.backend else None
        self.fine = self._fine_stage(prior, cfg) if self.variant in FINE_VARIANTS else None
        # The variant is its chain of stages after the filter, each `(keyframe, step) -> None`.
        graph = (self._graph_step,) if self.backend is not None else ()
        fine = (self._fine_step,) if self.fine is not None else ()
        report = (self._report,) if self.backend is not None else ()
        self._stages = (*graph, *fine, *report, self._twin_step, self._remember)
        self._uses_scan = bool(cfg.smcl.scan.enabled or self.matcher)
        self._uses_depth = self._uses_scan or self.fine is not None
        # The frames before the current one that a submap stitches in (registration.submap_keyframes − 1).
        self._recent: deque[Frame] = deque(maxlen=cfg.registration.submap_keyframes - 1)
        # Odometry bookkeeping (`_odometry_step`): the last trusted frame's raw odometry pose and time, the previous
        # frame's, the motion guessed across jumps since the trusted frame, the increment of the last trusted step,
        # the odometry pose the filter believes at the last step, and the map of a re-based odometry onto the first.
        self._last_odom: np.ndarray | None = None
        self._last_odom_s = 0.0
        self._prev_odom = np.zeros(3)
        self._prev_odom_s = 0.0
        self._guessed: np.ndarray | None = None
        self._last_increment = np.zeros(3)
        self._believed_odom = np.zeros(3)
        self._odom_offset: np.ndarray | None = None
        self._converged = False  # the filter's flag at the last step
        self._suggester: Suggester | None = None  # built at the first `suggest`
        self._suggestion: Suggestion | None = None  # `suggest`'s answer for the belief after the last step
        self._suggested_route: bytes | None = None  # ... for this route (`suggest(route_odom)`)
        self._seen: deque[np.ndarray] = deque(maxlen=SEEN_VIEWS)  # odometry poses of the views the belief weighed

    @staticmethod
    def _fine_stage(prior: BimPrior, cfg: Config) -> FineRegistration:
        """The fine stage, whose surface models come from the prior's wall meshes; a prior without them says how to
        run without it."""
        try:
            return FineRegistration.for_prior(prior, cfg)
        except InputError as exc:
            raise InputError(
                f"{exc} (the full variant registers scans against its walls; --variant smcl+graph runs without it)"
            ) from exc

    def _start_belief(self, pose: np.ndarray | list[float] | None, storey: int) -> None:
        """The filter's particles: about a (3,) pose guess on a storey (AMCL's initial pose, `smcl.start.sigma_*`),
        or without one uniform over the building (over `smcl.start.storeys` when the robot knows its floor)."""
        start = self.cfg.smcl.start
        if pose is None:
            self.filter.initialize(start.storeys)
        else:
            self.filter.initialize_around(
                np.asarray(pose, float), storey, start.sigma_xy_m, np.deg2rad(start.sigma_yaw_deg)
            )

    def reset(self, pose: np.ndarray | list[float] | None = None, storey: int = 0) -> None:
        """Start the belief over, as an operator does mid-run: from a (3,) pose guess x, y, yaw (the BIM's world
        frame, metres and radians; AMCL's initial pose) on `storey`, or without one over the building (AMCL's global
        localization; over `smcl.start.storeys` when set). The back end's modes and the fine stage's submap start
        over too; the odometry and the online scene graph carry on. InputError for a guess with no navigable space
        about it."""
        self._start_belief(pose, storey)
        self._suggestion = None
        self._seen.clear()
        if self.backend is not None:
            self.backend = MultiHypothesisBackend.from_prior(self.prior, self.cfg.backend, self.cfg.odometry)
        self._recent.clear()

    def step(self, frame: Frame) -> LocalizerStep | None:
        """One camera frame: None unless it is a keyframe (`due`); a keyframe goes through the variant's fixed chain:
        the keyframe (odometry, depth checks, perception, scan), the filter, then the variant's stages (`_stages`:
        the back end, the fine stage, the output choice, the twin check, the submap). An implausible keyframe
        (`FrameSkip`: unusable depth, an odometry jump) is skipped: the filter only predicts, by the odometry
        increment or, across a jump, the previous step's."""
        if not self.due(frame):
            return None
        key = self.keyframe(frame)
        filtered = self.filter.step(key.increment, key.seen, key.scan, key.frame.storey_change)
        self._converged, self._suggestion = filtered.converged, None
        out = LocalizerStep.of(key, filtered)
        for stage in self._stages:
            stage(key, out)
        return out

    def due(self, frame: Frame) -> bool:
        """Whether `frame` is a keyframe: the first, one whose odometry has moved `localization.keyframe_distance_m` or
        turned `keyframe_angle_deg` since the last keyframe (`odometry.keyframe_due`), one with a storey-change event,
        or one without a finite odometry pose (for `keyframe` to refuse)."""
        raw = np.asarray(frame.odom_pose, float)
        if self._last_odom is None or not np.all(np.isfinite(raw)) or frame.storey_change:
            return True
        odom = raw if self._odom_offset is None else se2_compose(self._odom_offset, raw)
        steps = self.cfg.localization
        return keyframe_due(self._believed_odom, odom, steps.keyframe_distance_m, np.deg2rad(steps.keyframe_angle_deg))

    def keyframe(self, frame: Frame) -> Keyframe:
        """Derive what every stage reads from one frame, once: the odometry step and its checks, the depth checks, the
        depth returns, the scan endpoints and perception's observations (none for a skipped frame)."""
        if not np.all(np.isfinite(frame.odom_pose)):
            raise InputError(
                f"frame {frame.index} has no odometry pose: the localizer predicts each step from wheel odometry "
                "(a TUM RGB-D folder has none; convert a recording with an odometry topic)"
            )
        increment, frame, skipped = self._odometry_step(frame)
        skipped = skipped or depth_problem(frame.depth_m, self.cfg)
        started = time.perf_counter()
        if skipped is not None:
            log.info("frame %d skipped: %s", frame.index, skipped)
            return Keyframe(frame, increment, skipped, None, None, self._no_observations(), 0.0, {})
        self._seen.append(self._believed_odom.copy())  # a view the filter weighs (`suggest`)
        columns = self._plate_columns(increment)
        parts = {"plate forecast": (time.perf_counter() - started) * 1000}
        perceived = self.perception.step(frame, columns)
        parts.update(perceived.timing_ms)
        lifted = time.perf_counter()
        points = DepthPoints.of_frame(frame, self.meta) if self._uses_depth else None
        scan = frame_endpoints(points, self.cfg) if points is not None and self._uses_scan else None
        parts[DEPTH_PART] = (time.perf_counter() - lifted) * 1000
        perception_ms = (time.perf_counter() - started) * 1000
        return Keyframe(
            frame, increment, None, points, scan, perceived.observations, perception_ms, parts,
            perceived.detections, perceived.readings,
        )  # fmt: skip

    def _twin_step(self, key: Keyframe, out: LocalizerStep) -> None:
        """The belief's weight at the output pose's twin: nothing observed tells the output pose from it, but what
        only one place has."""
        twin = self.twins.get(out.storey)
        if twin is None:
            return
        out.twin_pose = twin.apply(out.pose[None])[0]
        weights = self.filter.estimation_weights()
        near = near_pose(
            self.filter.particles,
            self.filter.storeys,
            out.twin_pose,
            out.storey,
            self.cfg.localization.output_mode_radius_m,
            np.deg2rad(TWIN_YAW_DEG),
        )
        out.twin_share = float(weights[near].sum() / weights.sum())

    def watch(self, observer: StepObserver) -> None:
        """Show every later step to `observer`, after the variant's stages."""
        self._stages = (*self._stages, lambda key, out: observer.on_step(self, key, out))

    def _remember(self, key: Keyframe, out: LocalizerStep) -> None:
        """A used keyframe's frame joins the submap's recent frames."""
        if key.skipped is None:
            self._recent.append(key.frame)

    def _plate_columns(self, increment: np.ndarray | None) -> np.ndarray | None:
        """(W,) bool: the image columns where the belief, moved by this step's odometry, holds a door plate in reading
        range (`perception.ocr.plate_columns`) at one of `PLATE_FORECAST_PARTICLES` particles drawn by weight
        (systematically, with no random number: the filter's stream is not touched); None where the text reader
        reads everywhere anyway (the simulator's)."""
        reader = self.perception.reader
        if reader is None or not reader.wants_columns:
            return None
        plates, weights = self.filter.models.plates, self.filter.estimation_weights()
        cumulative = np.cumsum(weights)
        marks = (np.arange(PLATE_FORECAST_PARTICLES) + 0.5) * (cumulative[-1] / PLATE_FORECAST_PARTICLES)
        drawn = np.unique(np.minimum(np.searchsorted(cumulative, marks), len(weights) - 1))
        poses = se2_compose(self.filter.particles[drawn], np.zeros(3) if increment is None else increment)
        share = plate_columns(
            plates.ends, plates.normal, plates.storey, poses, self.filter.storeys[drawn], np.ones(len(drawn)),
            self.meta.intrinsics, self.meta.T_base_camera,
        )  # fmt: skip
        return share > 0

    def suggest(self, route_odom: np.ndarray | None = None) -> Suggestion:
        """Where to look next from the belief after the last step (`bimfactor.active`): the viewpoint, as a goal in the
        odometry frame, whose predicted views on the way and at it best tell the filter's modes apart less the way
        there, with its expected gain and path; or, with `goal_odom` None, the reason there is none (one place holds
        the belief, it has converged, it is still spread over the building, or the route's next views are worth
        more). `route_odom` (R, 3): the odometry poses of the keyframes the robot's route takes next, where it has
        one (`active.path_views` turns a planned path into them); the route is scored as a candidate of no cost.
        Asked again with the same route before the next step, the same answer."""
        route = None if route_odom is None else np.asarray(route_odom, float).reshape(-1, 3)
        key = None if route is None else route.tobytes()
        if self._suggestion is not None and self._suggested_route == key:
            return self._suggestion
        if self._suggester is None:
            visibility = self.filter.models.semantic.visibility
            self._suggester = Suggester(self.prior, visibility, self.cfg, self.meta, self.filter.models)
        weights = self.filter.estimation_weights()
        modes = extract_modes(self.filter.particles, weights, self.cfg.backend, self.filter.storeys)
        share = float(sum(m.weight for m in modes))
        hypotheses = []
        for m in modes:
            p = m.weight / share
            twin, evidence = self.twins.get(m.storey), self.filter.twin_evidence
            if twin is None or evidence is None:
                hypotheses.append(Hypothesis(m.mean, m.storey, p, m.covariance))
                continue
            # The mode's image in the twin place explains the frames worse by the twin evidence's nats, no more.
            image = float(expit(-evidence.nats))
            hypotheses.append(Hypothesis(m.mean, m.storey, p * (1 - image), m.covariance))
            hypotheses.append(Hypothesis(twin.apply(m.mean[None])[0], m.storey, p * image, m.covariance))
        self._suggestion = self._suggester.suggest(
            hypotheses, self._believed_odom, share, self._converged, np.asarray(self._seen), route
        )
        self._suggested_route = key
        return self._suggestion

    def run_of(self, frames: list[Frame], rows: list[LocalizerStep], snapshots: dict | None = None) -> LocalizationRun:
        """The run of the given frames from this localizer's steps over them, one each (ground truth carried along
        when the frames have it)."""
        gt = [f.gt_pose for f in frames]
        has_gt = all(g is not None for g in gt)
        gt_poses = np.asarray(gt, float) if has_gt else None
        gt_storeys = [f.gt_storey or 0 for f in frames]
        gt_rooms = (
            np.asarray([self.prior.room_at(p[None, :2], s)[0] for p, s in zip(gt_poses, gt_storeys, strict=True)])
            if gt_poses is not None
            else None
        )
        filter_ms = np.asarray([sum(r.filtered.timings_ms.values()) for r in rows])
        filtered = Track(
            poses=np.asarray([r.filtered.pose for r in rows]),
            covariances=np.asarray([r.filtered.covariance for r in rows]),
            storeys=np.asarray([r.filtered.storey for r in rows]),
            rooms=np.asarray([r.filtered.room_id for r in rows]),
            step_ms=filter_ms,
        )
        graph = None
        if self.backend is not None:
            graph = Track(
                poses=np.asarray([r.pose for r in rows]),
                covariances=np.asarray([r.covariance for r in rows]),
                storeys=np.asarray([r.storey for r in rows]),
                rooms=np.asarray([r.room_id for r in rows]),
                step_ms=filter_ms + np.asarray([r.graph_ms + r.fine_ms for r in rows]),
            )
        fine = None
        if self.fine is not None:
            fine = FineTrack(
                ran=np.asarray([r.fine is not None for r in rows], bool),
                accepted=np.asarray([r.fine is not None and r.fine.accepted for r in rows], bool),
                reasons=[list(r.fine.reasons) if r.fine is not None else [] for r in rows],
                time_ms=np.asarray([r.fine_ms for r in rows], float),
            )
        return LocalizationRun(
            variant=self.variant,
            timestamps_s=np.asarray([f.timestamp_s for f in frames]),
            filter=filtered,
            converged=np.asarray([r.filtered.converged for r in rows]),
            ess=np.asarray([r.filtered.ess for r in rows]),
            n_observations=np.asarray([r.filtered.n_observations for r in rows]),
            perception_ms=np.asarray([r.perception_ms for r in rows]),
            n_particles=np.asarray([r.filtered.n_particles for r in rows], np.int64),
            scan_fit=np.asarray([np.nan if r.filtered.scan_fit is None else r.filtered.scan_fit for r in rows], float),
            lost_frames=np.asarray([r.filtered.lost_frames for r in rows], np.int64),
            challenged=np.asarray([r.filtered.challenged for r in rows], bool),
            odom_increments=np.asarray([r.odom_increment for r in rows[1:]], float).reshape(-1, 3),
            observations=[r.observations for r in rows],
            scans=[r.scan for r in rows],
            graph=graph,
            modes=[r.graph.modes if r.graph is not None else [] for r in rows],
            final_modes=self.backend.histories() if self.backend is not None else [],
            retired_modes=list(self.backend.retired) if self.backend is not None else [],
            fine=fine,
            gt_poses=gt_poses,
            gt_rooms=gt_rooms,
            snapshots=snapshots or {},
            twin_poses=np.asarray([np.full(3, np.nan) if r.twin_pose is None else r.twin_pose for r in rows])
            if self.twins
            else None,
            twin_share=np.asarray([r.twin_share for r in rows]) if self.twins else None,
            skipped=[r.skipped for r in rows],
        )

    def _no_observations(self) -> Observations:
        """What a skipped frame brought: no node, no text (the run's record; the filter is given None)."""
        dim = self.prior.object_embeddings.shape[1]
        return Observations(np.zeros((0, dim), np.float32), np.zeros(0), np.zeros(0), [], np.zeros(0, np.int64), None)

    def _odometry_step(self, frame: Frame) -> tuple[np.ndarray | None, Frame, FrameSkip | None]:
        """The odometry increment of this step (None: the first), the frame with its odometry pose continuous with the
        earlier frames' (itself unless the odometry was re-based), and an odometry jump's `FrameSkip`; the jump handling
        is the module docstring's."""
        raw = np.asarray(frame.odom_pose, float)
        t = float(frame.timestamp_s)
        skipped = None
        if self._last_odom is None:
            increment = None
        else:
            from_trusted = odometry_increment(self._last_odom, raw)
            from_previous = odometry_increment(self._prev_odom, raw)
            if plausible_odometry_step(from_trusted, t - self._last_odom_s):
                increment = from_trusted if self._guessed is None else se2_between(self._guessed, from_trusted)
            elif self._guessed is not None and plausible_odometry_step(from_previous, t - self._prev_odom_s):
                increment = from_previous
                believed = se2_compose(self._believed_odom, increment)
                self._odom_offset = se2_compose(believed, se2_inverse(raw))
            else:
                increment = self._last_increment.copy()
                skipped = FrameSkip("odometry_jump", float(np.hypot(from_previous[0], from_previous[1])))
        if skipped is None:
            self._last_odom, self._last_odom_s, self._guessed = raw, t, None
            if increment is not None:
                self._last_increment = increment
            if self._odom_offset is None:
                believed = raw
            else:
                believed = se2_compose(self._odom_offset, raw)
                frame = dataclasses.replace(frame, odom_pose=believed)
        else:
            assert increment is not None
            self._guessed = increment if self._guessed is None else se2_compose(self._guessed, increment)
            believed = se2_compose(self._believed_odom, increment)
        self._prev_odom, self._prev_odom_s, self._believed_odom = raw, t, believed
        return increment, frame, skipped

    def _graph_step(self, key: Keyframe, out: LocalizerStep) -> None:
        """The filter's modes update their pose graphs; the most probable mode becomes the step's output."""
        assert self.backend is not None
        started = time.perf_counter()
        weights = self.filter.estimation_weights()
        modes = extract_modes(self.filter.particles, weights, self.cfg.backend, self.filter.storeys)
        models = self.filter.models
        associate = semantic_associator(models.semantic, models.plates, out.observations)
        scan_match = None if self.matcher is None or out.scan is None else self.matcher.factor_fn(out.scan)
        out.graph = self.backend.step(modes, out.odom_increment, out.observations, associate, None, scan_match)
        out.graph_ms = (time.perf_counter() - started) * 1000

    def _fine_step(self, key: Keyframe, out: LocalizerStep) -> None:
        """Register the keyframe's scan from the best mode's pose; an accepted fit enters that mode's graph, and the
        mode's updated estimate replaces it in the back-end step. Not before a first mode, nor on a skipped frame."""
        assert self.fine is not None and self.backend is not None
        if out.graph is None or key.skipped is not None:
            return
        started = time.perf_counter()
        best = out.graph.best
        scan = self.fine.scan(key.frame, self.meta, self._recent, points=key.points)
        gate_covariance = self.cfg.localization.fine_covariance_scale * best.covariance
        out.fine = self.fine.register_scan(scan, best.pose, best.storey, gate_covariance)
        if out.fine.accepted:
            pose, covariance = self.backend.add_pose_factor(
                best.mode_id, out.graph.index, out.fine.pose, out.fine.information_body
            )
            updated = dataclasses.replace(best, pose=pose, covariance=covariance)
            out.graph.best = out.graph.modes[0] = updated
        out.fine_ms = (time.perf_counter() - started) * 1000

    def _report(self, key: Keyframe, out: LocalizerStep) -> None:
        """The graph variants' output pose, storey and room (`localization.output`), with the whole belief's covariance
        about it: best_mode, the most probable mode's graph pose; belief_median, the graph pose of the most probable
        mode within `output_mode_radius_m` of the particles' weighted geometric median, else the median with the nearby
        particles' yaw."""
        cfg = self.cfg.localization
        if cfg.output == "best_mode":  # before a first mode: the filter's estimate
            source = out.graph.best if out.graph is not None else out.filtered
            pose, storey = source.pose, source.storey
        else:
            storey = out.filtered.storey
            on_storey = self.filter.storeys == storey
            weights = self.filter.estimation_weights()[on_storey]
            median = weighted_geometric_median(self.filter.particles[on_storey, :2], weights)
            near = [
                m
                for m in (out.graph.modes if out.graph is not None else [])
                if m.storey == storey and np.hypot(*(m.pose[:2] - median)) <= cfg.output_mode_radius_m
            ]
            if near:
                pose = max(near, key=lambda m: m.probability).pose
            else:
                yaw = local_mean_yaw(self.filter.particles[on_storey], weights, median, cfg.output_mode_radius_m)
                pose = np.array([*median, out.filtered.pose[2] if yaw is None else yaw])
        out.pose, out.storey = pose, storey
        out.covariance = belief_covariance(out)
        out.room_id = int(self.prior.room_at(pose[None, :2], storey)[0])


def belief_covariance(out: LocalizerStep) -> np.ndarray:
    """(3, 3) uncertainty of reporting the step's output pose: the second moment about it of the mixture of every
    mode (its graph's Gaussian, weighted by its probability × the particle weight the modes hold) and the filter's
    belief (weighted by the particle weight no mode holds). Converged, it is the reported mode's graph covariance;
    while other places keep weight, their distance enters, so the 95 % ellipse reaches the rival modes."""
    modes = out.graph.modes if out.graph is not None else []
    clustered = min(sum(m.particle_weight for m in modes), 1.0)
    means = [m.pose for m in modes] + [out.filtered.pose]
    covariances = [m.covariance for m in modes] + [out.filtered.covariance]
    weights = [clustered * m.probability for m in modes] + [1.0 - clustered]
    return mixture_pose_covariance(out.pose, np.array(means), np.array(covariances), np.array(weights))


def localize_sequence(
    prior: BimPrior,
    meta: SequenceMeta,
    frames: Iterable[Frame],
    cfg: Config,
    seed: int,
    snapshot_steps: Iterable[int] = (),
    text_embedder: TextEmbedder | None = None,
    show_progress: bool = True,
    matcher: CorrelativeMatcher | None = None,
    twins: dict[int, Motion] | None = None,
    detections: DetectionsTable | None = None,
    suggest: bool = False,
    observer: StepObserver | None = None,
) -> LocalizationRun:
    """Localize every frame of a sequence (`Localizer`; ground truth carried along); with `suggest` the run ends with
    where to look next, and `observer` watches every step. The frames are checked against the prior first
    (InputError); a sequence whose every frame is skipped is an InputError.
    """
    if not isinstance(frames, SequenceFolder):  # a sequence folder answers without loading its images
        frames = list(frames)
    check_sequence_against_prior(frames, prior)
    localizer = Localizer(prior, meta, cfg, seed, text_embedder, matcher, twins, detections)
    if observer is not None:
        localizer.watch(observer)
    frames = list(frames)
    snapshot_steps = set(snapshot_steps)
    rows: list[LocalizerStep] = []
    snapshots = {}
    if 0 in snapshot_steps:
        snapshots[-1] = (localizer.filter.particles.copy(), localizer.filter.weights.copy())
    iterator = progress(frames, desc=f"localize ({localizer.variant})", unit="frame") if show_progress else frames
    keyframes: list[Frame] = []
    for frame in iterator:
        step = localizer.step(frame)
        if step is None:
            continue
        keyframes.append(frame)
        rows.append(step)
        if len(rows) - 1 in snapshot_steps:
            snapshots[len(rows) - 1] = (localizer.filter.particles.copy(), localizer.filter.weights.copy())
    run = localizer.run_of(keyframes, rows, snapshots)
    if rows and all(step.skipped is not None for step in rows):
        raise InputError(f"sequence {meta.name}: no frame could be used, {skipped_frames_note(run)}")
    run.suggestion = localizer.suggest() if suggest else None
    return run


def skipped_frames_note(run: LocalizationRun, max_steps: int = 10) -> str | None:
    """One line on the frames a run skipped, e.g. "skipped 3 frames: 2 with empty depth (steps 4, 7), 1 with an
    odometry jump of 1e6 m (step 12)"; None when it skipped none. Each kind lists up to `max_steps` steps."""
    by_kind: dict[str, list[int]] = {kind: [] for kind in SKIP_KINDS}
    jumps: list[float] = []
    for step, skip in enumerate(run.skipped):
        if skip is not None:
            by_kind.setdefault(skip.kind, []).append(step)
            if skip.kind == "odometry_jump":
                jumps.append(skip.jump_m)
    total = sum(len(steps) for steps in by_kind.values())
    if not total:
        return None
    parts = []
    for kind, steps in by_kind.items():
        if not steps:
            continue
        n = len(steps)
        if kind == "odometry_jump":
            what = (
                f"an odometry jump of {_metres(jumps[0])} m"
                if n == 1
                else f"odometry jumps of up to {_metres(max(jumps))} m"
            )
        else:
            what = kind.replace("_", " ")
        listed = ", ".join(map(str, steps[:max_steps])) + (f", … ({n} in all)" if n > max_steps else "")
        parts.append(f"{n} with {what} ({'step' if n == 1 else 'steps'} {listed})")
    return f"skipped {total} frame{'s' if total > 1 else ''}: " + ", ".join(parts)


def check_sequence_against_prior(frames: Iterable[Frame], prior: BimPrior) -> None:
    """InputError unless the sequence's frames fit the prior: every ground-truth storey (`Frame.gt_storey`) one of
    the prior's storeys. Cheap for a sequence folder, which answers from its table without loading images."""
    if isinstance(frames, SequenceFolder):
        gt_storeys, frame_indices = frames.ground_truth_storeys(), [int(i) for i in frames.indices()]
    else:
        listed = list(frames)
        gt_storeys, frame_indices = [f.gt_storey for f in listed], [f.index for f in listed]
    n = len(prior.storeys)
    for step, (index, storey) in enumerate(zip(frame_indices, gt_storeys, strict=True)):
        if storey is not None and not 0 <= int(storey) < n:
            valid = "0" if n == 1 else f"0–{n - 1}"
            raise InputError(
                f"frame {int(index)} (step {step}): gt_storey {int(storey)} is not a storey of the prior, which has "
                f"{n} storey{'s' if n != 1 else ''} ({valid}); is the sequence from another building?"
            )


def building_mismatch(meta: SequenceMeta, prior: BimPrior) -> str | None:
    """A one-line message when the sequence records the building it was simulated in (`SequenceMeta.prior_sha256`,
    the SHA-256 of the IFC file its prior was built from) and that is not the file this prior was built from
    (`BimPrior.source_sha256`); None when they match or either does not say (converted real recordings record
    none)."""
    recorded = str(meta.prior_sha256 or "").strip().lower()
    built_from = str(prior.source_sha256 or "").strip().lower()
    if not recorded or not built_from or recorded == built_from:
        return None
    return (
        f"sequence {meta.name!r} was recorded in the building of IFC file sha256 {recorded[:12]}…, but the prior was "
        f"built from {Path(prior.source_file).name or 'an IFC file'} (sha256 {built_from[:12]}…): another building, "
        "or another version of it"
    )


def _stretches(seams: list[int], T: int) -> list[range]:
    """The stretches of T steps that begin at `seams` (the first 0), in order."""
    return [range(a, b) for a, b in zip(seams, [*seams[1:], T], strict=True)]
