"""Trajectories: on indoor free space, room to room, T keyframes, distinct starts, reproducible, within limits."""

from __future__ import annotations

import math

import numpy as np

from bimfactor.bim.rooms import NO_ROOM, OUTSIDE
from bimfactor.odometry import keyframe_indices
from bimfactor.sim.trajectory import SimTrajectory, standard_trajectories

from .conftest import Building, config_with

DOORWAY_REACH_M = 1.0  # a pose in no room must be this close to a door of its storey


def test_every_pose_on_indoor_free_space(building: Building, six_trajectories: list[SimTrajectory]) -> None:
    prior, spec = building.prior, building.prior.grid
    min_clearance = building.cfg.bim.grid.robot_radius_m - spec.resolution_m
    for trajectory in six_trajectories:
        layers = prior.storeys[trajectory.storey_index]
        rc = spec.world_to_cell(trajectory.poses[:, :2])
        assert spec.contains(rc).all()
        clearance = layers.clearance_m[rc[:, 0], rc[:, 1]]
        labels = layers.room_labels[rc[:, 0], rc[:, 1]]
        assert clearance.min() >= min_clearance, f"trajectory {trajectory.index} comes within {clearance.min():.3f} m"
        assert (labels != OUTSIDE).all()
        in_room = labels >= 0
        assert layers.navigable[rc[in_room, 0], rc[in_room, 1]].all()
        # Poses in no room are in doorways: close to a door of the storey.
        doors = np.asarray([d.center_xy for d in prior.doors if d.storey_index == trajectory.storey_index])
        between = trajectory.poses[labels == NO_ROOM, :2]
        if len(between):
            gap = np.linalg.norm(between[:, None, :] - doors[None], axis=2).min(axis=1)
            assert gap.max() <= DOORWAY_REACH_M


def test_each_trajectory_has_exactly_t_steps(building: Building, six_trajectories: list[SimTrajectory]) -> None:
    for trajectory in six_trajectories:
        assert len(trajectory.keyframe_indices) == building.cfg.evaluation.trajectory_length == 50


def test_room_routes_visit_two_rooms(building: Building, config_overrides: list[str]) -> None:
    cfg = config_with(config_overrides, "sim.trajectory.route=rooms")
    for trajectory in standard_trajectories(building.prior, n=3, seed=0, cfg=cfg):
        assert len(trajectory.keyframe_indices) == 50
        rooms = building.prior.room_at(trajectory.keyframe_poses[:, :2], trajectory.storey_index)
        assert len(set(rooms[rooms >= 0].tolist())) >= 2, f"trajectory {trajectory.index} stays in one room"


def test_viewpoint_routes_start_looking_at_objects(building: Building, six_trajectories: list[SimTrajectory]) -> None:
    """The default routes start where ≥ 2 objects lie within the view radius in line of sight, facing them."""
    prior, tcfg = building.prior, building.cfg.sim.trajectory
    xy = prior.object_positions()[:, :2]
    lookable = np.asarray([o.label != "door" for o in prior.objects])
    facing = 0
    for trajectory in six_trajectories:
        start = trajectory.poses[0]
        _, ids = prior.visibility.candidates(start[None, :2], trajectory.storey_index)
        ids = ids[lookable[ids] & (np.linalg.norm(xy[ids] - start[:2], axis=1) <= tcfg.view_radius_m + 0.3)]
        assert len(ids) >= tcfg.min_view_objects, f"trajectory {trajectory.index} starts with nothing in view"
        bearing = np.arctan2(*(xy[ids] - start[:2]).mean(axis=0)[::-1]) - start[2]
        facing += abs((bearing + np.pi) % (2 * np.pi) - np.pi) < math.radians(60)
    assert facing >= 5  # the start heading is the look direction plus 20° (1 σ) noise


def test_starts_are_distinct_rooms(building: Building, six_trajectories: list[SimTrajectory]) -> None:
    starts = np.asarray([t.poses[0] for t in six_trajectories])
    gaps = np.linalg.norm(starts[:, None, :2] - starts[None, :, :2], axis=2) + np.eye(len(starts)) * 1e9
    assert gaps.min() > 0.5
    rooms = [int(building.prior.room_at(t.poses[:1, :2], t.storey_index)[0]) for t in six_trajectories]
    assert len(set(rooms)) == len(rooms), rooms  # both buildings have more than six usable rooms


