"""The S-MCL kinematic motion model (paper Sec. II.C): apply the odometry increment, add Gaussian noise.

x_t = x_{t-1} ⊕ u_t + [ε_trans, ε_rot], ε_trans ~ N(0, σ_trans² I) (metres) and ε_rot ~ N(0, σ_rot²) (radians) drawn
per particle and per step, not scaled with the increment: a step is a keyframe (`bimfactor.odometry`).

Between floors (`PortalMotion`): a particle whose step passed a portal's end goes through with `portal_share` per
step (`portal_cross_share` when it crossed a stair's footprint); told of a storey change (`types.STOREY_CHANGE`),
every particle at a portal reaching that floor goes through and the others come out of a portal's end on that floor
(`PortalMotion.exits`) with `event_miss_weight` of their weight.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from bimfactor.bim.navigation import PORTAL_REACH_M, box_distance
from bimfactor.bim.prior import BimPrior
from bimfactor.types import se2_compose, wrap_angle

_MIN_TURN_RATE = 1e-9  # rad/s: below this a velocity command is a straight line
EXIT_SPACING_M = 0.1  # the lattice of places a storey-change event may put a particle at near a portal's end
PATH_SAMPLES = 8  # points along a particle's step that are checked for passing a portal


def velocity_increment(v_mps: float, omega_rps: float, dt_s: float) -> np.ndarray:
    """(3,) robot-frame increment of driving at constant (v, ω) for dt: an exact circular arc."""
    dyaw = omega_rps * dt_s
    if abs(omega_rps) < _MIN_TURN_RATE:
        return np.array([v_mps * dt_s, 0.0, 0.0])
    radius = v_mps / omega_rps
    return np.array([radius * np.sin(dyaw), radius * (1.0 - np.cos(dyaw)), float(wrap_angle(dyaw))])


def propagate(
    particles: np.ndarray,
    increment: np.ndarray,
    sigma_trans_m: float,
    sigma_rot_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(M, 3) particles moved by a (3,) robot-frame increment, plus Gaussian noise; returns a new array."""
    particles = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
    moved = se2_compose(particles, np.broadcast_to(np.asarray(increment, np.float64), particles.shape))
    noise = rng.standard_normal((len(particles), 3))
    moved[:, :2] += sigma_trans_m * noise[:, :2]
    moved[:, 2] = wrap_angle(moved[:, 2] + sigma_rot_rad * noise[:, 2])
    return moved


