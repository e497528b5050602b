"""The S-MCL measurement model (paper Sec. II.C, Eqs. 1–4): semantic × spatial pair scores, Hungarian matching.

For a particle x, each candidate BIM object k in view has a distance d and bearing α, each observation j d_obs, α_obs
and an embedding f_j; the pair score is

    φ = φ_sem · φ_dist · φ_ang,  φ_sem = cos(f_j, C_k),  φ_dist = exp(−|d_obs − d| / σ_d),
    φ_ang = exp(κ_α (cos(α_obs − α) − 1)),

with φ_sem below `threshold` screened out. A one-to-one assignment maximises Σφ (Hungarian), the score is that sum
over the K observations, and P(z|x) = exp(K^(1−γ) · score / T) (`count_exponent` γ; `footprint_match`: docs/filter.md).
Everything but the assignment runs for all particles at once on a padded (M, K, C) array; scipy's Hungarian solver
is called only where the contested part is larger than 2 × 2 (`assignment_sums`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SemanticTermConfig
from bimfactor.localization.measurements.base import FrameData, Term
from bimfactor.types import Observations, wrap_angle

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------ score terms


def polar_coordinates(pose: np.ndarray, points_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance d and bearing α (counter-clockwise from the pose's heading, in [-π, π)) of points from poses.

    `pose` (..., 3) and `points_xy` (..., 2) broadcast against each other; returns two arrays of their shape.
    """
    pose, points_xy = np.asarray(pose, dtype=np.float64), np.asarray(points_xy, dtype=np.float64)
    dx = points_xy[..., 0] - pose[..., 0]
    dy = points_xy[..., 1] - pose[..., 1]
    return np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - pose[..., 2])


def semantic_similarity(observation_embeddings: np.ndarray, object_embeddings: np.ndarray) -> np.ndarray:
    """φ_sem: (K, N) cosine similarity of (K, D) and (N, D) unit-row embeddings.

    einsum, not BLAS: for products this small, waking BLAS threads costs more than the product (ms spikes).
    """
    obs = np.asarray(observation_embeddings, np.float32)
    return np.einsum("kd,nd->kn", obs, np.asarray(object_embeddings, np.float32))


def distance_similarity(d_obs: np.ndarray, d: np.ndarray, sigma_d_m: float) -> np.ndarray:
    """φ_dist = exp(−|d_obs − d| / σ_d), Eq. (1), elementwise with broadcasting."""
    return np.exp(-np.abs(np.asarray(d_obs) - np.asarray(d)) / sigma_d_m)


def bearing_similarity(alpha_obs: np.ndarray, alpha: np.ndarray, kappa_alpha: float) -> np.ndarray:
    """φ_ang = exp(κ_α (cos(α_obs − α) − 1)), Eq. (2), elementwise with broadcasting."""
    return np.exp(kappa_alpha * (np.cos(np.asarray(alpha_obs) - np.asarray(alpha)) - 1.0))


def pair_score(
    sem: np.ndarray,
    d_obs: np.ndarray,
    d: np.ndarray,
    alpha_obs: np.ndarray,
    alpha: np.ndarray,
    cfg: SemanticTermConfig,
) -> np.ndarray:
    """φ_tot = φ_sem · φ_dist · φ_ang, Eq. (3), and 0 where φ_sem < `threshold`; elementwise."""
    spatial = distance_similarity(d_obs, d, cfg.sigma_d_m) * bearing_similarity(alpha_obs, alpha, cfg.kappa_alpha)
    sem = np.asarray(sem)
    return np.where(sem >= cfg.threshold, sem * spatial, 0.0)


def likelihood_from_score(score: np.ndarray, temperature: float) -> np.ndarray:
    """P(z|x) = exp(score / T), Eq. (4)'s weight factor."""
    return np.exp(np.asarray(score) / temperature)


# ------------------------------------------------------------------------------------------ assignment


