"""Active localization: the expected information gain of a view, and the suggestions built on it."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bimfactor.active import Hypothesis, Suggester, information_gain, path_views
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from bimfactor.types import se2_compose, se2_inverse
from tests.active.twins import SHIFT_M, make_twin_prior

IN_A = np.array([3.1, 6.5, -np.pi / 2])  # in room A facing its door
IN_B = IN_A + np.array([SHIFT_M, 0.0, 0.0])  # the same place in room B
CORRIDOR_A = np.array([1.5, 1.5, 0.0])  # in unit A's corridor, 1.6 m west of its door, looking along it
CORRIDOR_B = CORRIDOR_A + np.array([SHIFT_M, 0.0, 0.0])


@pytest.fixture(scope="module")
def twins(test_config: Config) -> Suggester:
    prior = make_twin_prior()
    return Suggester(prior, VisibilityTable.build(prior, test_config.bim.visibility, progress=False), test_config)


def _gain(suggester: Suggester, relative: np.ndarray) -> float:
    """IG of the view `relative` to the robot for an even belief over room A and room B."""
    poses = np.stack([se2_compose(IN_A, relative), se2_compose(IN_B, relative)])[None]
    D = suggester.views.discrepancy(poses, np.zeros(2, np.int64))
    return float(information_gain(np.array([0.5, 0.5]), D)[0])


def test_a_view_of_the_plate_separates_the_twins_and_a_view_inside_them_does_not(twins: Suggester) -> None:
    through_the_door_and_back = np.array([5.5, 0.0, np.pi])  # 5.5 m ahead (south), turned to face the door 2 m off
    turned_round_inside = np.array([0.0, 0.0, np.pi])  # the room's far wall, its table: the same in both rooms
    plate_view, room_view = _gain(twins, through_the_door_and_back), _gain(twins, turned_round_inside)
    assert plate_view > 0.2  # of ln 2: a plate is read with probability 0.6, not surely (KL(0.6 ‖ ε) = 1.7 nats)
    assert room_view < 0.05
    assert plate_view > room_view


def test_the_filters_own_update_reads_the_plate_and_nothing_else_tells_the_twins_apart(twins: Suggester) -> None:
    # The frames the BIM predicts, weighed by the filter's own measurement models at the places' poses.
    views = np.array([[5.5, 0.0, np.pi], [0.0, 0.0, np.pi]])  # facing room B's door and plate; the room's far wall
    storeys = np.zeros(2, np.int64)
    frames = twins.views.frames(np.stack([se2_compose(IN_B, v) for v in views]), storeys)
    assert frames[0].observations.n_texts == 1 and frames[1].observations.n_texts == 0
    assert len(frames[1].observations) > 0 and frames[0].has_scan
    E = twins.update_evidence(views, [Hypothesis(IN_A, 0, 0.5), Hypothesis(IN_B, 0, 0.5)], storeys)
    assert E.shape == (2, 2, 2) and np.allclose(np.diagonal(E, axis1=1, axis2=2), 0.0)
    assert E[0, 1, 0] > 1.0  # B true: its plate is read (at its read chance), and A has none there
    assert abs(E[0, 0, 1]) < 0.1  # A true: no plate to read, and the filter takes nothing from a plate not read
    assert np.abs(E[1]).max() < 0.1  # the room's far wall: the same in both


def test_the_suggestion_walks_past_the_plate(twins: Suggester) -> None:
    odom = np.array([1.0, -2.0, 0.3])  # any odometry frame
    hyps = [Hypothesis(CORRIDOR_A, 0, 0.5), Hypothesis(CORRIDOR_B, 0, 0.5)]
    s = twins.suggest(hyps, odom)
    assert s.goal_odom is not None and s.reason == ""
    # A view on the way or at the goal, carried into unit B's frame, reads B's plate.
    views = np.vstack([path_views(s.path_odom, 0.5), s.goal_odom[None]])
    in_b = se2_compose(hyps[1].pose, se2_between_odom(odom, views))
    assert twins.views.plates(in_b, np.zeros(len(in_b), np.int64)).any()
    assert s.gain_nats > 0.2 and len(s.path_odom) >= 2
    np.testing.assert_allclose(s.path_odom[-1], s.goal_odom[:2], atol=0.3)


def test_the_views_on_the_way_count(twins: Suggester) -> None:
    # Down the corridor (east): the first keyframe on the way reads the plate, whichever goal ends the path.
    path = np.array([[0.0, 0.0], [4.0, 0.9]])  # relative to the robot at CORRIDOR_A / CORRIDOR_B
    views = path_views(path, 0.5)
    assert len(views) == 8 and np.allclose(views[:, 2], np.arctan2(0.9, 4.0))
    np.testing.assert_allclose(np.diff(views[:, :2], axis=0), np.tile([[0.49, 0.11]], (7, 1)), atol=0.01)
    in_b = se2_compose(CORRIDOR_B, views)
    assert twins.views.plates(in_b[:1], np.zeros(1, np.int64)).all()


def _route_through(odom: np.ndarray, suggestion) -> np.ndarray:
    """(R, 3) the odometry poses of the keyframes along a suggestion's path, and its goal."""
    return np.vstack([path_views(suggestion.path_odom, 0.5), suggestion.goal_odom[None]])


