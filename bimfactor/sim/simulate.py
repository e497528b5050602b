"""Simulate a whole RGB-D + odometry sequence over a BIM prior.

`simulate_sequence` is what `bimfactor simulate` runs: it builds the world from the IFC model, drives a
trajectory, takes odometry between keyframes and renders one RGB-D frame per keyframe. Nothing is written
to disk here (the sequence format is `bimfactor.io.sequence`'s job).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior, source_model
from bimfactor.config import Config, load_config
from bimfactor.errors import InputError
from bimfactor.progress import progress as progress_bar
from bimfactor.sim.sensors import RgbdCamera
from bimfactor.sim.trajectory import SimTrajectory, TrajectorySimulator
from bimfactor.sim.world import SimWorld
from bimfactor.types import STOREY_CHANGE, Frame, SequenceMeta, se2_between, se2_compose

log = logging.getLogger(__name__)

# Independent random streams of one (seed, trajectory): the world is shared by all trajectories of a seed.
WORLD_STREAM, SENSOR_STREAM = 0x3D, 0x5E5
ODOMETRY_STEP = "keyframe"  # the odometry motion model is applied to the increments between keyframes


@dataclass
class SimResult:
    """A simulated sequence: shared metadata, one frame per keyframe, and the dense ground truth and commands."""

    meta: SequenceMeta
    frames: list[Frame]
    trajectory: SimTrajectory


def world_rng(seed: int) -> np.random.Generator:
    """The generator of a seed's as-built world (the same for every trajectory of that seed)."""
    return np.random.default_rng([seed, WORLD_STREAM])


def build_world(prior: BimPrior, model: IfcModel, cfg: Config, seed: int) -> SimWorld:
    """The simulated world of a seed; raises InputError when the model is not the prior's IFC."""
    if model.sha256 != prior.source_sha256:
        raise InputError(
            f"IFC model {Path(model.source_path).name} (sha256 {model.sha256[:12]}…) is not the one the prior "
            f"was built from (sha256 {prior.source_sha256[:12]}…)"
        )
    return SimWorld.from_model(model, prior, cfg.sim.as_built, world_rng(seed), cfg.sim.door_plates)


def simulate_sequence(
    prior: BimPrior,
    model: IfcModel,
    cfg: Config,
    trajectory_index: int,
    seed: int,
    progress: bool = True,
    world: SimWorld | None = None,
    change_storey: bool = False,
) -> SimResult:
    """Simulate trajectory `trajectory_index` of `seed`: T keyframes of RGB-D, ground truth and wheel odometry.

    Reproducible bit for bit from (prior, model, cfg, trajectory_index, seed). Pass `world` (from `build_world`
    with the same seed) to reuse one world across trajectories. With `change_storey` the route goes through a
    portal to another floor (`TrajectorySimulator.storey_route`), and the first keyframe after it carries the
    storey-change event (`types.STOREY_CHANGE`) a robot's barometer or lift would give.
    """
    world = world if world is not None else build_world(prior, model, cfg, seed)
    simulator = TrajectorySimulator(prior, cfg, world_obstacles(prior, world, cfg))
    route = simulator.storey_route if change_storey else simulator.trajectory
    trajectory = route(trajectory_index, seed)
    gt, odom = trajectory.keyframe_poses, trajectory.odometry
    camera = RgbdCamera.from_config(world, cfg)
    sensor_rng = np.random.default_rng([seed, trajectory_index, SENSOR_STREAM])
    storey = trajectory.storey_index
    storeys = trajectory.keyframe_storeys
    floor = prior.floor_rank()
    frames = []
    times = trajectory.keyframe_times_s
    steps = range(len(gt))
    for i in progress_bar(steps, desc="simulating frames", unit="frame") if progress else steps:
        elevation = prior.storeys[storeys[i]].storey.elevation_m
        frames.append(render_frame(camera, i, float(times[i]), gt[i], odom[i], int(storeys[i]), elevation, sensor_rng))
        if i and storeys[i] != storeys[i - 1]:
            frames[-1].extras[STOREY_CHANGE] = float(floor[int(storeys[i])] - floor[int(storeys[i - 1])])
    meta = sim_sequence_meta(
        sim_sequence_name(prior, trajectory_index, seed),
        prior,
        world,
        camera,
        {
            "trajectory_index": trajectory_index,
            "seed": seed,
            "storey_index": storey,
            "odometry_step": ODOMETRY_STEP,
            "odometry_alpha": list(cfg.odometry.alpha),
            "goals": trajectory.goals,
            "as_built_changes": world.changes,
        },
    )
    log.info("simulated %s: %d frames on storeys %s", meta.name, len(frames), sorted(set(storeys.tolist())))
    return SimResult(meta, frames, trajectory)