def assignment_sums(phi: np.ndarray) -> tuple[np.ndarray, int]:
    """Best one-to-one matching of observations to candidates per particle: (M,) summed φ, Hungarian call count.

    `phi` (M, K, C) ≥ 0 (0: no pair). Exact everywhere; solved without a per-particle Python call where possible:
    1. each observation's best candidate, when these are distinct (or K = 1), is the optimum (row-maxima bound);
    2. otherwise an observation whose best candidate pairs with no other observation keeps it (an exchange
       argument shows some optimum does), and the rest (the residual) is compacted to (B, R, C');
    3. residuals with one row or column take their largest entry, with two rows or columns the best of all
       distinct pairs (vectorised brute force); only larger ones go to scipy's Hungarian solver, one call each.
    """
    M, K, C = phi.shape
    if K == 0 or C == 0:
        return np.zeros(M), 0
    best_col = phi.argmax(axis=2)
    best = np.take_along_axis(phi, best_col[:, :, None], axis=2)[:, :, 0]
    totals = best.sum(axis=1, dtype=np.float64)
    if K == 1:
        return totals, 0
    # Rows without any pair take unique dummy columns so they never count as a conflict.
    keys = np.where(best > 0, best_col, C + np.arange(K)[None, :])
    keys.sort(axis=1)
    conflict = np.flatnonzero((keys[:, 1:] == keys[:, :-1]).any(axis=1))
    if len(conflict) == 0:
        return totals, 0
    sub, sub_best, sub_col = phi[conflict], best[conflict], best_col[conflict]
    pairs_per_col = (sub > 0).sum(axis=1)  # (B, C) observations that pair with each candidate
    exclusive = (sub_best > 0) & (np.take_along_axis(pairs_per_col, sub_col, axis=1) == 1)
    fixed = np.where(exclusive, sub_best, 0).sum(axis=1, dtype=np.float64)
    residual_rows = (sub_best > 0) & ~exclusive
    residual = _compact_residual(sub, residual_rows)
    n_rows = (residual > 0).any(axis=2).sum(axis=1)
    n_cols = (residual > 0).any(axis=1).sum(axis=1)
    small = np.minimum(n_rows, n_cols)
    solved = np.zeros(len(conflict))
    one = small <= 1
    solved[one] = residual[one].max(axis=(1, 2), initial=0.0)
    two_rows = (small == 2) & (n_rows == 2)
    solved[two_rows] = _best_distinct_pair(residual[two_rows, :2, :])
    two_cols = (small == 2) & (n_rows > 2)
    solved[two_cols] = _best_distinct_pair(residual[two_cols, :, :2].transpose(0, 2, 1))
    large = np.flatnonzero(small > 2)
    for b in large:
        rows, cols = linear_sum_assignment(residual[b, : n_rows[b], : n_cols[b]], maximize=True)
        solved[b] = float(residual[b, rows, cols].sum(dtype=np.float64))
    totals[conflict] = fixed + solved
    return totals, len(large)


