"""The S-MCL kinematic motion model (paper Sec. II.C): apply the odometry increment, add Gaussian noise.

x_t = x_{t-1} ⊕ u_t + [ε_trans, ε_rot] with ε_trans ~ N(0, σ_trans² I) (metres, world frame: the noise is
isotropic, so the frame does not matter) and ε_rot ~ N(0, σ_rot²) (radians), drawn independently per particle
and per step, as the paper does; the noise does not scale with the length of the increment. A step is therefore a
keyframe (`bimfactor.odometry`, which also holds the increments and the odometry noise model the simulator and the
back end share with the localizer).

Between floors (`PortalMotion`): a particle at a portal's end (`bim.navigation.portal_zones`) may have taken it.
Without word of it, each such particle goes through with the small probability `portal_share` per step, to another
floor of its portal, and the observations decide; told that the robot changed storey (a barometer, an IMU, a lift's
interface: `types.STOREY_CHANGE`), every particle at a portal reaching that floor goes through, and the others keep
only `event_miss_weight` of their weight (the belief may have been wrong about where the robot stood).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimfactor.bim.grid import GridSpec
from bimfactor.bim.navigation import portal_zones
from bimfactor.bim.prior import BimPrior

# Re-exported: the README's live-robot snippet imports the keyframe gate from here.
from bimfactor.odometry import keyframe_due as keyframe_due
from bimfactor.types import se2_compose, wrap_angle

_MIN_TURN_RATE = 1e-9  # rad/s: below this a velocity command is a straight line


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

    grid: GridSpec
    zones: np.ndarray  # (S, rows, cols) the portal end whose zone holds each navigable cell, -1: none
    end_portal: np.ndarray  # (E,) portal id of each end
    end_storey: np.ndarray  # (E,) storey of each end
    end_cells: list[np.ndarray]  # per end, its zone's flat (row, col) cell indices
    floor_rank: np.ndarray  # (S,) each storey's place among the floors (0: lowest), -1: not a floor

    @classmethod
    def of_prior(cls, prior: BimPrior, navigable: np.ndarray) -> PortalMotion | None:
        """Over the (S, rows, cols) navigable cells; None when the prior has no portal with navigable ends."""
        zones, ends = portal_zones(prior, navigable)
        end_cells = [np.flatnonzero(zones[storey] == e) for e, (_, storey) in enumerate(ends)]
        if not any(len(c) for c in end_cells):
            return None
        rank = np.full(len(prior.storeys), -1, np.int64)
        floors = [layers.storey.index for layers in prior.storeys if layers.storey.is_floor]
        rank[floors] = np.arange(len(floors))
        portal = np.asarray([p for p, _ in ends], np.int64)
        storey = np.asarray([s for _, s in ends], np.int64)
        return cls(prior.grid, zones, portal, storey, end_cells, rank)

    def carry(
        self, particles: np.ndarray, storeys: np.ndarray, share: float, change: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (M, 3) particles on their (M,) storeys after the portals: with `change` 0 (no event) each at a portal
        end goes through with probability `share`; with a change of floors, each at an end of a portal that reaches
        that floor goes there. Returns new particles, new storeys and the (M,) bool mask of those that could have
        made the change (all True without an event)."""
        particles, storeys = particles.copy(), storeys.copy()
        rc = self.grid.world_to_cell(particles[:, :2])
        inside = self.grid.contains(rc)
        end = np.full(len(particles), -1, np.int64)
        end[inside] = self.zones[storeys[inside], rc[inside, 0], rc[inside, 1]]
        target = np.full(len(particles), -1, np.int64)
        for e in np.unique(end[end >= 0]):
            at = np.flatnonzero(end == e)
            others = np.flatnonzero((self.end_portal == self.end_portal[e]) & (np.arange(len(self.end_portal)) != e))
            others = others[[len(self.end_cells[o]) > 0 for o in others]]
            if change:
                rank = self.floor_rank[self.end_storey[e]] + change
                others = others[self.floor_rank[self.end_storey[others]] == rank]
                if len(others):
                    target[at] = others[0]
            elif len(others):
                go = at[rng.random(len(at)) < share]
                target[go] = others[rng.integers(len(others), size=len(go))]
        for t in np.unique(target[target >= 0]):
            moving = np.flatnonzero(target == t)
            storey = int(self.end_storey[t])
            # A lift keeps the particle's place where it is the target's zone too; else a cell of the target's zone.
            same = self.zones[storey, rc[moving, 0], rc[moving, 1]] == t
            cells = self.end_cells[t][rng.integers(len(self.end_cells[t]), size=int((~same).sum()))]
            drawn = self.grid.cell_to_world(np.stack(np.unravel_index(cells, self.zones.shape[1:]), axis=1))
            jitter = rng.uniform(-0.5, 0.5, drawn.shape) * self.grid.resolution_m
            particles[moving[~same], :2] = drawn + jitter
            storeys[moving] = storey
        return particles, storeys, target >= 0 if change else np.ones(len(particles), bool)