def test_keyframes_every_distance_or_angle_of_odometry(
    building: Building, six_trajectories: list[SimTrajectory]
) -> None:
    """The drive takes its keyframes on what its wheel odometry reads, as the localizer's keyframe rule does: every
    keyframe is one to the rule, and the true motion between them is the rule's up to the odometry's noise."""
    tcfg, robot = building.cfg.localization, building.cfg.sim.robot
    distance, angle = tcfg.keyframe_distance_m, math.radians(tcfg.keyframe_angle_deg)
    max_step_m = robot.max_speed_mps * robot.control_dt_s
    for trajectory in six_trajectories:
        odometry, kf = trajectory.odometry, trajectory.keyframe_poses
        assert odometry.shape == kf.shape
        np.testing.assert_array_equal(keyframe_indices(odometry, distance, angle), np.arange(len(kf)))
        moved = np.linalg.norm(np.diff(kf[:, :2], axis=0), axis=1)
        turned = np.abs((np.diff(kf[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
        read = np.linalg.norm(np.diff(odometry[:, :2], axis=0), axis=1)
        # the odometry's noise (odometry.alpha: σ ≈ 22 % of a 0.5 m step) moves the true spacing off the rule's;
        # turns on the spot (a few centimetres of travel) read their heading with the noise of δrot1 and δrot2 both
        assert np.all(moved <= 3 * distance + max_step_m) and np.median(turned[moved < distance / 5]) < 2 * angle
        assert 0 < np.abs(read - moved).max() < distance
        assert trajectory.keyframe_indices[0] == 0
        assert np.all(np.diff(trajectory.keyframe_times_s) > 0)


def test_commands_within_limits_and_integrate_to_the_poses(
    building: Building, six_trajectories: list[SimTrajectory]
) -> None:
    robot = building.cfg.sim.robot
    for trajectory in six_trajectories:
        v, w = trajectory.commands.T
        assert v.min() >= 0 and v.max() <= robot.max_speed_mps + 1e-9
        assert np.abs(w).max() <= math.radians(robot.max_turn_rate_deg_s) + 1e-9
        # Independent midpoint integration of the commands reproduces the poses.
        p, dt = trajectory.poses, robot.control_dt_s
        mid = p[:-1, 2] + w[:-1] * dt / 2
        step = v[:-1] * dt * np.sinc(w[:-1] * dt / 2 / np.pi)
        predicted = p[:-1, :2] + step[:, None] * np.column_stack([np.cos(mid), np.sin(mid)])
        assert np.abs(predicted - p[1:, :2]).max() < 1e-9
        turn = (p[1:, 2] - p[:-1, 2] - w[:-1] * dt + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(turn).max() < 1e-9
        np.testing.assert_allclose(np.diff(trajectory.times_s), dt)


def test_reproducible_per_seed(building: Building, six_trajectories: list[SimTrajectory]) -> None:
    again = standard_trajectories(building.prior, n=2, seed=0, cfg=building.cfg)
    other = standard_trajectories(building.prior, n=2, seed=1, cfg=building.cfg)
    for first, second, third in zip(six_trajectories[:2], again, other, strict=True):
        assert np.array_equal(first.poses, second.poses)
        assert np.array_equal(first.commands, second.commands)
        assert np.array_equal(first.keyframe_indices, second.keyframe_indices)
        assert first.poses.shape != third.poses.shape or not np.array_equal(first.poses, third.poses)


class _SendOnce:
    """A steering that sends the robot to one goal at keyframe `at` and records the keyframes it sees."""

    def __init__(self, at: int, goal: np.ndarray) -> None:
        self.at, self.goal, self.seen, self.arrivals = at, goal, [], 0

    def on_keyframe(self, pose: np.ndarray, odom: np.ndarray, time_s: float, following: bool) -> np.ndarray | None:
        self.seen.append(np.array(pose))
        return self.goal if len(self.seen) == self.at + 1 else None

    def on_arrival(self) -> np.ndarray | None:
        self.arrivals += 1
        return None


def test_a_steering_sends_the_robot_to_its_goal_and_the_route_is_the_same_before(paper_floor) -> None:
    from bimfactor.sim.trajectory import TrajectorySimulator

    sim = TrajectorySimulator(paper_floor.prior, paper_floor.cfg)
    plain = sim.trajectory(0, 0)
    start = plain.keyframe_poses[3]
    graph = sim.graphs[plain.storey_index]
    dist, _ = graph.shortest_paths(graph.nearest_node(start[:2]))
    near = np.flatnonzero((dist > 3.0) & (dist < 5.0))  # a place 3-5 m of path away
    goal = np.array([*graph.node_xy[near[0]], 1.0])
    steer = _SendOnce(3, goal)
    steered = sim.trajectory(0, 0, steer=steer)
    kf = steered.keyframe_poses
    assert len(kf) == len(plain.keyframe_poses) == len(steer.seen)  # every keyframe went to the steering
    np.testing.assert_allclose(kf[:4], plain.keyframe_poses[:4])  # the route until the goal was sent
    reached = np.hypot(*(steered.poses[:, :2] - goal[:2]).T).argmin()
    assert np.hypot(*(steered.poses[reached, :2] - goal[:2])) < 0.3
    assert abs((steered.poses[reached:, 2] - goal[2] + np.pi) % (2 * np.pi) - np.pi).min() < 1e-2  # turned to it
    assert steer.arrivals == 1