def _compact_residual(phi: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(B, R, C') the selected (B, K) rows of (B, K, C) phi, moved first, and the columns they pair with, first."""
    row_order = np.argsort(~rows, axis=1, kind="stable")[:, : max(int(rows.sum(axis=1).max()), 1)]
    kept = np.take_along_axis(phi, row_order[:, :, None], axis=1)
    kept = kept * np.take_along_axis(rows, row_order, axis=1)[:, :, None]
    cols = (kept > 0).any(axis=1)
    col_order = np.argsort(~cols, axis=1, kind="stable")[:, : max(int(cols.sum(axis=1).max()), 1)]
    return np.take_along_axis(kept, col_order[:, None, :], axis=2)


def _best_distinct_pair(two: np.ndarray) -> np.ndarray:
    """(B,) max over c1 ≠ c2 of two[:, 0, c1] + two[:, 1, c2] for (B, 2, C) with C ≥ 2 (padding columns are 0)."""
    if two.shape[0] == 0:
        return np.zeros(0)
    if two.shape[2] < 2:
        two = np.concatenate([two, np.zeros((*two.shape[:2], 2 - two.shape[2]), two.dtype)], axis=2)
    sums = two[:, 0, :, None].astype(np.float64) + two[:, 1, None, :]
    diagonal = np.arange(two.shape[2])
    sums[:, diagonal, diagonal] = -np.inf
    return sums.max(axis=(1, 2))


# ------------------------------------------------------------------------------------------ all particles


@dataclass
class ScoreStats:
    """What one batch of scores cost: candidate pairs after each screen and the Hungarian calls."""

    candidates: int = 0
    in_view: int = 0
    semantic_pairs: int = 0
    hungarian_calls: int = 0


class SemanticLikelihood:
    """Scores particles against one step's observations using the prior's objects and the visibility table."""

    name = "semantic"

    def __init__(self, prior: BimPrior, visibility: VisibilityTable, cfg: SemanticTermConfig) -> None:
        self.visibility = visibility
        self.cfg = cfg
        self.object_xy = prior.object_positions()[:, :2].copy()
        self.object_embeddings = np.asarray(prior.object_embeddings, np.float32)
        # The label vocabulary of the prior: softmax φ_sem normalises over its distinct label embeddings.
        labels = [o.label for o in prior.objects]
        vocabulary = sorted(set(labels))
        self.object_label = np.asarray([vocabulary.index(label) for label in labels], np.int64)
        first = [labels.index(label) for label in vocabulary]
        self.label_embeddings = self.object_embeddings[first] if first else self.object_embeddings[:0]
        self.radius_m = visibility.radius_m
        self.half_fov_rad = 0.5 * np.deg2rad(cfg.fov_deg)
        # Footprint radius: half the diagonal of the object's axis-aligned footprint (0: centre-only FOV test).
        sizes = prior.object_sizes()[:, :2]
        # World-frame footprint boxes (the objects' axis-aligned extents) for `footprint_match`.
        self.object_lo, self.object_hi = self.object_xy - sizes / 2, self.object_xy + sizes / 2
        self.object_radius_m = 0.5 * np.hypot(sizes[:, 0], sizes[:, 1]) if cfg.fov_extent else np.zeros(len(sizes))
        self.last_stats = ScoreStats()

    def semantic(self, observations: Observations, objects: np.ndarray | None = None) -> np.ndarray:
        """(K, N) φ_sem of K observations against the BIM objects `objects` (default: all) (`similarity`).

        cosine: the paper's cos(f_j, C_k). softmax: p(label of k | f_j), the cosines to the prior's distinct
        label embeddings turned into class probabilities at `softmax_temperature` (CLIP's zero-shot rule).
        """
        objects = slice(None) if objects is None else objects
        if self.cfg.similarity == "cosine" or len(observations) == 0:
            return semantic_similarity(observations.embeddings, self.object_embeddings[objects])
        tau = self.cfg.softmax_temperature
        logits = semantic_similarity(observations.embeddings, self.label_embeddings) / tau
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        p /= p.sum(axis=1, keepdims=True)
        return p[:, self.object_label[objects]].astype(np.float32)

    def pair_scores(
        self, particles: np.ndarray, storeys: np.ndarray, observations: Observations
    ) -> tuple[np.ndarray, np.ndarray]:
        """Padded φ (M, K, C) float32 and the matching (M, C) object ids (-1: padding) for M particles."""
        particles = np.asarray(particles, np.float64).reshape(-1, 3)
        M, K = len(particles), len(observations)
        stats = ScoreStats()
        offsets, ids = self.visibility.candidates(particles[:, :2], storeys)
        stats.candidates = len(ids)
        owner = np.repeat(np.arange(M), np.diff(offsets))
        # Polar coordinates of every listed candidate from its particle; keep those within r and the FOV.
        d, alpha = polar_coordinates(particles[owner], self.object_xy[ids])
        keep = (d <= self.radius_m) & (np.abs(alpha) <= self.half_fov_rad + self._half_extent(ids, d))
        owner, ids, d, alpha = owner[keep], ids[keep], d[keep], alpha[keep]
        # A partly seen object is observed where its seen part is: inside the FOV, nearest its centre.
        alpha = np.clip(alpha, -self.half_fov_rad, self.half_fov_rad)
        stats.in_view = len(ids)
        if K == 0 or len(ids) == 0:
            self.last_stats = stats
            return np.zeros((M, K, 0), np.float32), np.full((M, 0), -1, np.int64)
        # Semantic screen on the sparse (observation, candidate) pairs; spatial terms only where it passes.
        present = np.flatnonzero(np.bincount(ids, minlength=len(self.object_xy)))  # objects in some particle's view
        local = np.zeros(len(self.object_xy), np.int64)
        local[present] = np.arange(len(present))
        sem = self.semantic(observations, present)[:, local[ids]]  # (K, E)
        k_idx, e_idx = np.nonzero(sem >= self.cfg.threshold)
        stats.semantic_pairs = len(k_idx)
        if len(k_idx) == 0:
            self.last_stats = stats
            return np.zeros((M, K, 0), np.float32), np.full((M, 0), -1, np.int64)
        d_obs = np.asarray(observations.range_m, np.float64)[k_idx]
        a_obs = np.asarray(observations.bearing_rad, np.float64)[k_idx]
        if self.cfg.footprint_match:
            d_exp, a_exp = self.footprint_polar(particles[owner[e_idx]], ids[e_idx], d_obs, a_obs)
        else:
            d_exp, a_exp = d[e_idx], alpha[e_idx]
        phi = sem[k_idx, e_idx] * (
            np.exp(-np.abs(d_obs - d_exp) / self.cfg.sigma_d_m + self.cfg.kappa_alpha * (np.cos(a_obs - a_exp) - 1.0))
        )
        # Columns: the candidates that take part in a pair, numbered per particle.
        used = np.flatnonzero(np.bincount(e_idx, minlength=len(ids)))  # sorted, like np.unique but cheaper
        used_owner = owner[used]
        col_of_used = np.arange(len(used)) - np.searchsorted(used_owner, used_owner, side="left")
        n_cols = int(col_of_used.max()) + 1
        pos = np.searchsorted(used, e_idx)
        phi_pad = np.zeros((M, K, n_cols), np.float32)
        phi_pad[owner[e_idx], k_idx, col_of_used[pos]] = phi
        ids_pad = np.full((M, n_cols), -1, np.int64)
        ids_pad[used_owner, col_of_used] = ids[used]
        self.last_stats = stats
        return phi_pad, ids_pad

    def footprint_polar(
        self, poses: np.ndarray, ids: np.ndarray, range_m: np.ndarray, bearing_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Expected (d, α) of objects `ids` from (P, 3) `poses` for nodes observed at (`range_m`, `bearing_rad`):
        the polar coordinates of the point of each object's footprint box nearest to the node's world point.

        A node is the centroid of the object's seen part, which lies anywhere on a large object's footprint (a
        3 m table seen from one end is observed a metre and more from its centre); inside the box it matches
        exactly, outside it the distance to the box is what the spatial terms see.
        """
        heading = poses[:, 2] + bearing_rad
        seen = poses[:, :2] + range_m[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
        nearest = np.clip(seen, self.object_lo[ids], self.object_hi[ids])
        return polar_coordinates(poses, nearest)

    def _half_extent(self, ids: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Half the angle objects `ids` subtend at distances `d` (their footprint circles; π/2 from inside one)."""
        return np.arcsin(np.minimum(1.0, self.object_radius_m[ids] / np.maximum(d, 1e-9)))

    def scores(self, particles: np.ndarray, storeys: np.ndarray, observations: Observations) -> np.ndarray:
        """(M,) mean matched score in [0, 1] of each particle: the optimal assignment's summed φ over K."""
        K = len(observations)
        if K == 0:
            return np.zeros(len(np.asarray(particles).reshape(-1, 3)))
        phi, _ = self.pair_scores(particles, storeys, observations)
        totals, calls = assignment_sums(phi)
        self.last_stats.hungarian_calls = calls
        return totals / K

    def count_scale(self, n_observations: int) -> float:
        """K^(1−γ): what the mean matched score of K observations is multiplied by in the log-likelihood (1 for the
        paper's mean, γ = 1; K for the sum, γ = 0)."""
        return float(n_observations) ** (1.0 - self.cfg.count_exponent)

    def log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, observations: Observations) -> np.ndarray:
        """(M,) log P(z|x) = K^(1−γ) · score / T (`count_scale`)."""
        scores = self.scores(particles, storeys, observations)
        return scores * (self.count_scale(len(observations)) / self.cfg.temperature)

    def weigh(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> Term | None:
        """The frame's semantic term; its evidence is each particle's mean matched score over T, on an absolute
        scale whatever the number of observations (what augmented MCL averages). None without observations."""
        observations = frame.observations
        if observations is None or len(observations) == 0:
            return None
        log_likelihood = self.log_likelihood(particles, storeys, observations)
        return Term(log_likelihood, log_likelihood / self.count_scale(len(observations)))
