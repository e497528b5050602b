"""End to end on the synth office: from a uniform start, S-MCL finds the robot within ~20 steps.

Observations are generated here from the true pose: the BIM objects the visibility table lists at the true
pose, within r and the field of view, with range and bearing noise, and embeddings = the object's BIM text
embedding plus noise (renormalised). Odometry increments come from the true path plus noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SmclConfig, updated
from bimfactor.localization.filter import SemanticMCL, StepResult
from bimfactor.types import Observations, se2_between, wrap_angle

RANGE_SIGMA_M = 0.1
BEARING_SIGMA_RAD = np.deg2rad(3.0)
EMBEDDING_NOISE = 0.02  # per dimension of 384: cos(observed, true label) ≈ 0.93
ODOM_SIGMA_M = 0.02
ODOM_SIGMA_RAD = np.deg2rad(1.0)
STEP_M = 0.5
TURN_RAD = np.deg2rad(30.0)
# Along the corridor towards its east end, then into the kitchen (room ids are looked up, not assumed).
WAYPOINTS = [(17.0, 7.3), (21.8, 7.3), (21.8, 10.0), (24.0, 11.0)]
MAX_STEPS_TO_CONVERGE = 20


def scripted_path(waypoints: list[tuple[float, float]]) -> list[np.ndarray]:
    """(3,) poses: turn in place towards each waypoint in ≤ 30° steps, then drive there in ≤ 0.5 m steps."""
    x, y = waypoints[0]
    yaw = float(np.arctan2(waypoints[1][1] - y, waypoints[1][0] - x))
    poses = [np.array([x, y, yaw])]
    for tx, ty in waypoints[1:]:
        heading = np.arctan2(ty - y, tx - x)
        while abs(wrap_angle(heading - yaw)) > 1e-9:
            yaw = float(wrap_angle(yaw + np.clip(wrap_angle(heading - yaw), -TURN_RAD, TURN_RAD)))
            poses.append(np.array([x, y, yaw]))
        n = int(np.ceil(np.hypot(tx - x, ty - y) / STEP_M))
        for i in range(n):
            x, y = x + (tx - x) / (n - i), y + (ty - y) / (n - i)
            poses.append(np.array([x, y, yaw]))
    return poses


def observe_from(
    prior: BimPrior, table: VisibilityTable, cfg: SmclConfig, pose: np.ndarray, rng: np.random.Generator
) -> Observations:
    """What the robot at the true pose sees: visible objects in r (the table's radius) and the FOV, with noise."""
    ids = table.visible_ids(pose[:2], 0)
    xy = prior.object_positions()[ids, :2]
    dist = np.hypot(xy[:, 0] - pose[0], xy[:, 1] - pose[1])
    bearing = wrap_angle(np.arctan2(xy[:, 1] - pose[1], xy[:, 0] - pose[0]) - pose[2])
    keep = (dist <= table.radius_m) & (np.abs(bearing) <= np.deg2rad(cfg.semantic.fov_deg) / 2)
    ids, dist, bearing = ids[keep], dist[keep], bearing[keep]
    embeddings = prior.object_embeddings[ids] + EMBEDDING_NOISE * rng.standard_normal(
        (len(ids), prior.object_embeddings.shape[1])
    )
    embeddings /= np.linalg.norm(embeddings, axis=1, keepdims=True)
    return Observations(
        embeddings.astype(np.float32),
        dist + RANGE_SIGMA_M * rng.standard_normal(len(ids)),
        wrap_angle(bearing + BEARING_SIGMA_RAD * rng.standard_normal(len(ids))),
        labels=[prior.objects[i].label for i in ids],
    )


def drive(
    prior: BimPrior, table: VisibilityTable, cfg: SmclConfig, seed: int, start: np.ndarray | None = None
) -> list[tuple[np.ndarray, StepResult]]:
    """The true pose and the filter's step along the scripted path, from a uniform start or from a belief converged
    about a (3,) `start` pose."""
    path = scripted_path(WAYPOINTS)
    filter_rng, world_rng = np.random.default_rng(seed), np.random.default_rng(1000 + seed)
    mcl = SemanticMCL(prior, table, cfg, filter_rng)
    if start is None:
        mcl.initialize()
    else:
        mcl.initialize_around(start, 0, 0.3, np.deg2rad(5.0))
    out = []
    for i, pose in enumerate(path):
        increment = None
        if i > 0:
            noise = np.r_[ODOM_SIGMA_M * world_rng.standard_normal(2), ODOM_SIGMA_RAD * world_rng.standard_normal()]
            increment = se2_between(path[i - 1], pose) + noise
        out.append((pose, mcl.step(increment, observe_from(prior, table, cfg, pose, world_rng))))
    return out


def run(prior: BimPrior, table: VisibilityTable, cfg: SmclConfig, seed: int) -> list[tuple[float, float, bool, int]]:
    """(position error m, yaw error rad, converged flag, room id) after every step of the scripted path."""
    return [
        (
            float(np.hypot(*(result.pose[:2] - pose[:2]))),
            float(abs(wrap_angle(result.pose[2] - pose[2]))),
            result.converged,
            result.room_id,
        )
        for pose, result in drive(prior, table, cfg, seed)
    ]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_converges_from_a_uniform_start_within_20_steps(office_prior, office_visibility, smcl_cfg, seed):
    # The observations here are text embeddings plus noise (matched cosines ≈ 0.93), not the CLIP-like space of the
    # sim perception that the defaults are scaled to: use that space's threshold and temperature.
    smcl_cfg = updated(smcl_cfg, {"semantic.threshold": 0.7, "semantic.temperature": 0.15})
    errors = run(office_prior, office_visibility, smcl_cfg, seed)
    within = [e < 1.0 and y < np.deg2rad(15.0) for e, y, _, _ in errors]
    # The first step from which the estimate stays within 1 m / 15° until the end of the path.
    settled = next(i for i in range(len(within) + 1) if all(within[i:]))
    trace = [(round(e, 2), round(float(np.rad2deg(y)))) for e, y, _, _ in errors]
    assert settled <= MAX_STEPS_TO_CONVERGE, f"seed {seed}: (error m, error °) per step {trace}"
    final_err, _, converged, room = errors[-1]
    assert converged and final_err < 0.5
    (kitchen,) = [r.id for r in office_prior.rooms if r.category == "kitchen"]
    assert int(office_prior.room_at(np.array([WAYPOINTS[-1]]), 0)[0]) == kitchen
    assert room == kitchen


# ------------------------------------------------------------------------------------------ the look-alike place


def track_from(
    prior: BimPrior, table: VisibilityTable, cfg: SmclConfig, start: np.ndarray, seed: int
) -> tuple[list[float], list[bool], list[bool]]:
    """The scripted path tracked from a belief gathered about `start`: position error, `challenged` and `converged`
    per step."""
    steps = drive(prior, table, cfg, seed, start)
    errors = [float(np.hypot(*(r.pose[:2] - pose[:2]))) for pose, r in steps]
    return errors, [r.challenged for _, r in steps], [r.converged for _, r in steps]


def _challenger_cfg(smcl_cfg: SmclConfig, challenger: bool) -> SmclConfig:
    """The settings of the uniform-start test with the challenger as the only recovery (no injection, no respread)."""
    return updated(
        smcl_cfg,
        {
            "semantic.threshold": 0.7,
            "semantic.temperature": 0.15,
            "augmented.enabled": False,
            "relocalize.enabled": False,
            "challenger.enabled": challenger,
        },
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_a_challenger_moves_a_belief_locked_one_office_along_the_corridor(
    office_prior, office_visibility, smcl_cfg, seed
):
    # The belief starts converged 5 m west of the robot: the corridor's doors repeat every 5 m. Without a
    # challenger it stays there for the whole path; with one it moves to the robot and tracks it.
    start = scripted_path(WAYPOINTS)[0] + [-5.0, 0.0, 0.0]
    locked, never, _ = track_from(office_prior, office_visibility, _challenger_cfg(smcl_cfg, False), start, seed)
    assert min(locked) > 4.0 and not any(never)
    errors, challenged, converged = track_from(
        office_prior, office_visibility, _challenger_cfg(smcl_cfg, True), start, seed
    )
    (moved,) = np.flatnonzero(challenged)
    assert max(errors[moved:]) < 0.6 and min(errors[:moved]) > 4.0
    # Compact all along, but converged only where the challenger found no better place: never 5 m off.
    assert not any(converged[:moved]) and converged[-1]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_challenger_leaves_a_belief_at_the_right_place_alone(office_prior, office_visibility, smcl_cfg, seed):
    start = scripted_path(WAYPOINTS)[0]
    errors, challenged, converged = track_from(
        office_prior, office_visibility, _challenger_cfg(smcl_cfg, True), start, seed
    )
    assert not any(challenged) and max(errors) < 0.6
    assert converged[-1] and not converged[0]  # confirmed once a challenger found no better place
