"""Resampling: which particles survive a step, and how many (paper Sec. II.C: systematic resampling of M when the
ESS drops below δ_ess·M). `make_resampler` picks one from `smcl.resampler`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from bimfactor.config import ResamplerConfig
from bimfactor.types import wrap_angle

Recount = Callable[[int], int]
"""Given the new particle count, how many of them the recoveries redraw instead of resampling."""


def kld_particle_count(bins: np.ndarray | int, epsilon: float, z: float) -> np.ndarray:
    """Particles that keep the KL divergence between the sample and the belief below ε with probability 1 − δ
    when the sample occupies k bins (Fox 2003, Eq. 13; z = z_(1−δ)):
    n = (k − 1) / (2ε) · (1 − 2 / (9(k − 1)) + √(2 / (9(k − 1))) · z)³, and 1 for a single bin."""
    k = np.asarray(bins, np.float64)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return np.where(k <= 1, 1, np.ceil(n)).astype(np.int64)


def systematic_resample(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) indices drawn by low-variance (systematic) sampling from the cumulative (M,) weights.

    Each particle i is drawn ⌊n·w_i⌋ or ⌈n·w_i⌉ times.
    """
    cumulative = np.cumsum(np.asarray(weights, np.float64))
    cumulative /= cumulative[-1]
    positions = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cumulative, positions, side="right"), len(cumulative) - 1)


class Resampler(Protocol):
    """Chooses the particles that survive a resampling."""

    def initial_count(self, num_particles: int) -> int:
        """How many particles a start spreads (M for a fixed count)."""
        ...

    def resample(
        self,
        weights: np.ndarray,
        poses: np.ndarray,
        storeys: np.ndarray,
        replaced: int,
        recount: Recount,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Indices of the particles kept. `replaced` of the current count are redrawn by the recoveries; a
        resampler that changes the count asks `recount` how many of the new one are."""
        ...


class SystematicResampler:
    """The paper's: M particles by low-variance sampling, less those the recoveries redraw."""

    def initial_count(self, num_particles: int) -> int:
        return num_particles

    def resample(
        self,
        weights: np.ndarray,
        poses: np.ndarray,
        storeys: np.ndarray,
        replaced: int,
        recount: Recount,
        rng: np.random.Generator,
    ) -> np.ndarray:
        return systematic_resample(weights, len(weights) - replaced, rng)


class KldResampler:
    """KLD-sampling (Fox 2003, as AMCL does), beyond the paper: a start spreads `max_particles`, and each resampling
    keeps as many as the pose bins its draws occupy need (`kld_particle_count`), never fewer than M: a global start
    over a large floor is sampled densely, a converged cloud cheaply."""

    def __init__(self, cfg: ResamplerConfig, min_particles: int) -> None:
        self.cfg, self.min_particles = cfg, min_particles

    def initial_count(self, num_particles: int) -> int:
        return self.cfg.max_particles

    def resample(
        self,
        weights: np.ndarray,
        poses: np.ndarray,
        storeys: np.ndarray,
        replaced: int,
        recount: Recount,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """`max_particles` systematic draws in random order, cut at the first n that reaches both M and
        `kld_particle_count` of the (storey, x, y, yaw) bins the first n draws occupy; of those, as many as the
        recoveries leave for the new count."""
        cfg = self.cfg
        draws = systematic_resample(weights, cfg.max_particles, rng)
        draws = draws[rng.permutation(len(draws))]
        drawn = poses[draws]
        cells = np.floor(drawn[:, :2] / cfg.bin_m).astype(np.int64)
        cells -= cells.min(axis=0)
        yaw = np.floor((wrap_angle(drawn[:, 2]) + np.pi) / np.deg2rad(cfg.bin_deg)).astype(np.int64)
        span = cells.max(axis=0) + 1
        keys = ((storeys[draws] * span[0] + cells[:, 0]) * span[1] + cells[:, 1]) * (yaw.max() + 1) + yaw
        first_in_bin = np.zeros(len(draws), bool)
        first_in_bin[np.unique(keys, return_index=True)[1]] = True
        need = np.maximum(kld_particle_count(np.cumsum(first_in_bin), cfg.epsilon, cfg.z), self.min_particles)
        enough = np.flatnonzero(np.arange(1, len(draws) + 1) >= need)
        kept = draws[: enough[0] + 1] if len(enough) else draws
        return kept[: len(kept) - recount(len(kept))]


def make_resampler(cfg: ResamplerConfig, num_particles: int, fixed: bool) -> Resampler:
    """`cfg.kind`'s resampler for M = `num_particles`; a `fixed` count (benchmarks) is always systematic."""
    if cfg.kind == "kld" and not fixed:
        return KldResampler(cfg, num_particles)
    return SystematicResampler()