def propagate_velocity(
    particles: np.ndarray,
    v_mps: float,
    omega_rps: float,
    dt_s: float,
    sigma_trans_m: float,
    sigma_rot_rad: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """(M, 3) particles moved by the control u = (v, ω) over dt (the paper's form of the motion model)."""
    return propagate(particles, velocity_increment(v_mps, omega_rps, dt_s), sigma_trans_m, sigma_rot_rad, rng)


@dataclass(frozen=True)
class PortalMotion:
    """Carries particles between floors through the prior's portals (module docstring); built once per prior."""

    boxes: np.ndarray  # (E, 4) x_min, y_min, x_max, y_max of each portal end
    end_portal: np.ndarray  # (E,) portal id of each end
    end_storey: np.ndarray  # (E,) storey of each end
    floor_rank: np.ndarray  # (S,) each storey's place among the floors (0: lowest), -1: not a floor
    _exit_places: dict[int, np.ndarray] = field(default_factory=dict)  # `_places` of each portal end, when first asked

    @classmethod
    def of_prior(cls, prior: BimPrior) -> PortalMotion | None:
        """None when the prior has no portal."""
        ends = [(p.id, e.storey_index, e.box_xy) for p in prior.portals for e in p.ends]
        if not ends:
            return None
        portal, storey, boxes = zip(*ends, strict=True)
        return cls(
            np.asarray(boxes, float), np.asarray(portal, np.int64), np.asarray(storey, np.int64), prior.floor_rank()
        )

    def carry(
        self,
        before_xy: np.ndarray,
        after_xy: np.ndarray,
        storeys: np.ndarray,
        shares: tuple[float, float],
        change: int,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The (M,) storeys of particles that moved from (M, 2) `before_xy` to `after_xy` in a step, after the
        portals: a particle whose path passed within `PORTAL_REACH_M` of a portal's end on its storey may have gone
        through, keeping its place (a lift's floors share their x, y; a stair's climb is in the odometry). With
        `change` 0 (no event) each goes to another floor of the portal with probability `shares[0]`, or `shares[1]`
        where its path crossed a footprint of the portal (a stair's steps, where a robot on the floor cannot drive);
        with a change of floors, each whose portal reaches that floor goes there. Returns the new storeys and the
        (M,) bool mask of the particles that could have made the change (all True without an event)."""
        path = (
            before_xy[:, None, :]
            + np.linspace(0.0, 1.0, PATH_SAMPLES)[None, :, None] * (after_xy - before_xy)[:, None, :]
        )  # (M, P, 2)
        storeys = storeys.copy()
        target = np.full(len(storeys), -1, np.int64)
        for e in range(len(self.boxes)):
            at = np.flatnonzero((storeys == self.end_storey[e]) & (target < 0))
            if not len(at):
                continue
            at = at[box_distance(path[at], self.boxes[e]).min(axis=1) <= PORTAL_REACH_M]
            others = np.flatnonzero((self.end_portal == self.end_portal[e]) & (np.arange(len(self.boxes)) != e))
            if change:
                floor = self.floor_rank[self.end_storey[e]] + change
                reached = others[self.floor_rank[self.end_storey[others]] == floor]
                if len(reached):
                    target[at] = reached[0]
            elif len(others):
                ends = np.flatnonzero(self.end_portal == self.end_portal[e])
                crossed = np.min([box_distance(path[at], self.boxes[o]).min(axis=1) for o in ends], axis=0) <= 0.0
                go = at[rng.random(len(at)) < np.where(crossed, shares[1], shares[0])]
                target[go] = others[rng.integers(len(others), size=len(go))]
        moving = target >= 0
        storeys[moving] = self.end_storey[target[moving]]
        return storeys, moving if change else np.ones(len(storeys), bool)

    def exits(
        self, storeys: np.ndarray, change: int, rng: np.random.Generator, navigable: Callable
    ) -> tuple[np.ndarray, np.ndarray]:
        """(M, 2) random navigable places within `PORTAL_REACH_M` of a portal's end `change` floors above (below) each
        of (M,) `storeys`, of a portal with an end on that storey where there is one, else of any reaching that far,
        and their (M,) storeys; NaN places (and the storey kept) where no portal joins floors `change` apart.
        `navigable((N, 3) poses, (N,) storeys)` says which places are on navigable space."""
        rank = self.floor_rank[self.end_storey]
        below = [
            np.any((self.end_portal == p) & (rank == r - change)) for p, r in zip(self.end_portal, rank, strict=True)
        ]
        places = [self._places(e, navigable) for e in range(len(self.boxes))]
        reach = np.asarray(below, bool) & (rank >= 0) & np.array([len(p) > 0 for p in places])
        xy, out = np.full((len(storeys), 2), np.nan), np.array(storeys, np.int64)
        for s in np.unique(out):
            members = np.flatnonzero(out == s)
            here = reach & np.isin(self.end_portal, self.end_portal[self.end_storey == s])
            options = np.flatnonzero(here & (rank == self.floor_rank[s] + change))
            options = options if len(options) else np.flatnonzero(reach)
            if not len(options):
                continue
            for k, e in zip(members, options[rng.integers(len(options), size=len(members))], strict=True):
                xy[k] = places[e][rng.integers(len(places[e]))]
                out[k] = self.end_storey[e]
        return xy, out

    def _places(self, end: int, navigable: Callable) -> np.ndarray:
        """(N, 2) the navigable points of a lattice `EXIT_SPACING_M` apart within `PORTAL_REACH_M` of a portal's end."""
        if end not in self._exit_places:
            x0, y0, x1, y1 = self.boxes[end] + np.array([-1, -1, 1, 1]) * PORTAL_REACH_M
            grid = np.stack(np.meshgrid(np.arange(x0, x1, EXIT_SPACING_M), np.arange(y0, y1, EXIT_SPACING_M)), -1)
            points = grid.reshape(-1, 2)
            poses = np.column_stack([points, np.zeros(len(points))])
            self._exit_places[end] = points[navigable(poses, np.full(len(points), self.end_storey[end]))]
        return self._exit_places[end]
