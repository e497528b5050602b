"""The active scenario (`evaluation.scenario: active`): the simulated robot follows the localizer's suggestions.

From the uniform belief on route k, the robot drives its route until the localizer suggests where to look, then to
each suggested goal (given in the odometry frame, driven in the true world), asking again on arrival; T keyframes in
all. Beside it, from the same start and seeds, the passive route (its first T keyframes); both are scored from their
first frame, the active run's variants named with `+active`. docs/active.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.symmetry import Motion
from bimfactor.config import Config, updated
from bimfactor.evaluation.paper import (
    ACTIVE_SUFFIX,
    SERVED_BY,
    RunResult,
    forward_variants,
    online_config,
    run_seed,
    score_runs,
)
from bimfactor.pipeline import (
    GRAPH_VARIANTS,
    LocalizationRun,
    Localizer,
    LocalizerStep,
    localize_sequence,
    scan_matcher,
)
from bimfactor.sim.sensors import RgbdCamera
from bimfactor.sim.simulate import (
    SENSOR_STREAM,
    build_world,
    load_world_inputs,
    render_frame,
    sim_sequence_meta,
    sim_sequence_name,
    simulate_sequence,
    world_obstacles,
)
from bimfactor.sim.trajectory import TrajectorySimulator
from bimfactor.sim.world import SimWorld
from bimfactor.types import Frame, se2_compose, se2_inverse


@dataclass
class _Steer:
    """The closed loop (`sim.trajectory.Steering`): renders each keyframe, steps the localizer, turns its
    suggestions into goals in the true world."""

    localizer: Localizer
    camera: RgbdCamera
    elevation_m: float
    storey: int
    sensor_rng: np.random.Generator
    frames: list[Frame] = field(default_factory=list)
    rows: list[LocalizerStep] = field(default_factory=list)
    goals: list[dict] = field(default_factory=list)
    first_suggestion: int | None = None
    route: list[Frame] = field(default_factory=list)  # the passive route's frames, from the same start

    def route_ahead(self) -> np.ndarray | None:
        """(R, 3) the odometry poses of the route's next keyframes while the robot is still on the route (it has
        not left it for a goal: its last frame is the route's), None once it has."""
        k = len(self.frames) - 1
        if k + 1 >= len(self.route) or not np.allclose(self.frames[k].gt_pose, self.route[k].gt_pose, atol=1e-9):
            return None
        return np.asarray([f.odom_pose for f in self.route[k + 1 :]], float)

    def on_keyframe(self, pose: np.ndarray, odom: np.ndarray, time_s: float, following: bool) -> np.ndarray | None:
        frame = render_frame(
            self.camera, len(self.frames), float(time_s), pose, odom, self.storey, self.elevation_m, self.sensor_rng
        )
        step = self.localizer.step(frame)  # the drive takes keyframes by the localizer's own rule: never None
        assert step is not None, f"keyframe {frame.index} is no keyframe to the localizer"
        self.frames.append(frame)
        self.rows.append(step)
        if not following:
            return self._next_goal()
        # On the way: once nothing is to be told apart any more (one place holds the belief, or it converged, or it
        # spread out again), the goal is given up where the robot stands and it goes on with its route.
        return None if self.localizer.suggest(self.route_ahead()).goal_odom is not None else np.asarray(pose, float)

    def on_arrival(self) -> np.ndarray | None:
        return self._next_goal()

    def _next_goal(self) -> np.ndarray | None:
        """The localizer's suggestion as a goal in the true world: the odometry-frame goal carried by the true pose
        of the last keyframe (where the robot stands)."""
        suggestion = self.localizer.suggest(self.route_ahead())
        if suggestion.goal_odom is None:
            return None
        last = self.frames[-1]
        world_from_odom = se2_compose(last.gt_pose, se2_inverse(last.odom_pose))
        goal = se2_compose(world_from_odom, suggestion.goal_odom)
        if self.first_suggestion is None:
            self.first_suggestion = len(self.frames) - 1
        self.goals.append(
            {"keyframe": len(self.frames) - 1, "gain_nats": suggestion.gain_nats, "xy": [float(v) for v in goal[:2]]}
        )
        return goal


