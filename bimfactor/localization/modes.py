"""Modes of the particle filter's belief: clusters of weighted particles, and their identities over time.

Clustering (`extract_modes`), per storey: the heaviest bin of unassigned particles (`cluster_radius_m`,
`cluster_yaw_deg`) seeds a flat-window mean-shift; the window's particles form a cluster (weight share, circular mean,
(3, 3) covariance with wrapped yaw), repeated while weight remains; the strongest `max_modes` clusters holding
`min_cluster_weight` are the modes. Tracking (`ModeTracker`): a mode keeps its id while a cluster near its
odometry-predicted pose continues it; an unmatched cluster of `spawn_weight` spawns one; modes within
`merge_distance_m` and `merge_yaw_deg` merge; modes below `prune_probability` are pruned, never the most probable.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from bimfactor.config import BackendConfig
from bimfactor.localization.stats import circular_mean, pose_window, weighted_pose_stats
from bimfactor.types import se2_compose, wrap_angle

log = logging.getLogger(__name__)

_MEAN_SHIFT_ITERATIONS = 20
_MEAN_SHIFT_TOL_M = 1e-3


@dataclass
class Mode:
    """One cluster of particles: (3,) mean pose (circular yaw), (3, 3) world-frame covariance, its weight share."""

    mean: np.ndarray
    covariance: np.ndarray
    weight: float
    storey: int = 0
    n_particles: int = 0


@dataclass
class TrackedMode:
    """A mode with an identity kept across steps; `probability` is set by the back end (default: the weight)."""

    id: int
    mean: np.ndarray
    covariance: np.ndarray
    weight: float
    storey: int
    probability: float
    born_step: int
    missed: int = 0


@dataclass
class TrackEvents:
    """What one tracker update changed: new ids, (kept id, absorbed id) merges, pruned ids."""

    spawned: list[int] = field(default_factory=list)
    merged: list[tuple[int, int]] = field(default_factory=list)
    pruned: list[int] = field(default_factory=list)


# ------------------------------------------------------------------------------------------ clustering


def _weighted_mean(poses: np.ndarray, weights: np.ndarray) -> np.ndarray:
    mean = np.empty(3)
    mean[:2] = weights @ poses[:, :2] / weights.sum()
    mean[2] = circular_mean(poses[:, 2], weights)
    return mean


def _cluster_storey(
    poses: np.ndarray, weights: np.ndarray, radius_m: float, yaw_half_rad: float, max_clusters: int
) -> list[np.ndarray]:
    """Index arrays of up to `max_clusters` clusters of (N, 3) poses with (N,) weights, by greedy mean-shift."""
    # Bins: yaw bins of width yaw_half_rad (a window spans two), wrapped so ±π share a bin edge, not a bin.
    n_yaw_bins = max(int(np.floor(2 * np.pi / yaw_half_rad)), 1)
    cell = np.stack(
        [
            np.floor(poses[:, 0] / radius_m),
            np.floor(poses[:, 1] / radius_m),
            np.floor((poses[:, 2] + np.pi) / (2 * np.pi) * n_yaw_bins) % n_yaw_bins,
        ],
        axis=1,
    ).astype(np.int64)
    _, bin_of = np.unique(cell, axis=0, return_inverse=True)
    bin_of = bin_of.reshape(-1)
    unassigned = np.ones(len(poses), bool)
    clusters: list[np.ndarray] = []
    while unassigned.any() and len(clusters) < max_clusters:
        bin_weight = np.bincount(bin_of[unassigned], weights=weights[unassigned], minlength=bin_of.max() + 1)
        seed_bin = int(np.argmax(bin_weight))
        if bin_weight[seed_bin] <= 0:
            break
        seed = unassigned & (bin_of == seed_bin)
        centre = _weighted_mean(poses[seed], weights[seed])
        members = seed
        for _ in range(_MEAN_SHIFT_ITERATIONS):
            members = unassigned & pose_window(poses, centre, radius_m, yaw_half_rad)
            if not members.any() or weights[members].sum() <= 0:
                members = seed
                break
            new_centre = _weighted_mean(poses[members], weights[members])
            moved = np.hypot(*(new_centre[:2] - centre[:2])) + radius_m * abs(wrap_angle(new_centre[2] - centre[2]))
            centre = new_centre
            if moved < _MEAN_SHIFT_TOL_M:
                break
        members = unassigned & (pose_window(poses, centre, radius_m, yaw_half_rad) | seed)
        clusters.append(np.flatnonzero(members))
        unassigned &= ~members
    return clusters


def extract_modes(
    particles: np.ndarray,
    weights: np.ndarray,
    cfg: BackendConfig,
    storeys: np.ndarray | None = None,
) -> list[Mode]:
    """The strongest `cfg.max_modes` clusters of (M, 3) particles with (M,) weights and (M,) storeys, heaviest first."""
    particles = np.asarray(particles, np.float64).reshape(-1, 3)
    weights = np.asarray(weights, np.float64)
    storeys = np.zeros(len(particles), np.int64) if storeys is None else np.asarray(storeys, np.int64)
    total = weights.sum()
    if len(particles) == 0 or total <= 0:
        return []
    radius, yaw_half = cfg.cluster_radius_m, np.deg2rad(cfg.cluster_yaw_deg)
    modes: list[Mode] = []
    # A few more clusters than kept, so a heavy mode is never crowded out by light ones found first on a storey.
    for storey in np.unique(storeys):
        on = np.flatnonzero(storeys == storey)
        for members in _cluster_storey(particles[on], weights[on], radius, yaw_half, 4 * cfg.max_modes):
            idx = on[members]
            w = weights[idx]
            if w.sum() / total < cfg.min_cluster_weight:
                continue
            mean, covariance = weighted_pose_stats(particles[idx], w)
            modes.append(Mode(mean, covariance, float(w.sum() / total), int(storey), len(idx)))
    modes.sort(key=lambda m: -m.weight)
    return modes[: cfg.max_modes]


# ------------------------------------------------------------------------------------------ tracking


def poses_close(a: np.ndarray, b: np.ndarray, distance_m: float, yaw_rad: float) -> bool:
    """Are two (3,) poses within `distance_m` in position and `yaw_rad` in wrapped yaw?"""
    return bool(np.hypot(a[0] - b[0], a[1] - b[1]) <= distance_m and abs(wrap_angle(a[2] - b[2])) <= yaw_rad)


class ModeTracker:
    """Keeps mode identities across steps: continue, spawn, merge, prune (see the module docstring)."""

    def __init__(self, cfg: BackendConfig) -> None:
        self.cfg = cfg
        self.modes: list[TrackedMode] = []
        self.step_index = -1
        self._next_id = 0

    def get(self, mode_id: int) -> TrackedMode:
        for mode in self.modes:
            if mode.id == mode_id:
                return mode
        raise KeyError(f"no mode with id {mode_id}")

    def update(self, clusters: list[Mode], odom_increment: np.ndarray | None = None) -> TrackEvents:
        """Continue, spawn and merge modes from this step's clusters; modes are first moved by the (3,) increment."""
        self.step_index += 1
        events = TrackEvents()
        gate_m, gate_yaw = self.cfg.track_gate_m, np.deg2rad(self.cfg.track_gate_yaw_deg)
        if odom_increment is not None:
            for mode in self.modes:
                mode.mean = se2_compose(mode.mean, np.asarray(odom_increment, np.float64))
        # Gated nearest match, heaviest cluster first; each mode continues at most one cluster.
        free = {mode.id for mode in self.modes}
        unmatched: list[Mode] = []
        for cluster in sorted(clusters, key=lambda c: -c.weight):
            candidates = [
                m
                for m in self.modes
                if m.id in free and m.storey == cluster.storey and poses_close(m.mean, cluster.mean, gate_m, gate_yaw)
            ]
            if not candidates:
                unmatched.append(cluster)
                continue
            best = min(candidates, key=lambda m: np.hypot(*(m.mean[:2] - cluster.mean[:2])))
            free.discard(best.id)
            best.mean, best.covariance, best.weight, best.missed = cluster.mean, cluster.covariance, cluster.weight, 0
        for mode in self.modes:
            if mode.id in free:
                mode.weight *= self.cfg.missed_decay
                mode.missed += 1
        for cluster in unmatched:
            if cluster.weight >= self.cfg.spawn_weight:
                events.spawned.append(self._spawn(cluster))
        events.merged = self.merge_converged()
        self._normalise_probabilities_from_weights()
        return events

    def merge_converged(self) -> list[tuple[int, int]]:
        """Merge modes on one storey whose means are within the merge thresholds; returns (kept, absorbed) ids."""
        merged: list[tuple[int, int]] = []
        dist, yaw = self.cfg.merge_distance_m, np.deg2rad(self.cfg.merge_yaw_deg)
        order = sorted(self.modes, key=lambda m: (-m.probability, m.id))
        kept: list[TrackedMode] = []
        for mode in order:
            target = next(
                (k for k in kept if k.storey == mode.storey and poses_close(k.mean, mode.mean, dist, yaw)), None
            )
            if target is None:
                kept.append(mode)
                continue
            target.weight += mode.weight
            target.probability += mode.probability
            merged.append((target.id, mode.id))
            log.debug("mode %d merged into mode %d", mode.id, target.id)
        self.modes = sorted(kept, key=lambda m: m.id)
        return merged

    def set_probabilities(self, probabilities: dict[int, float]) -> None:
        """Set each mode's probability (the back end's weight × graph evidence); ids not given keep theirs."""
        for mode in self.modes:
            if mode.id in probabilities:
                mode.probability = float(probabilities[mode.id])

    def prune(self) -> list[int]:
        """Drop modes whose probability is below `prune_probability` (never the most probable); returns their ids."""
        if not self.modes:
            return []
        best = max(self.modes, key=lambda m: m.probability)
        pruned = [m.id for m in self.modes if m is not best and m.probability < self.cfg.prune_probability]
        self.modes = [m for m in self.modes if m.id not in pruned]
        total = sum(m.probability for m in self.modes)
        if total > 0:
            for mode in self.modes:
                mode.probability /= total
        return pruned

    # -------------------------------------------------------------------------------- helpers

    def _spawn(self, cluster: Mode) -> int:
        mode = TrackedMode(
            self._next_id,
            cluster.mean.copy(),
            cluster.covariance.copy(),
            cluster.weight,
            cluster.storey,
            cluster.weight,
            self.step_index,
        )
        self._next_id += 1
        self.modes.append(mode)
        log.debug("mode %d spawned at (%.2f, %.2f, %.1f°)", mode.id, *mode.mean[:2], np.rad2deg(mode.mean[2]))
        return mode.id

    def _normalise_probabilities_from_weights(self) -> None:
        """Until the back end sets them, probabilities are the particle-weight shares of the tracked modes."""
        total = sum(m.weight for m in self.modes)
        for mode in self.modes:
            mode.probability = mode.weight / total if total > 0 else 1.0 / len(self.modes)
