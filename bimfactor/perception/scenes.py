"""Perception test drives: the camera circles groups of furniture, looking at them.

The standard trajectories see few objects in a sparse building; a furniture tour visits every group of objects (BIM
objects within `link_m` of each other) on a navigable arc `clearance_m` beyond it, so the front end and the graph see
objects from several sides (`bimfactor bench graph --tour`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior
from bimfactor.config import Config
from bimfactor.errors import InputError
from bimfactor.sim.sensors import RgbdCamera, simulate_odometry
from bimfactor.sim.simulate import SimResult, build_world, sim_sequence_meta
from bimfactor.types import Frame

TOUR_STREAM = 0x70C
_ARC_STEP_DEG = 10.0
_MAX_ARC_DEG = 180.0
_MIN_ARC_DEG = 40.0


@dataclass(frozen=True)
class FurnitureGroup:
    """An arc around a group of objects: centre (x, y), radius, start and end angle (deg, around the centre)."""

    centre_xy: tuple[float, float]
    radius_m: float
    start_deg: float
    end_deg: float
    object_ids: tuple[int, ...] = ()


def orbit_poses(group: FurnitureGroup, n: int) -> np.ndarray:
    """(n, 3) poses on the group's arc, each looking at its centre."""
    (cx, cy), angles = group.centre_xy, np.deg2rad(np.linspace(group.start_deg, group.end_deg, n))
    x, y = cx + group.radius_m * np.cos(angles), cy + group.radius_m * np.sin(angles)
    return np.column_stack([x, y, np.arctan2(cy - y, cx - x)])


def furniture_groups(
    prior: BimPrior, storey_index: int = 0, link_m: float = 2.5, clearance_m: float = 2.5, min_objects: int = 2
) -> list[FurnitureGroup]:
    """Groups of ≥ `min_objects` objects (doors and windows left out) and the longest navigable arc around each."""
    objects = [o for o in prior.objects if o.storey_index == storey_index and o.label not in ("door", "window")]
    if len(objects) < min_objects:
        return []
    xy = np.asarray([o.position_m[:2] for o in objects])
    _, component = connected_components(cdist(xy, xy) <= link_m, directed=False)
    navigable = prior.storeys[storey_index].navigable
    groups = []
    for c in np.unique(component):
        members = np.flatnonzero(component == c)
        if len(members) < min_objects:
            continue
        centre = xy[members].mean(axis=0)
        reach = [
            np.abs(np.subtract(objects[i].position_m[:2], centre)) + np.divide(objects[i].size_m[:2], 2)
            for i in members
        ]
        radius = float(np.max(reach) + clearance_m)
        angles = np.arange(0.0, 360.0, _ARC_STEP_DEG)
        ring = centre + radius * np.column_stack([np.cos(np.deg2rad(angles)), np.sin(np.deg2rad(angles))])
        cells = prior.grid.world_to_cell(ring)
        ok = prior.grid.contains(cells)
        ok[ok] = navigable[cells[ok, 0], cells[ok, 1]]
        start, length = _longest_circular_run(ok)
        if length * _ARC_STEP_DEG < _MIN_ARC_DEG:
            continue
        length = min(length, int(_MAX_ARC_DEG / _ARC_STEP_DEG) + 1)
        first = angles[start]
        groups.append(
            FurnitureGroup(
                (float(centre[0]), float(centre[1])),
                radius,
                float(first),
                float(first + (length - 1) * _ARC_STEP_DEG),
                tuple(int(objects[i].id) for i in members),
            )
        )
    return groups


def _longest_circular_run(flags: np.ndarray) -> tuple[int, int]:
    """(start index, length) of the longest run of True in a circular (N,) bool array."""
    n = len(flags)
    if flags.all():
        return 0, n
    best = (0, 0)
    doubled = np.concatenate([flags, flags])
    run_start, run = 0, 0
    for i, flag in enumerate(doubled):
        if flag:
            run_start, run = (i, 1) if run == 0 else (run_start, run + 1)
            if run > best[1] and run_start < n:
                best = (run_start, min(run, n))
        else:
            run = 0
    return best


def render_poses(
    prior: BimPrior,
    model: IfcModel,
    cfg: Config,
    poses: np.ndarray,
    storey_index: int = 0,
    seed: int = 0,
    name: str = "drive",
) -> SimResult:
    """Frames rendered at (N, 3) ground-truth poses, with wheel odometry from the motion model between them."""
    world = build_world(prior, model, cfg, seed)
    camera = RgbdCamera.from_config(world, cfg)
    rng = np.random.default_rng([seed, TOUR_STREAM])
    odom = simulate_odometry(poses, cfg.odometry.alpha, rng)
    elevation = prior.storeys[storey_index].storey.elevation_m
    frames = []
    for i, pose in enumerate(np.asarray(poses, float)):
        image = camera.render(pose, elevation, rng)
        frames.append(
            Frame(i, 0.5 * i, image.rgb, image.depth_m, odom[i], pose.copy(), storey_index, image.instance_ids)
        )
    meta = sim_sequence_meta(
        f"{name}-s{seed}", prior, world, camera, {"storey_index": storey_index, "seed": seed, "poses": "given"}
    )
    return SimResult(meta, frames, None)  # type: ignore[arg-type]  # no planned trajectory behind given poses


def furniture_tour(
    prior: BimPrior, model: IfcModel, cfg: Config, frames_per_group: int = 12, storey_index: int = 0, seed: int = 0
) -> SimResult:
    """One sequence orbiting every furniture group of a storey in turn (`frames_per_group` frames each)."""
    groups = furniture_groups(prior, storey_index)
    if not groups:
        raise InputError(f"storey {storey_index} of {prior.source_file} has no furniture group to orbit")
    poses = np.concatenate([orbit_poses(g, frames_per_group) for g in groups])
    name = f"tour-{Path(prior.source_file).stem}-st{storey_index}"
    return render_poses(prior, model, cfg, poses, storey_index, seed, name)