def active_route(
    prior_dir: str | Path,
    cfg: Config,
    trajectory: int,
    repeat: int,
    twins: dict[int, Motion],
    loaded: tuple[BimPrior, SimWorld] | None = None,
    route: list[Frame] | None = None,
) -> tuple[LocalizationRun, list[Frame], _Steer]:
    """One closed-loop run of route `trajectory` in the online variant `cfg.localization.variant`: the localizer's
    run, the frames it saw and the loop's record (goals, the keyframe of the first suggestion). `loaded`: the prior
    and the seed's world, when the caller has them; `route`: the passive route's frames, whose next keyframes the
    localizer scores as a candidate (`Localizer.suggest(route_odom)`) while the robot is on it."""
    if loaded is None:
        prior, model = load_world_inputs(prior_dir, cfg)
        loaded = prior, build_world(prior, model, cfg, cfg.seed)
    prior, world = loaded
    sim = TrajectorySimulator(prior, cfg, world_obstacles(prior, world, cfg))
    starts = sim.start_rooms(cfg.seed)
    storey = starts[trajectory % len(starts)][0]  # the route's storey, as `TrajectorySimulator.trajectory` picks it
    camera = RgbdCamera.from_config(world, cfg)
    # The passive route's name: its perception draws the same as the passive run's while the frames are the same.
    name = sim_sequence_name(prior, trajectory, cfg.seed)
    meta = sim_sequence_meta(name, prior, world, camera, {"trajectory_index": trajectory, "seed": cfg.seed})
    matcher = scan_matcher(prior, cfg) if cfg.localization.variant in GRAPH_VARIANTS else None
    localizer = Localizer(prior, meta, cfg, run_seed(cfg.seed, trajectory, repeat), matcher=matcher, twins=twins)
    steer = _Steer(
        localizer,
        camera,
        prior.storeys[storey].storey.elevation_m,
        storey,
        np.random.default_rng([cfg.seed, trajectory, SENSOR_STREAM]),
        route=list(route or []),
    )
    sim.trajectory(trajectory, cfg.seed, steer=steer)
    return localizer.run_of(steer.frames, steer.rows), steer.frames, steer


def active_runs(
    prior_dir: str | Path, cfg: Config, trajectory: int, repeat: int, twins: dict[int, Motion]
) -> list[RunResult]:
    """The passive route and the closed loop from the same start, each variant scored over its T keyframes from the
    first (the active run's named with `ACTIVE_SUFFIX`)."""
    ev = cfg.evaluation
    cfg = updated(cfg, {"evaluation.score_from": "start"})
    window = slice(0, ev.trajectory_length)
    prior, model = load_world_inputs(prior_dir, cfg)
    world = build_world(prior, model, cfg, cfg.seed)
    sim = simulate_sequence(prior, model, cfg, trajectory, cfg.seed, progress=False, world=world)
    online = forward_variants(ev.variants)
    matcher = scan_matcher(prior, cfg) if any(v in GRAPH_VARIANTS for v in online) else None
    seed = run_seed(cfg.seed, trajectory, repeat)
    passive = {
        v: localize_sequence(
            prior, sim.meta, sim.frames, online_config(cfg, v), seed, show_progress=False,
            matcher=matcher, twins=twins,
        )
        for v in online
    }  # fmt: skip
    results = score_runs(cfg, prior, sim.frames, passive, window, trajectory, repeat, twins, matcher)
    # Each online variant drives its own loop: score the variants it yields on its own frames.
    for k, v in enumerate(online):
        run, frames, _ = active_route(
            prior_dir, online_config(cfg, v), trajectory, repeat, twins, (prior, world), sim.frames
        )
        served = [x for x in ev.variants if x in SERVED_BY.get(v, {v}) or (x == "smcl" and k == 0)]
        own = updated(cfg, {"evaluation.variants": served})
        results += score_runs(own, prior, frames, {v: run}, window, trajectory, repeat, twins, matcher, ACTIVE_SUFFIX)
    return results
