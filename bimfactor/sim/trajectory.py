"""Robot trajectories through the building: room-to-room goals, grid path planning, pure-pursuit driving.

The robot follows paths planned on the BIM's navigation graph (`bim.navigation`) with a unicycle pure-pursuit
controller within its speed and turn-rate limits, and takes a keyframe when its wheel odometry says one is due
(`odometry.keyframe_due`), until the trajectory has exactly T keyframes. Routes (`sim.trajectory.route`: `viewpoints`
or `rooms`) and storey routes through a portal (`TrajectorySimulator.storey_route`): docs/simulator.md.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from bimfactor.bim.navigation import PORTAL_REACH_M, NavGraph, box_distance, build_nav_graph
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config, load_config
from bimfactor.errors import BimfactorError, InputError
from bimfactor.odometry import keyframe_due
from bimfactor.sim.sensors import WheelOdometry
from bimfactor.types import wrap_angle

log = logging.getLogger(__name__)

MIN_ROOM_NODES = 25  # rooms with fewer planning nodes (1 m² at 0.2 m) are no start or goal (closets)
FIRST_GOAL_BUDGET = 0.6  # a goal lies within this share of the travel the remaining keyframes allow
MIN_GOAL_BUDGET_M = 5.0
GOAL_TOLERANCE_M = 0.15
SLOWDOWN_DISTANCE_M = 0.8  # the robot slows down linearly within this distance of a goal
MIN_SPEED_MPS = 0.1
ROTATE_IN_PLACE_RAD = math.radians(45.0)  # heading errors beyond this are turned out on the spot
MIN_LOOKAHEAD_M = 0.2
START_HEADING_STD_RAD = math.radians(20.0)
LEG_TIME_FACTOR = 4.0  # a leg that takes this many times its nominal duration is abandoned
MAX_LEGS_PER_STEP = 5  # a trajectory needing more legs than this per keyframe is stuck
LIFT_RIDE_S = 8.0  # a lift ride per floor, doors included
STAIR_SPEED_MPS = 0.3  # a stair climbed, along the straight line from its foot to its head
AFTER_CHANGE_KEYFRAMES = 10  # a storey route goes on at least this far on the other floor
_START_ORDER_STREAM = 0x57A7
_TRAJECTORY_STREAM = 0x7A1
ODOMETRY_STREAM = 0x0D0


class SimulationError(BimfactorError):
    """The simulated robot could not complete its trajectory (a planning or control failure)."""


@dataclass
class SimTrajectory:
    """Ground truth of one simulated drive, starting on `storey_index`.

    `poses` (K, 3) T_world_base at `times_s` (K,), every control step; `commands` (K, 2) the (v, ω) commanded
    from times_s[i] to times_s[i+1] (the last is zero); `keyframe_indices` (T,) the steps where frames are taken;
    `odometry` (T, 3) the wheel odometry's T_odom_base at them (`sim.sensors.WheelOdometry`); `storeys` (K,) the
    storey of each step (None: all on `storey_index`).
    """

    index: int
    seed: int
    storey_index: int
    times_s: np.ndarray
    poses: np.ndarray
    commands: np.ndarray
    keyframe_indices: np.ndarray
    odometry: np.ndarray
    goals: list[dict] = field(default_factory=list)
    storeys: np.ndarray | None = None

    @property
    def keyframe_storeys(self) -> np.ndarray:
        """(T,) the storey of each keyframe."""
        if self.storeys is None:
            return np.full(len(self.keyframe_indices), self.storey_index, np.int64)
        return self.storeys[self.keyframe_indices]

    @property
    def keyframe_poses(self) -> np.ndarray:
        """(T, 3) ground-truth T_world_base at the keyframes."""
        return self.poses[self.keyframe_indices]

    @property
    def keyframe_times_s(self) -> np.ndarray:
        return self.times_s[self.keyframe_indices]


# ------------------------------------------------------------------------------------------ trajectories


class Steering(Protocol):
    """Closes the loop around a drive (`TrajectorySimulator.trajectory(..., steer=)`): a localizer that sees each
    keyframe as it is taken and may send the robot to a goal of its own."""

    def on_keyframe(self, pose: np.ndarray, odom: np.ndarray, time_s: float, following: bool) -> np.ndarray | None:
        """A keyframe at the true (3,) pose, where the wheel odometry reads `odom` (3,): a goal (3,) x, y, yaw in the
        world to drive to now (in place of the last one; the pose itself: give the last one up), or None to drive on.
        `following`: the robot is on its way to the last goal given."""

    def on_arrival(self) -> np.ndarray | None:
        """The robot reached the last goal given: the next one, or None to go on with the route."""


class TrajectorySimulator:
    """Plans and drives trajectories on a prior; holds the planning graphs of its storeys."""

    def __init__(self, prior: BimPrior, cfg: Config, extra_obstacles: dict[int, np.ndarray] | None = None) -> None:
        self.prior = prior
        self.cfg = cfg
        tcfg = cfg.sim.trajectory
        radius = cfg.bim.grid.robot_radius_m
        self.graphs: dict[int, NavGraph] = {}
        self.rooms: dict[tuple[int, int], list[int]] = {}  # (storey, component) → usable rooms
        for layers in prior.storeys:
            if not layers.navigable.any():
                continue
            index = layers.storey.index
            extra = (extra_obstacles or {}).get(index)
            graph = build_nav_graph(prior, index, radius, max(tcfg.inflation_m, radius), extra)
            self.graphs[index] = graph
            for comp in np.unique(graph.node_component):
                in_comp = (graph.node_component == comp) & (graph.node_room >= 0)
                ids, counts = np.unique(graph.node_room[in_comp], return_counts=True)
                usable = [int(r) for r, n in zip(ids, counts, strict=True) if n >= MIN_ROOM_NODES]
                if len(usable) >= 2:
                    self.rooms[(index, int(comp))] = usable
        if not self.rooms:
            raise InputError(
                f"{prior.source_file}: no storey has two rooms joined by a doorway; nothing to drive between"
            )
        lookahead = 2 * math.sqrt(2) * (max(tcfg.inflation_m, radius) - radius)  # corner cut ≤ inflation margin
        self.lookahead_m = max(MIN_LOOKAHEAD_M, lookahead)
        self.views: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if tcfg.route == "viewpoints":
            visibility = prior.visibility or VisibilityTable.build(prior, cfg.bim.visibility, progress=False)
            self.views = {index: self._views(graph, visibility) for index, graph in self.graphs.items()}

    def _views(self, graph: NavGraph, visibility: VisibilityTable) -> tuple[np.ndarray, np.ndarray]:
        """(M,) objects in view within `view_radius_m` of each node and (M, 2) their centroid (NaN where none): what
        a viewpoint looks at. Doors are left out; line of sight is the prior's visibility table."""
        tcfg = self.cfg.sim.trajectory
        centroid = np.full((len(graph.node_xy), 2), np.nan)
        offsets, ids = visibility.candidates(graph.node_xy, graph.storey_index)
        xy = self.prior.object_positions()[:, :2]
        lookable = np.asarray([o.label != "door" for o in self.prior.objects], bool)
        owner = np.repeat(np.arange(len(graph.node_xy)), np.diff(offsets))
        near = lookable[ids] & (np.hypot(*(xy[ids] - graph.node_xy[owner]).T) <= tcfg.view_radius_m)
        owner, ids = owner[near], ids[near]
        count = np.bincount(owner, minlength=len(graph.node_xy))
        with np.errstate(invalid="ignore"):
            for axis in range(2):
                centroid[:, axis] = np.bincount(owner, xy[ids, axis], len(graph.node_xy)) / count
        return count, centroid

    def _has_viewpoint(self, storey: int, room: int) -> bool:
        if storey not in self.views:  # `rooms` routes
            return False
        in_room = self.graphs[storey].node_room == room
        return bool((self.views[storey][0][in_room] >= self.cfg.sim.trajectory.min_view_objects).any())

    def viewpoints(self, storey: int, nodes: np.ndarray) -> np.ndarray:
        """The nodes among `nodes` that are viewpoints, or all of them when none is (or routes are `rooms`)."""
        if storey not in self.views:
            return nodes
        good = nodes[self.views[storey][0][nodes] >= self.cfg.sim.trajectory.min_view_objects]
        return good if len(good) else nodes

    def start_rooms(self, seed: int) -> list[tuple[int, int, int]]:
        """(storey, component, room) of every usable room, in the seed's order, alternating between components."""
        rng = np.random.default_rng([seed, _START_ORDER_STREAM])
        groups = [[(s, c, r) for r in rng.permutation(rooms)] for (s, c), rooms in sorted(self.rooms.items())]
        groups = [sorted(g, key=lambda scr: not self._has_viewpoint(scr[0], scr[2])) for g in groups]  # stable
        groups = [groups[i] for i in rng.permutation(len(groups))]
        order = []
        for k in range(max(len(g) for g in groups)):
            order.extend(g[k] for g in groups if k < len(g))
        return [(int(s), int(c), int(r)) for s, c, r in order]

    def trajectory(self, index: int, seed: int, steer: Steering | None = None) -> SimTrajectory:
        """Trajectory `index` for `seed` (bit-for-bit reproducible): starts in the index-th room of the seed's order.

        With `steer`, the robot drives the route until the steering sends it to a goal, then to its goals (each
        reached, then turned to its heading) while it sends them; until it sends one, and between, the route."""
        order = self.start_rooms(seed)
        storey, comp, room = order[index % len(order)]
        rng = np.random.default_rng([seed, index, _TRAJECTORY_STREAM])
        graph = self.graphs[storey]
        rooms = self.rooms[(storey, comp)]
        steps = self.cfg.evaluation.trajectory_length

        # Start: a roomy node of the start room from which another room lies within the first goal's budget.
        budget = self._first_goal_budget_m(steps)
        in_comp = graph.node_component == comp
        others = np.flatnonzero(in_comp & np.isin(graph.node_room, [r for r in rooms if r != room]))
        to_other, _ = graph.shortest_paths(others)
        in_room = np.flatnonzero(in_comp & (graph.node_room == room))
        roomy = in_room[graph.node_clearance[in_room] >= graph.inflation_m]
        candidates = roomy if len(roomy) else in_room
        near = candidates[to_other[candidates] <= budget / 2]
        if len(near) == 0:
            near = candidates[to_other[candidates] <= np.quantile(to_other[candidates], 0.1)]
        near = self.viewpoints(storey, near)
        start_node = int(near[rng.integers(len(near))])
        driver = _Driver(self, graph, rng, self._wheels(index, seed), steps, steer)
        driver.run(start_node, rooms)
        return driver.trajectory(index, seed, storey)

    def portal_ways(self) -> list[tuple[int, int, int, int]]:
        """Every way between two floors the robot can take, in both directions: (portal id, from storey, its planning
        node there, to storey, its node there) for each two consecutive ends of a portal with a node within
        `PORTAL_REACH_M` of each."""
        nodes = {}
        for portal in self.prior.portals:
            for end in portal.ends:
                graph = self.graphs.get(end.storey_index)
                if graph is None:
                    continue
                gap = box_distance(graph.node_xy, end.box_xy)
                node = int(np.argmin(gap))
                if gap[node] <= PORTAL_REACH_M:
                    nodes[(portal.id, end.storey_index)] = node
        ways = []
        for portal in self.prior.portals:
            for a, b in zip(portal.ends, portal.ends[1:], strict=False):
                ka, kb = (portal.id, a.storey_index), (portal.id, b.storey_index)
                if ka in nodes and kb in nodes:
                    ways += [(portal.id, a.storey_index, nodes[ka], b.storey_index, nodes[kb])]
                    ways += [(portal.id, b.storey_index, nodes[kb], a.storey_index, nodes[ka])]
        return ways

    def storey_route(self, index: int, seed: int) -> SimTrajectory:
        """Trajectory `index` for `seed` that changes floor (module docstring): through the index-th way of
        `portal_ways`. SimulationError when the building has no way between floors the robot can take."""
        ways = self.portal_ways()
        if not ways:
            raise SimulationError(f"{self.prior.source_file}: no portal joins two floors the robot drives on")
        portal, storey, node, other, other_node = ways[index % len(ways)]
        rng = np.random.default_rng([seed, index, _TRAJECTORY_STREAM])
        graph, steps = self.graphs[storey], self.cfg.evaluation.trajectory_length
        # Start: a viewpoint in a room within the first goal's budget of the portal, at least a few metres off.
        budget = self._first_goal_budget_m(steps)
        dist, _ = graph.shortest_paths(node)
        roomy = (graph.node_room >= 0) & (graph.node_clearance >= graph.inflation_m) & np.isfinite(dist)
        near = np.flatnonzero(roomy & (dist <= budget / 2) & (dist >= MIN_GOAL_BUDGET_M))
        near = near if len(near) else np.flatnonzero(roomy)
        near = self.viewpoints(storey, near)
        start_node = int(near[rng.integers(len(near))])
        driver = _Driver(self, graph, rng, self._wheels(index, seed), steps // 2)
        driver.run(start_node, self._rooms_about(graph, start_node))
        pose = driver.drive_to(driver.last_pose, node)
        kind = self.prior.portals[portal].kind
        rank = self.prior.floor_rank()
        driver.go_through(pose, self.graphs[other], other_node, kind, abs(int(rank[other] - rank[storey])))
        driver.steps = max(steps, len(driver.keyframes) + AFTER_CHANGE_KEYFRAMES)
        driver.run(other_node, self._rooms_about(self.graphs[other], other_node), pose=driver.last_pose)
        return driver.trajectory(index, seed, storey)

    def _first_goal_budget_m(self, steps: int) -> float:
        """How far the first goal may lie: a share of the travel `steps` keyframes allow, at least a few metres."""
        return max(FIRST_GOAL_BUDGET * steps * self.cfg.localization.keyframe_distance_m, MIN_GOAL_BUDGET_M)

    def _wheels(self, index: int, seed: int) -> WheelOdometry:
        """The wheel odometry of route `index` for `seed` (its own random stream)."""
        return WheelOdometry(self.cfg.odometry.alpha, np.random.default_rng([seed, index, ODOMETRY_STREAM]))

    def _rooms_about(self, graph: NavGraph, node: int) -> list[int]:
        """The usable rooms of the node's component (its rooms where none is usable)."""
        comp = int(graph.node_component[node])
        rooms = self.rooms.get((graph.storey_index, comp))
        if rooms:
            return rooms
        in_comp = (graph.node_component == comp) & (graph.node_room >= 0)
        return [int(r) for r in np.unique(graph.node_room[in_comp])]


class _Driver:
    """Drives one trajectory: picks goals, plans, follows with pure pursuit, takes keyframes."""

    def __init__(
        self,
        sim: TrajectorySimulator,
        graph: NavGraph,
        rng: np.random.Generator,
        wheels: WheelOdometry,
        steps: int,
        steer: Steering | None = None,
    ) -> None:
        self.sim, self.graph, self.rng, self.wheels, self.steps, self.steer = sim, graph, rng, wheels, steps, steer
        self.redirect: np.ndarray | None = None  # a goal the steering sent, not yet driven to
        self.following = False
        robot, tcfg, steps_cfg = sim.cfg.sim.robot, sim.cfg.sim.trajectory, sim.cfg.localization
        self.dt = robot.control_dt_s
        self.v_max = robot.max_speed_mps
        self.w_max = math.radians(robot.max_turn_rate_deg_s)
        self.kf_distance = steps_cfg.keyframe_distance_m
        self.kf_angle = math.radians(steps_cfg.keyframe_angle_deg)
        self.min_goal_distance = tcfg.min_start_goal_m
        self.times: list[float] = []
        self.poses: list[tuple[float, float, float]] = []
        self.commands: list[tuple[float, float]] = []
        self.keyframes: list[int] = []
        self.odometry: list[np.ndarray] = []  # the wheel odometry's pose at each keyframe
        self.goals: list[dict] = []
        self.storeys: list[int] = []

    @property
    def last_pose(self) -> tuple[float, float, float]:
        return self.poses[-1]

    def trajectory(self, index: int, seed: int, storey: int) -> SimTrajectory:
        """What was driven, as a trajectory starting on `storey`."""
        return SimTrajectory(
            index=index,
            seed=seed,
            storey_index=storey,
            times_s=np.asarray(self.times),
            poses=np.asarray(self.poses),
            commands=np.asarray(self.commands),
            keyframe_indices=np.asarray(self.keyframes, np.int64),
            odometry=np.asarray(self.odometry),
            goals=self.goals,
            storeys=np.asarray(self.storeys, np.int64) if len(set(self.storeys)) > 1 else None,
        )

    def drive_to(self, pose: tuple[float, float, float], node: int) -> tuple[float, float, float]:
        """Drive from `pose` to a node (however many keyframes it takes)."""
        steps, self.steps = self.steps, 10**9
        dist, pred = self.graph.shortest_paths(self.graph.nearest_node(pose[:2]))
        if not np.isfinite(dist[node]):
            raise SimulationError(f"the portal on storey {self.graph.storey_index} cannot be reached from the route")
        pose = self._follow(pose, self.graph.plan(np.array(pose[:2]), pred, node))
        self.steps = steps
        return pose

    def go_through(self, pose: tuple[float, float, float], graph: NavGraph, node: int, kind: str, floors: int) -> None:
        """Through a portal to `node` of another floor's graph: a lift ride (the wheels still) or a stair climbed,
        time passing, no keyframe taken; the driver drives on on that floor."""
        start, end = np.array(pose[:2]), graph.node_xy[node]
        duration = LIFT_RIDE_S * floors if kind == "lift" else float(np.hypot(*(end - start))) / STAIR_SPEED_MPS
        n = max(1, math.ceil(duration / self.dt))
        for t in np.linspace(0.0, 1.0, n + 1)[1:]:
            xy = start if kind == "lift" else start + t * (end - start)
            self._log((float(xy[0]), float(xy[1]), pose[2]), keyframe=False)
        self.graph = graph
        self.storeys[-1] = graph.storey_index
        end_pose = (float(end[0]), float(end[1]), pose[2])
        self._log(end_pose, keyframe=False)

    def run(self, start_node: int, rooms: list[int], pose: tuple[float, float, float] | None = None) -> None:
        """Drive from `start_node` (from `pose` there, or a first keyframe of its own) to goals in `rooms` (other
        than the current one) until T keyframes are taken."""
        graph, node = self.graph, start_node
        for _ in range(MAX_LEGS_PER_STEP * self.steps):
            if len(self.keyframes) >= self.steps:
                return
            if self.redirect is not None and pose is not None:
                pose = self._redirected(pose)
                node = graph.nearest_node(pose[:2])
                continue
            xy = graph.node_xy[node] if pose is None else np.array(pose[:2])
            dist, pred = graph.shortest_paths(node)
            goal = self._pick_goal(xy, int(graph.node_room[node]), dist, rooms)
            path = graph.plan(xy, pred, goal)
            self.goals.append({"room_id": int(graph.node_room[goal]), "xy": [float(v) for v in graph.node_xy[goal]]})
            if pose is None:
                d = path[min(1, len(path) - 1)] - path[0]
                look = self._look_at(node)
                yaw = (math.atan2(d[1], d[0]) if look is None else look) + self.rng.normal(0.0, START_HEADING_STD_RAD)
                pose = (float(xy[0]), float(xy[1]), float(wrap_angle(yaw)))
                self._log(pose, keyframe=True)
            pose = self._follow(pose, path)
            if self.redirect is not None:
                continue
            node = goal if np.hypot(*(np.array(pose[:2]) - graph.node_xy[goal])) < 0.5 else graph.nearest_node(pose[:2])
            look = self._look_at(goal) if node == goal else None
            if look is not None:
                pose = self._turn_to(pose, look)
        raise SimulationError(f"the robot got stuck: {len(self.keyframes)} of {self.steps} keyframes after many goals")

    def _redirected(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """Drive to the steering's goal (the reachable node nearest to it, then its heading) and ask for the next; a
        goal that takes no keyframe to reach gives way to the route."""
        goal, self.redirect = self.redirect, None
        assert goal is not None
        graph, before = self.graph, len(self.keyframes)
        dist, pred = graph.shortest_paths(graph.nearest_node(pose[:2]))
        reachable = np.flatnonzero(np.isfinite(dist))
        target = int(reachable[np.argmin(np.hypot(*(graph.node_xy[reachable] - goal[:2]).T))])
        self.following = True
        pose = self._follow(pose, graph.plan(np.array(pose[:2]), pred, target))
        if self.redirect is None:
            pose = self._turn_to(pose, float(goal[2]))
        self.following = False
        if self.redirect is None and self.steer is not None and len(self.keyframes) < self.steps:
            self.redirect = self.steer.on_arrival()
        if len(self.keyframes) == before:
            self.redirect = None
        return pose

    def _pick_goal(self, xy: np.ndarray, current_room: int, dist: np.ndarray, rooms: list[int]) -> int:
        """A node in another room (a viewpoint in any room on `viewpoints` routes): preferably ≥ min_start_goal_m
        away and within the remaining travel budget."""
        graph = self.graph
        remaining = self.steps - len(self.keyframes)
        budget = max(FIRST_GOAL_BUDGET * remaining * self.kf_distance, MIN_GOAL_BUDGET_M)
        if self.sim.cfg.sim.trajectory.route == "rooms":
            rooms = [r for r in rooms if r != current_room] or rooms
        nodes = np.flatnonzero(np.isin(graph.node_room, rooms) & np.isfinite(dist))
        roomy = nodes[graph.node_clearance[nodes] >= graph.inflation_m]
        nodes = self.sim.viewpoints(graph.storey_index, roomy if len(roomy) else nodes)
        far = np.hypot(*(graph.node_xy[nodes] - xy).T) >= self.min_goal_distance
        within = dist[nodes] <= budget
        for pick in (far & within, within, far, np.ones(len(nodes), bool)):
            if pick.any():
                nodes = nodes[pick]
                break
        room_choice = self.rng.choice(np.unique(graph.node_room[nodes]))
        nodes = nodes[graph.node_room[nodes] == room_choice]
        return int(nodes[self.rng.integers(len(nodes))])

    def _look_at(self, node: int) -> float | None:
        """Heading from a viewpoint node to the centroid of what it sees; None on `rooms` routes or nothing seen."""
        views = self.sim.views.get(self.graph.storey_index)
        centroid = views[1][node] if views is not None else np.full(2, np.nan)
        if not np.isfinite(centroid).all():
            return None
        d = centroid - self.graph.node_xy[node]
        return math.atan2(d[1], d[0]) if np.hypot(*d) > 1e-6 else None

    def _turn_to(self, pose: tuple[float, float, float], yaw: float) -> tuple[float, float, float]:
        """Turn on the spot to `yaw` at the turn-rate limit, taking keyframes as usual."""
        while len(self.keyframes) < self.steps:
            error = float(wrap_angle(yaw - pose[2]))
            if abs(error) < 1e-3:
                break
            w = math.copysign(min(self.w_max, abs(error) / self.dt), error)
            self.commands[-1] = (0.0, w)
            pose = _integrate(pose, 0.0, w, self.dt)
            self._log(pose, keyframe=self._is_keyframe(pose))
            if self.redirect is not None:
                break
        return pose

    def _follow(self, pose: tuple[float, float, float], path: np.ndarray) -> tuple[float, float, float]:
        """Pure pursuit along `path` (P, 2) until the goal is reached or all keyframes are taken."""
        seg = np.diff(path, axis=0)
        seg_len = np.hypot(seg[:, 0], seg[:, 1])
        s_start = np.concatenate([[0.0], np.cumsum(seg_len)])
        total = float(s_start[-1])
        goal = path[-1]
        progress = 0.0
        nominal = total / self.v_max + 2 * math.pi / self.w_max
        max_steps = int(LEG_TIME_FACTOR * nominal / self.dt) + 1
        for _ in range(max_steps):
            x, y, _ = pose
            if math.hypot(goal[0] - x, goal[1] - y) < GOAL_TOLERANCE_M or len(self.keyframes) >= self.steps:
                return pose
            progress = self._progress(np.array([x, y]), path, seg, seg_len, s_start, progress)
            target = self._point_at(path, seg, seg_len, s_start, min(progress + self.sim.lookahead_m, total))
            v, w = self._command(pose, target, math.hypot(goal[0] - x, goal[1] - y))
            self.commands[-1] = (v, w)
            pose = _integrate(pose, v, w, self.dt)
            self._log(pose, keyframe=self._is_keyframe(pose))
            if self.redirect is not None:
                return pose
        log.warning("trajectory leg of %.1f m not finished in %d steps; choosing a new goal", total, max_steps)
        return pose

    @staticmethod
    def _progress(p, path, seg, seg_len, s_start, progress: float) -> float:
        """Arc length of the closest path point near the current progress (never going back)."""
        window = (s_start[:-1] <= progress + 1.0) & (s_start[1:] >= progress - 0.05)
        idx = np.flatnonzero(window)
        if len(idx) == 0:
            return progress
        rel = p - path[idx]
        t = np.clip(np.einsum("ij,ij->i", rel, seg[idx]) / np.maximum(seg_len[idx] ** 2, 1e-12), 0.0, 1.0)
        closest = path[idx] + t[:, None] * seg[idx]
        k = int(np.argmin(np.hypot(*(closest - p).T)))
        return max(progress, float(s_start[idx[k]] + t[k] * seg_len[idx[k]]))

    @staticmethod
    def _point_at(path, seg, seg_len, s_start, s: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(s_start, s, side="right") - 1, 0, len(seg) - 1))
        return path[k] + seg[k] * ((s - s_start[k]) / max(seg_len[k], 1e-12))

    def _command(self, pose, target: np.ndarray, goal_distance: float) -> tuple[float, float]:
        """Unicycle pure pursuit with speed and turn-rate limits; large heading errors are turned on the spot."""
        x, y, yaw = pose
        dx, dy = target[0] - x, target[1] - y
        lookahead = math.hypot(dx, dy)
        if lookahead < 1e-9:
            return 0.0, 0.0
        alpha = float(wrap_angle(math.atan2(dy, dx) - yaw))
        if abs(alpha) > ROTATE_IN_PLACE_RAD:
            return 0.0, math.copysign(min(self.w_max, abs(alpha) / self.dt), alpha)
        curvature = 2.0 * math.sin(alpha) / lookahead
        v = self.v_max * min(1.0, max(goal_distance / SLOWDOWN_DISTANCE_M, MIN_SPEED_MPS / self.v_max))
        if abs(v * curvature) > self.w_max:
            v = self.w_max / abs(curvature)
        return v, v * curvature

    def _is_keyframe(self, pose) -> bool:
        """Whether the wheel odometry has moved or turned a keyframe's worth since the last keyframe."""
        reading = self.wheels.read(np.asarray(self.poses[self.keyframes[-1]]), np.asarray(pose))
        return keyframe_due(np.zeros(3), reading, self.kf_distance, self.kf_angle)

    def _log(self, pose, keyframe: bool) -> None:
        self.times.append(len(self.times) * self.dt)
        self.storeys.append(self.graph.storey_index)
        self.poses.append(pose)
        self.commands.append((0.0, 0.0))
        if keyframe:
            last = np.asarray(self.poses[self.keyframes[-1]]) if self.keyframes else None
            self.odometry.append(np.zeros(3) if last is None else self.wheels.take(last, np.asarray(pose)).copy())
            self.keyframes.append(len(self.poses) - 1)
            if self.steer is not None:
                goal = self.steer.on_keyframe(np.array(pose), self.odometry[-1], self.times[-1], self.following)
                if goal is not None:
                    self.redirect = np.asarray(goal, float)


def _integrate(pose: tuple[float, float, float], v: float, w: float, dt: float) -> tuple[float, float, float]:
    """Exact unicycle motion for one step of constant (v, ω): the arc's chord, in a form stable for small ω."""
    x, y, yaw = pose
    half_turn = w * dt / 2
    chord = v * dt * (math.sin(half_turn) / half_turn if abs(half_turn) > 1e-12 else 1.0)
    heading = yaw + half_turn
    return x + chord * math.cos(heading), y + chord * math.sin(heading), float(wrap_angle(yaw + w * dt))


def standard_trajectories(prior: BimPrior, n: int = 6, seed: int = 0, cfg: Config | None = None) -> list[SimTrajectory]:
    """The n benchmark trajectories of a prior for a seed, with distinct starts (different rooms where possible).

    `cfg` defaults to the default configuration.
    """
    sim = TrajectorySimulator(prior, cfg if cfg is not None else load_config())
    return [sim.trajectory(k, seed) for k in range(n)]
