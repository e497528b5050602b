"""Where to look next: active Markov localization (Burgard, Fox and Thrun 1997) with the BIM as the sensor model.

A candidate viewpoint c is a pose relative to the robot (the odometry frame); the BIM predicts what each of the
belief's places would show there (`active.views`), and the candidate scores its expected information gain about
which place is true, IG(c) = H(p) − Σ_k p_k · H(q(· | k)), less `cost_per_keyframe` per keyframe the drive takes.
Candidates, the cost and when nothing is suggested: docs/active.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from bimfactor.active.views import OBJECT_RECALL, PLATE_READ, ViewPredictor
from bimfactor.bim.navigation import PLANNING_CELL_M, NavGraph, build_nav_graph
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from bimfactor.localization.filter import FilterModels
from bimfactor.types import SequenceMeta, se2_compose, se2_inverse, wrap_angle

HEADINGS = 8  # candidate headings per position, 45° apart (half the field of view)
MIN_MODES_SHARE = 0.8  # below this share of the particle weight in the modes, the belief is not a few places
MIN_GAIN_NATS = 0.01  # a view that gains less than this tells the places apart by nothing
MIN_MOVE_M = 1.0  # a suggestion is a place to go: the view from where the robot stands the filter has just weighed
SAME_PLACE_M = 2.0  # modes closer than this on one storey are one place (a wrong convergence is one > 2 m off)
SNAP_M = 1.5 * PLANNING_CELL_M  # a candidate farther than this from a graph node is not on free space
SEEN_VIEWS = 30  # the views already weighed that a candidate's evidence is counted beyond (the last 15 m or 450°)
CLEARANCE_MARGIN_M = 0.1  # paths keep this much beyond the robot's radius from obstacles where they can
RESCORED = 8  # the candidates best by the screen that the filter's own update then scores over their whole way
PLACE_SAMPLES = 9  # poses of a place's spread the filter's update is averaged over (its mean and 8 fixed draws)
MAX_SPREAD_M, MAX_SPREAD_RAD = 1.0, np.deg2rad(30.0)  # a place is at most this wide (a mode wider is a spread belief)
# The chance a model's evidence is there to be seen: the detector's recall, a plate's read chance (the scan: always).
SEEN_CHANCE = {"semantic": OBJECT_RECALL, "text": PLATE_READ}
SEEN_STRIDE = 3  # of the views taken, every third (the last first) is scored by the filter's update
_DRAWS = np.random.default_rng(0).standard_normal((PLACE_SAMPLES - 1, 3))  # fixed: one answer per belief


@dataclass(frozen=True)
class Hypothesis:
    """One place the robot may be: (3,) world pose, storey, probability among the hypotheses."""

    pose: np.ndarray
    storey: int
    probability: float
    covariance: np.ndarray | None = None  # (3, 3) the pose's spread (world frame); None: a point


@dataclass
class Suggestion:
    """The next goal, or why there is none (`goal_odom` None and `reason`).

    `odom_pose` (3,) the robot's odometry pose the suggestion is for; `goal_odom` (3,) x, y, yaw in the odometry
    frame; `path_odom` / `path_world` (P, 2) the path to it in the odometry frame and in the most probable place's
    world frame (on `storey`); `gain_nats` the expected information gain of
    the views on the way and at the goal, `travel_m` the expected path length; `route_gain_nats` that of the route's
    next views (0 without a route). `candidates_odom` (C, 3) and `gains_nats` (C,) are every candidate scored,
    `seen_odom` (V, 3) the views already weighed (the route so far), for figures."""

    hypotheses: list[Hypothesis]
    odom_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    goal_odom: np.ndarray | None = None
    gain_nats: float = 0.0
    travel_m: float = 0.0
    storey: int = 0
    path_odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    path_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    candidates_odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gains_nats: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seen_odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    route_gain_nats: float = 0.0
    entropy_nats: float = 0.0
    reason: str = ""

    def describe(self) -> str:
        """One line on where to look next: the goal in the odometry frame and its gain, or why there is none."""
        if self.goal_odom is None:
            return f"nothing to suggest: {self.reason}"
        x, y, yaw = (float(v) for v in self.goal_odom)
        return (
            f"next: drive to ({x:.2f} m, {y:.2f} m, {math.degrees(yaw):.0f}°) in the odometry frame, "
            f"{self.travel_m:.1f} m away; its view is expected to tell the {len(self.hypotheses)} places apart by "
            f"{self.gain_nats:.2f} of {self.entropy_nats:.2f} nats"
        )

    def to_dict(self) -> dict:
        """JSON-ready: the goal (x, y in metres, yaw in degrees, odometry frame), gain, path and the hypotheses."""
        goal = None
        if self.goal_odom is not None:
            x, y, yaw = (float(v) for v in self.goal_odom)
            goal = {"x_m": x, "y_m": y, "yaw_deg": math.degrees(yaw), "frame": "odom"}
        return {
            "goal": goal,
            "odom_pose": {
                "x_m": float(self.odom_pose[0]),
                "y_m": float(self.odom_pose[1]),
                "yaw_deg": math.degrees(float(self.odom_pose[2])),
            },
            "reason": self.reason,
            "expected_gain_nats": self.gain_nats,
            "route_gain_nats": self.route_gain_nats,
            "belief_entropy_nats": self.entropy_nats,
            "travel_m": self.travel_m,
            "storey": self.storey,
            "path_odom": np.round(self.path_odom, 3).tolist(),
            "path_world": np.round(self.path_world, 3).tolist(),
            "hypotheses": [
                {
                    "x_m": float(h.pose[0]),
                    "y_m": float(h.pose[1]),
                    "yaw_deg": math.degrees(float(h.pose[2])),
                    "storey": h.storey,
                    "probability": h.probability,
                }
                for h in self.hypotheses
            ],
        }


def distinct_places(hypotheses: list[Hypothesis]) -> list[Hypothesis]:
    """The hypotheses as distinct places, most probable first: one within `SAME_PLACE_M` of a more probable one on its
    storey adds its probability to it (the views of two poses of one place differ by what tracking settles)."""
    places: list[Hypothesis] = []
    for h in sorted(hypotheses, key=lambda h: -h.probability):
        same = next(
            (
                k
                for k, p in enumerate(places)
                if p.storey == h.storey and np.hypot(*(p.pose[:2] - h.pose[:2])) < SAME_PLACE_M
            ),
            None,
        )
        if same is None:
            places.append(h)
        else:
            kept = places[same]
            places[same] = Hypothesis(kept.pose, h.storey, kept.probability + h.probability, kept.covariance)
    return places


def entropy(p: np.ndarray, axis: int = -1) -> np.ndarray:
    """Shannon entropy in nats of probabilities along `axis` (0 · ln 0 = 0)."""
    p = np.asarray(p, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(p > 0, -p * np.log(p), 0.0)
    return terms.sum(axis=axis)


def information_gain(probabilities: np.ndarray, discrepancy: np.ndarray) -> np.ndarray:
    """(C,) IG = H(p) − Σ_k p_k H(q(· | k)), q_j(· | k) ∝ p_j exp(−D[c, k, j]), for (K,) p and (C, K, K) D."""
    p = np.asarray(probabilities, float)
    with np.errstate(divide="ignore"):
        log_q = np.log(p)[None, None, :] - discrepancy
    log_q -= log_q.max(axis=-1, keepdims=True)
    q = np.exp(log_q)
    q /= q.sum(axis=-1, keepdims=True)
    return entropy(p) - (entropy(q) * p[None, :]).sum(axis=-1)


class Suggester:
    """Suggests the next viewpoint for a belief's hypotheses on one prior (`suggest`); navigation graphs are built
    per storey when first needed."""

    def __init__(
        self,
        prior: BimPrior,
        visibility: VisibilityTable,
        cfg: Config,
        meta: SequenceMeta | None = None,
        models: FilterModels | None = None,
    ) -> None:
        self.prior, self.cfg = prior, cfg
        self.models = models or FilterModels.build(prior, visibility, cfg.smcl)  # the filter's, when it runs
        field = None if self.models.scan is None else self.models.scan.field
        self.views = ViewPredictor(prior, visibility, cfg, meta, field)
        self._graphs: dict[int, NavGraph] = {}

    def graph(self, storey: int) -> NavGraph:
        if storey not in self._graphs:
            radius = self.cfg.bim.grid.robot_radius_m
            self._graphs[storey] = build_nav_graph(self.prior, storey, radius, radius + CLEARANCE_MARGIN_M)
        return self._graphs[storey]

    def suggest(
        self,
        hypotheses: list[Hypothesis],
        odom_pose: np.ndarray,
        modes_share: float = 1.0,
        converged: bool = False,
        seen_odom: np.ndarray | None = None,
        route_odom: np.ndarray | None = None,
    ) -> Suggestion:
        """The next goal for (K,) hypotheses (probabilities summing to 1, most probable first) at the robot's current
        odometry pose; `modes_share` is the particle weight the hypotheses hold, `converged` the filter's flag,
        `seen_odom` (V, 3) the odometry poses of the views the filter has weighed (the localizer keeps the last
        `SEEN_VIEWS`), `route_odom` (R, 3) the odometry poses of the keyframes the robot's route takes next (its
        planned path through `path_views`); those beyond `horizon_m` of path are not counted. The route is a
        candidate of no cost: where its views are worth as much as the best candidate's way, nothing is suggested."""
        cfg = self.cfg.active
        hyps = distinct_places(hypotheses)
        odom_pose = np.asarray(odom_pose, float)
        out = Suggestion(hyps, odom_pose, entropy_nats=float(entropy([h.probability for h in hyps])))
        out.seen_odom = np.zeros((0, 3)) if seen_odom is None else np.asarray(seen_odom, float).reshape(-1, 3)
        if not hyps:
            out.reason = "the belief has no modes"
            return out
        if converged:
            out.reason = "the belief has converged"
            return out
        if modes_share < MIN_MODES_SHARE:
            out.reason = f"the belief is still spread over the building (its modes hold {modes_share:.0%})"
            return out
        if hyps[0].probability >= cfg.settled_share:
            out.reason = f"one place holds {hyps[0].probability:.0%} of the belief"
            return out
        top = hyps[0]
        graph = self.graph(top.storey)
        start = graph.nearest_node(top.pose[:2])
        dist, pred = graph.shortest_paths(start, cfg.horizon_m)
        away = np.hypot(*(graph.node_xy - top.pose[:2]).T) >= MIN_MOVE_M
        reachable = np.flatnonzero(np.isfinite(dist) & away)
        if not len(reachable):
            out.reason = "no place within the horizon to go to"
            return out
        positions = reachable[_farthest_points(graph.node_xy[reachable], max(cfg.candidates // HEADINGS, 1))]
        yaws = np.arange(HEADINGS) * (2 * np.pi / HEADINGS)
        world = np.column_stack([np.repeat(graph.node_xy[positions], HEADINGS, axis=0), np.tile(yaws, len(positions))])
        to_robot = se2_inverse(top.pose)
        relative = se2_compose(to_robot, world)  # (C, 3) in the robot's frame
        poses = np.stack([se2_compose(h.pose, relative) for h in hyps], axis=1)  # (C, K, 3)
        storeys = np.asarray([h.storey for h in hyps], np.int64)
        p = np.asarray([h.probability for h in hyps], float)
        p /= p.sum()
        travel = np.full((len(relative), len(hyps)), np.inf)
        travel[:, 0] = np.repeat(dist[positions], HEADINGS)
        for k, h in enumerate(hyps[1:], start=1):
            travel[:, k] = self._travel(h, poses[:, k, :2])
        everywhere = np.isfinite(travel).all(axis=1)
        keep = everywhere if everywhere.any() else np.isfinite(travel[:, 0])
        # Screen: each candidate's goal view alone, by the BIM's discrepancy beyond what the views already weighed
        # show; the best few, and the route, are then scored by the filter's own update over their whole way.
        seen = se2_compose(se2_inverse(odom_pose), out.seen_odom)  # the views weighed, relative to the robot
        weighed = self._discrepancy(seen, hyps, storeys).max(axis=0) if len(seen) else 0.0
        screen = np.zeros(len(relative))
        screen[keep] = information_gain(p, np.maximum(self.views.discrepancy(poses[keep], storeys) - weighed, 0.0))
        expected_travel = np.where(np.isfinite(travel), travel, 0.0) @ p / np.maximum(np.isfinite(travel) @ p, 1e-12)
        keyframes = self._keyframes(relative, expected_travel)
        out.candidates_odom = se2_compose(odom_pose, relative[keep])
        out.gains_nats = screen[keep]
        screened = np.where(keep & (screen >= MIN_GAIN_NATS), screen - cfg.cost_per_keyframe * keyframes, -np.inf)
        shortlist = np.argsort(-screened, kind="stable")[:RESCORED]
        shortlist = shortlist[np.isfinite(screened[shortlist])]
        sampled = seen[::-SEEN_STRIDE][::-1]
        taken = self.update_evidence(sampled, hyps, storeys).max(axis=0) if len(sampled) else 0.0

        def beyond(views: np.ndarray) -> np.ndarray:
            """(V, K, K) the filter's update from the views at (V, 3) relative poses, each beyond what a view taken
            gave."""
            return np.maximum(self.update_evidence(views, hyps, storeys) - taken, 0.0)

        # A path's views are scored once for all the headings shortlisted at its end.
        spacing = self.cfg.localization.keyframe_distance_m
        paths = {int(c // HEADINGS): graph.plan(top.pose[:2], pred, int(positions[c // HEADINGS])) for c in shortlist}
        ways = {n: beyond(se2_compose(to_robot, path_views(path, spacing))).sum(axis=0) for n, path in paths.items()}
        gains = np.full(len(relative), -np.inf)
        for c, goal in zip(shortlist, beyond(relative[shortlist]), strict=True):
            gains[c] = float(information_gain(p, (ways[int(c // HEADINGS)] + goal)[None])[0])
        # The route's own next views: a candidate of no cost (the robot takes those keyframes anyway).
        route = self._route_ahead(odom_pose, route_odom)
        if len(route):
            out.route_gain_nats = float(information_gain(p, beyond(route).sum(axis=0)[None])[0])
        informative = gains >= MIN_GAIN_NATS
        if not informative.any():
            out.reason = "no reachable view within the horizon tells the places apart"
            return out
        score = np.where(informative, gains - cfg.cost_per_keyframe * keyframes, -np.inf)
        best = int(np.argmax(score))
        if len(route) and score[best] <= out.route_gain_nats:
            out.reason = "the route's next views are worth more"
            return out
        if score[best] <= 0:  # no view is worth its way: the route's own keyframes are worth more
            out.reason = "no view within the horizon is worth the way there"
            return out
        out.goal_odom = se2_compose(odom_pose, relative[best])
        out.gain_nats, out.travel_m, out.storey = float(gains[best]), float(expected_travel[best]), top.storey
        out.path_world = paths[best // HEADINGS]
        in_robot = se2_compose(to_robot, np.column_stack([out.path_world, np.zeros(len(out.path_world))]))
        out.path_odom = se2_compose(odom_pose, in_robot)[:, :2]
        return out

    def _discrepancy(self, relative: np.ndarray, hyps: list[Hypothesis], storeys: np.ndarray) -> np.ndarray:
        """(N, K, K) the BIM's discrepancy (`ViewPredictor.discrepancy`) of the views at (N, 3) poses relative to the
        robot."""
        return self.views.discrepancy(np.stack([se2_compose(h.pose, relative) for h in hyps], axis=1), storeys)

    def update_evidence(self, relative: np.ndarray, hyps: list[Hypothesis], storeys: np.ndarray) -> np.ndarray:
        """(V, K, K) E[v, k, j]: what the filter's own update takes against place j, in nats, from the view at each
        of (V, 3) poses relative to the robot when place k is true: ln p(z_kv | place k) − ln p(z_kv | place j), z_kv
        the frame the BIM predicts at place k's view v (`ViewPredictor.frames`), p(z | place) the filter's
        measurement models averaged over `PLACE_SAMPLES` poses of the place's spread. Each model's term is taken at
        the chance its evidence is seen (the detector's recall, a plate's read chance; the scan always)."""
        K, V = len(hyps), len(relative)
        if not V:
            return np.zeros((0, K, K))
        offsets = np.stack([_spread_offsets(h) for h in hyps])  # (K, S, 3) in each place's frame
        S = offsets.shape[1]
        # The particles of every place after each view's motion: (V, K·S, 3), on their places' storeys.
        starts = np.concatenate([se2_compose(h.pose, offsets[k]) for k, h in enumerate(hyps)])  # (K·S, 3)
        particles = np.stack([se2_compose(starts, np.broadcast_to(v, (K * S, 3))) for v in relative])
        particle_storeys = np.repeat(storeys, S)
        truths = np.stack([se2_compose(h.pose, relative) for h in hyps], axis=1).reshape(V * K, 3)
        frames = self.views.frames(truths, np.tile(storeys, V))
        evidence = np.zeros((V, K, K))
        for n, frame in enumerate(frames):
            v, k = divmod(n, K)
            log_p = np.zeros(K * S)
            for model in self.models.measurements:
                term = model.weigh(particles[v], particle_storeys, frame)
                if term is not None:
                    log_p += SEEN_CHANCE.get(model.name, 1.0) * term.log_likelihood
            per_place = logsumexp(log_p.reshape(K, S), axis=1) - np.log(S)
            evidence[v, k] = per_place[k] - per_place
        return evidence

    def _route_ahead(self, odom_pose: np.ndarray, route_odom: np.ndarray | None) -> np.ndarray:
        """(R, 3) the route's next keyframe poses relative to the robot, those within `horizon_m` of path."""
        if route_odom is None or not len(route_odom):
            return np.zeros((0, 3))
        route = se2_compose(se2_inverse(odom_pose), np.asarray(route_odom, float).reshape(-1, 3))
        along = np.cumsum(np.hypot(*np.diff(np.vstack([np.zeros((1, 2)), route[:, :2]]), axis=0).T))
        return route[along <= self.cfg.active.horizon_m]

    def _keyframes(self, relative: np.ndarray, travel_m: np.ndarray) -> np.ndarray:
        """(C,) keyframes the robot takes to reach each (C, 3) relative pose along paths of (C,) length: the distance
        per keyframe distance, the turns towards the goal and then to its heading per keyframe angle."""
        kf = self.cfg.localization
        towards = np.arctan2(relative[:, 1], relative[:, 0])
        moves = np.hypot(relative[:, 0], relative[:, 1]) >= kf.keyframe_distance_m
        turns = np.where(
            moves, np.abs(towards) + np.abs(wrap_angle(relative[:, 2] - towards)), np.abs(wrap_angle(relative[:, 2]))
        )
        return travel_m / kf.keyframe_distance_m + turns / np.deg2rad(kf.keyframe_angle_deg)

    def _travel(self, hypothesis: Hypothesis, xy: np.ndarray) -> np.ndarray:
        """(C,) path length from the hypothesis's pose to each (C, 2) point of its storey; inf off free space or beyond
        the horizon's reach (1.5 × horizon: the same motion may wind more in another place)."""
        graph = self.graph(hypothesis.storey)
        dist, _ = graph.shortest_paths(graph.nearest_node(hypothesis.pose[:2]), 1.5 * self.cfg.active.horizon_m)
        gap, node = graph.nearest_nodes(xy)
        return np.where(gap <= SNAP_M, dist[node], np.inf)


def path_views(path_xy: np.ndarray, spacing_m: float) -> np.ndarray:
    """(V, 3) the views the robot takes on its way along a (P, 2) path: one every `spacing_m` of path after its start
    and before its end, heading along the path (x, y, yaw)."""
    path_xy = np.asarray(path_xy, float).reshape(-1, 2)
    seg = np.diff(path_xy, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    seg, start, length = seg[length > 1e-9], path_xy[:-1][length > 1e-9], length[length > 1e-9]
    if not len(length):
        return np.zeros((0, 3))
    ends = np.cumsum(length)
    s = np.arange(1, int(np.ceil(ends[-1] / spacing_m))) * spacing_m
    s = s[s < ends[-1]]
    k = np.searchsorted(ends, s, side="right")
    t = (s - (ends[k] - length[k])) / length[k]
    xy = start[k] + t[:, None] * seg[k]
    return np.column_stack([xy, np.arctan2(seg[k, 1], seg[k, 0])])


def _spread_offsets(hypothesis: Hypothesis) -> np.ndarray:
    """(PLACE_SAMPLES, 3) poses of the place's spread in its own frame: the mean, then fixed normal draws scaled by
    its position spread (the covariance's mean xy variance, so in any frame) and its heading spread, each capped."""
    offsets = np.zeros((PLACE_SAMPLES, 3))
    if hypothesis.covariance is not None:
        cov = np.asarray(hypothesis.covariance, float)
        xy = min(float(np.sqrt(max(np.trace(cov[:2, :2]) / 2, 0.0))), MAX_SPREAD_M)
        yaw = min(float(np.sqrt(max(cov[2, 2], 0.0))), MAX_SPREAD_RAD)
        offsets[1:] = _DRAWS * np.array([xy, xy, yaw])
    return offsets


def _farthest_points(xy: np.ndarray, n: int) -> np.ndarray:
    """Indices of up to n of the (M, 2) points, each the farthest from those before (the first is the first point)."""
    if len(xy) <= n:
        return np.arange(len(xy))
    chosen = [0]
    gap = np.hypot(*(xy - xy[0]).T)
    for _ in range(n - 1):
        k = int(np.argmax(gap))
        chosen.append(k)
        gap = np.minimum(gap, np.hypot(*(xy - xy[k]).T))
    return np.asarray(chosen)