def test_the_suggester_abstains_where_the_routes_next_views_are_worth_more(twins: Suggester) -> None:
    # The route itself drives past the plate: what a candidate would show the robot, its route shows it at no cost.
    odom = np.array([1.0, -2.0, 0.3])
    hyps = [Hypothesis(CORRIDOR_A, 0, 0.5), Hypothesis(CORRIDOR_B, 0, 0.5)]
    first = twins.suggest(hyps, odom)
    assert first.goal_odom is not None
    route = _route_through(odom, first)
    s = twins.suggest(hyps, odom, route_odom=route)
    assert s.goal_odom is None and s.reason == "the route's next views are worth more"
    assert s.route_gain_nats == pytest.approx(first.gain_nats, abs=1e-9)  # the same views, the same evidence
    assert s.to_dict()["route_gain_nats"] == s.route_gain_nats
    # Beyond the horizon the same route is not counted: the candidates are worth their way again.
    far = se2_compose(odom, np.array([[20.0, 0.0, 0.0]]))
    later = twins.suggest(hyps, odom, route_odom=np.vstack([far, route]))
    assert later.goal_odom is not None and later.route_gain_nats == 0.0


def test_a_candidate_is_chosen_where_the_route_tells_nothing(twins: Suggester) -> None:
    # The route turns round by the south (its back to the plate) and drives west down the corridor to its end wall:
    # the same in both units.
    odom = np.array([1.0, -2.0, 0.3])
    hyps = [Hypothesis(CORRIDOR_A, 0, 0.5), Hypothesis(CORRIDOR_B, 0, 0.5)]
    west = np.array([[0.0, 0.0, a] for a in np.deg2rad(-15.0 * np.arange(1, 13))])
    west = np.vstack([west, [[-x, 0.0, np.pi] for x in (0.5, 1.0)]])
    s = twins.suggest(hyps, odom, route_odom=se2_compose(odom, west))
    assert s.route_gain_nats < 0.1  # the scan alone: unit B's corridor is 0.2 m shorter
    assert s.goal_odom is not None and s.reason == "" and s.gain_nats > 0.2


def se2_between_odom(odom: np.ndarray, goal_odom: np.ndarray) -> np.ndarray:
    return se2_compose(se2_inverse(odom), goal_odom)


@pytest.mark.parametrize(
    ("hyps", "converged", "why"),
    [
        ([Hypothesis(IN_A, 0, 0.97), Hypothesis(IN_B, 0, 0.03)], False, "one place holds 97%"),
        ([Hypothesis(IN_A, 0, 0.5), Hypothesis(IN_B, 0, 0.5)], True, "converged"),
        ([], False, "no modes"),
    ],
)
def test_a_settled_belief_suggests_nothing(twins: Suggester, hyps: list, converged: bool, why: str) -> None:
    s = twins.suggest(hyps, np.zeros(3), converged=converged)
    assert s.goal_odom is None and why in s.reason