def render_frame(
    camera: RgbdCamera,
    index: int,
    time_s: float,
    gt_pose: np.ndarray,
    odom_pose: np.ndarray,
    storey: int,
    elevation_m: float,
    rng: np.random.Generator,
) -> Frame:
    """Keyframe `index`: the RGB-D image rendered at the true (3,) pose on the storey, with its odometry pose."""
    image = camera.render(gt_pose, elevation_m, rng)
    return Frame(
        index=index,
        timestamp_s=time_s,
        rgb=image.rgb,
        depth_m=image.depth_m,
        odom_pose=odom_pose,
        gt_pose=np.array(gt_pose, float),
        gt_storey=storey,
        instance_ids=image.instance_ids,
    )


def world_obstacles(prior: BimPrior, world: SimWorld, cfg: Config) -> dict[int, np.ndarray] | None:
    """Per storey, the (rows, cols) cells the as-built world blocks beyond the BIM (moved furniture, clutter), which
    the simulated robot drives around; None when the world adds nothing."""
    if not any(c["kind"] in ("moved", "clutter") for c in world.changes):
        return None
    band = cfg.bim.grid
    return {
        layers.storey.index: world.added_obstacles(
            prior.grid,
            layers.storey.index,
            layers.storey.elevation_m + band.band_min_m,
            layers.storey.elevation_m + band.band_max_m,
        )
        for layers in prior.storeys
    }


def kidnap(first: list[Frame], second: list[Frame], at: int, resume_at: int) -> list[Frame]:
    """The kidnapped robot: `first`'s frames up to keyframe `at`, then `second`'s after keyframe `resume_at`.

    The robot is carried, not driven, to where `second` is at keyframe `resume_at`: the odometry says it stood still
    there, so that pose is no keyframe (`Localizer.due`), and the frames go on from `second`'s next, the odometry
    continuing from the last odometry pose of the first with `second`'s own increments while the ground truth jumps.
    Timestamps continue one keyframe interval later; frames are renumbered. Both parts must come from one building
    and one world (the same instance table).
    """
    if not 0 < at <= len(first) or not 0 <= resume_at < len(second) - 1:
        raise ValueError(f"kidnap at {at} of {len(first)} frames, resume at {resume_at} of {len(second)}: out of range")
    head, tail = first[:at], second[resume_at + 1 :]
    odom_from, odom_to = np.asarray(second[resume_at].odom_pose, float), np.asarray(head[-1].odom_pose, float)
    interval = float(np.median(np.diff([f.timestamp_s for f in first]))) if len(first) > 1 else 1.0
    shift = head[-1].timestamp_s + interval - tail[0].timestamp_s
    frames = list(head)
    for i, f in enumerate(tail):
        frames.append(
            replace(
                f,
                index=at + i,
                timestamp_s=f.timestamp_s + shift,
                odom_pose=se2_compose(odom_to, se2_between(odom_from, f.odom_pose)),
            )
        )
    return frames


def sim_sequence_name(prior: BimPrior, trajectory_index: int, seed: int) -> str:
    """The name of route `trajectory_index` of `seed`, which also seeds its sim perception's draws
    (`perception.pipeline.sim_rng`): a closed loop on the same route and seeds draws what its frames would."""
    return f"sim-{Path(prior.source_file).stem}-t{trajectory_index}-s{seed}"


def sim_sequence_meta(name: str, prior: BimPrior, world: SimWorld, camera: RgbdCamera, extras: dict) -> SequenceMeta:
    """The metadata of a simulated sequence: camera, mount, building, the world's instance table."""
    return SequenceMeta(
        name=name,
        source="sim",
        intrinsics=camera.intrinsics,
        T_base_camera=camera.T_base_camera.copy(),
        prior_sha256=prior.source_sha256,
        instances=[dict(rec) for rec in world.instances],
        extras=extras,
    )


def load_world_inputs(prior_dir: str | Path, cfg: Config | None = None) -> tuple[BimPrior, IfcModel]:
    """Load a prior folder and the IFC model it was built from (see `source_model`)."""
    cfg = cfg if cfg is not None else load_config()
    prior = BimPrior.load(prior_dir)
    return prior, source_model(prior, cfg, prior_dir)