def test_a_spread_belief_suggests_nothing(twins: Suggester) -> None:
    s = twins.suggest([Hypothesis(IN_A, 0, 0.5), Hypothesis(IN_B, 0, 0.5)], np.zeros(3), modes_share=0.2)
    assert s.goal_odom is None and "spread" in s.reason


free_xy = st.tuples(st.floats(0.6, 5.6), st.floats(3.7, 9.3))  # inside room A, off its walls


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(a=free_xy, yaw=st.floats(-np.pi, np.pi), share=st.floats(0.3, 0.7))
def test_every_suggested_goal_is_reachable_in_every_place(twins: Suggester, a, yaw: float, share: float) -> None:
    pose_a = np.array([*a, yaw])
    pose_b = pose_a + np.array([SHIFT_M, 0.0, 0.0])
    free = twins.graph(0)
    if free.clearance_at(np.array([a]))[0] < 0.3:
        return  # by an object
    s = twins.suggest([Hypothesis(pose_a, 0, share), Hypothesis(pose_b, 0, 1 - share)], np.zeros(3))
    if s.goal_odom is None:  # far from the plate's view, the way there can cost more than the plate tells
        assert s.reason == "no view within the horizon is worth the way there"
        return
    assert s.travel_m <= twins.cfg.active.horizon_m * 1.5
    for pose in (pose_a, pose_b):
        goal = se2_compose(pose, s.goal_odom)  # odometry frame = the robot's frame here
        gap, node = free.nearest_nodes(goal[None, :2])
        dist, _ = free.shortest_paths(free.nearest_node(pose[:2]))
        assert gap[0] <= 0.3 and np.isfinite(dist[node[0]])


def test_a_suggestion_is_written_as_json_and_drawn(twins: Suggester, tmp_path) -> None:
    import json

    from bimfactor.evaluation.plots import save_suggestion_figure

    s = twins.suggest([Hypothesis(CORRIDOR_A, 0, 0.5), Hypothesis(CORRIDOR_B, 0, 0.5)], np.array([1.0, -2.0, 0.3]))
    data = json.loads(json.dumps(s.to_dict()))
    assert data["goal"]["frame"] == "odom" and data["goal"]["x_m"] == pytest.approx(s.goal_odom[0])
    assert data["odom_pose"]["x_m"] == 1.0 and len(data["hypotheses"]) == 2 and data["path_odom"]
    assert save_suggestion_figure(twins.prior, s, tmp_path / "suggestion.png", "twins").stat().st_size > 10_000
    none = twins.suggest([Hypothesis(IN_A, 0, 1.0)], np.zeros(3))
    assert none.to_dict()["goal"] is None
    assert save_suggestion_figure(twins.prior, none, tmp_path / "none.png").is_file()


def test_a_plate_too_close_is_above_the_image(twins: Suggester) -> None:
    # Room B's plate hangs on the corridor side of its door (x ≈ 9.1, y = 3.0), 1.4 m up; the camera is 0.5 m up.
    facing = np.pi / 2
    far, close = np.array([[9.1, 1.0, facing]]), np.array([[9.1, 2.2, facing]])  # 2.0 m and 0.8 m ahead of it
    assert twins.views.plate_near_m == pytest.approx(1.3, abs=0.05)
    assert twins.views.plates(far, np.zeros(1, np.int64)).any()
    assert not twins.views.plates(close, np.zeros(1, np.int64)).any()


def test_a_view_the_filter_has_weighed_is_not_suggested_again(twins: Suggester) -> None:
    # The plate is the only thing that tells the units apart: once the filter has weighed the plate's view and the
    # belief is still even, no view is predicted to add anything, and the robot is left to its own route.
    odom = np.array([1.0, -2.0, 0.3])
    hyps = [Hypothesis(CORRIDOR_A, 0, 0.5), Hypothesis(CORRIDOR_B, 0, 0.5)]
    first = twins.suggest(hyps, odom)
    assert first.goal_odom is not None and first.gain_nats > 0.2
    again = twins.suggest(hyps, odom, seen_odom=_route_through(odom, first))
    assert again.goal_odom is None and "tells the places apart" in again.reason
