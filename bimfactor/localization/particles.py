"""Where particles come from: uniform over the navigable space, or drawn so that they explain an observation or a
door plate read (sensor resetting), optionally screened by the frame's depth scan."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from bimfactor.bim.prior import BimPrior
from bimfactor.config import MotionConfig
from bimfactor.errors import InputError
from bimfactor.localization.measurements.base import FrameData
from bimfactor.localization.measurements.scan import ScanLikelihood
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.types import Observations, wrap_angle

Poses = tuple[np.ndarray, np.ndarray]
"""(n, 3) x, y, yaw and (n,) storey indices."""


class FreeSpace:
    """The prior's navigable cells of every storey, built once and shared by every filter over the prior."""

    def __init__(self, prior: BimPrior) -> None:
        self.grid = prior.grid
        self.navigable = np.stack([layers.navigable.astype(bool) for layers in prior.storeys])  # (S, rows, cols)
        self.cells = np.flatnonzero(self.navigable).astype(np.int64)  # flat (storey, row, col) indices
        if len(self.cells) == 0:
            raise InputError("the prior has no navigable space to spread particles over")

    @property
    def n_storeys(self) -> int:
        return self.navigable.shape[0]

    def contains(self, poses: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(M,) bool: is each pose's position in navigable space of its storey?"""
        rc = self.grid.world_to_cell(poses[:, :2])
        ok = self.grid.contains(rc)
        out = np.zeros(len(rc), bool)
        out[ok] = self.navigable[storeys[ok], rc[ok, 0], rc[ok, 1]]
        return out


class ParticleSampler:
    """Draws poses for one filter, from its generator: uniform, from observations, from door plates."""

    def __init__(
        self,
        free: FreeSpace,
        semantic: SemanticLikelihood,
        plates: PlateLikelihood,
        scan: ScanLikelihood | None,
        motion: MotionConfig,
        object_storey: np.ndarray,
        rng: np.random.Generator,
    ) -> None:
        self.free, self.semantic, self.plates, self.scan = free, semantic, plates, scan
        self.motion, self.object_storey, self.rng = motion, object_storey, rng

    def uniform(self, n: int, storeys: list[int] | None = None) -> Poses:
        """n poses uniform over the navigable space of the given storeys (all: None) and uniform in yaw."""
        free = self.free
        cells = free.cells
        if storeys is not None:
            per_storey = free.navigable[0].size
            cells = cells[np.isin(cells // per_storey, np.asarray(storeys, np.int64))]
            if len(cells) == 0:
                raise InputError(f"no navigable space on storeys {list(storeys)}")
        picked = cells[self.rng.integers(0, len(cells), n)]
        s, r, c = np.unravel_index(picked, free.navigable.shape)
        grid = free.grid
        jitter = self.rng.random((n, 2))
        poses = np.empty((n, 3))
        poses[:, 0] = grid.origin_x + (c + jitter[:, 0]) * grid.resolution_m
        poses[:, 1] = grid.origin_y + (r + jitter[:, 1]) * grid.resolution_m
        poses[:, 2] = self.rng.uniform(-np.pi, np.pi, n)
        return poses, s.astype(np.int64)

    def from_observations(self, n: int, observations: Observations) -> Poses:
        """Up to n poses drawn from the measurement model: each explains one observation by one BIM object.

        A pair (observation j, object k) is drawn in proportion to φ_sem among the pairs that pass the semantic
        screen; the robot is put at j's observed range from k in a uniformly drawn direction and turned so k
        appears at j's observed bearing, with the motion noise added. Poses off navigable space or from which k is
        not in the visibility table's list are dropped (five rounds of draws at most), so fewer than n may come
        back.
        """
        empty = np.zeros((0, 3)), np.zeros(0, np.int64)
        if n <= 0 or len(observations) == 0:
            return empty
        scorer = self.semantic
        sem = scorer.semantic(observations)
        sem = np.where(sem >= scorer.cfg.threshold, sem, 0.0).ravel().astype(np.float64)
        if sem.sum() <= 0:
            return empty
        n_objects = sem.size // len(observations)
        ranges = np.asarray(observations.range_m, np.float64)
        bearings = np.asarray(observations.bearing_rad, np.float64)

        def draw(m: int) -> Poses:
            j, k = np.divmod(self.rng.choice(sem.size, size=m, p=sem / sem.sum()), n_objects)
            direction = self.rng.uniform(-np.pi, np.pi, m)
            drawn = np.empty((m, 3))
            drawn[:, 0] = scorer.object_xy[k, 0] + ranges[j] * np.cos(direction)
            drawn[:, 1] = scorer.object_xy[k, 1] + ranges[j] * np.sin(direction)
            drawn[:, 2] = direction + np.pi - bearings[j]
            self.add_motion_noise(drawn)
            storey = self.object_storey[k]
            ok = self.free.contains(drawn, storey)
            offsets, ids = scorer.visibility.candidates(drawn[ok, :2], storey[ok])
            owner = np.repeat(np.arange(int(ok.sum())), np.diff(offsets))
            sees = np.zeros(len(drawn), bool)
            sees[np.flatnonzero(ok)] = np.bincount(owner[ids == k[ok][owner]], minlength=int(ok.sum())) > 0
            return drawn[sees], storey[sees]

        return self.draw_in_rounds(n, draw)

    def from_texts(self, n: int, observations: Observations, readings: list[int]) -> Poses:
        """Up to n poses that explain the door-plate readings `readings` of `observations`: each drawn in front of a
        plate a reading names (`PlateLikelihood.sample_poses`), with the motion noise added; poses off navigable
        space are dropped (five rounds of draws at most)."""
        texts, plates = observations.texts, self.plates

        def draw(m: int) -> Poses:
            k = self.rng.choice(readings, size=m)
            poses, storeys = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
            for reading in np.unique(k):
                count = int(np.sum(k == reading))
                text, r, b = texts.texts[reading], float(texts.range_m[reading]), float(texts.bearing_rad[reading])
                drawn, storey = plates.sample_poses(text, r, b, count, self.rng)
                self.add_motion_noise(drawn)
                ok = self.free.contains(drawn, storey)
                poses.append(drawn[ok])
                storeys.append(storey[ok])
            return np.concatenate(poses), np.concatenate(storeys)

        return self.draw_in_rounds(n, draw)

    @staticmethod
    def draw_in_rounds(n: int, draw: Callable[[int], Poses]) -> Poses:
        """Up to n poses and their storeys from `draw(m)` (the poses kept of m drawn): five rounds at most, each
        drawing four times as many as are still missing."""
        poses, storeys = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
        for _ in range(5):
            kept, kept_storeys = draw(4 * (n - sum(len(p) for p in poses)))
            poses.append(kept)
            storeys.append(kept_storeys)
            if sum(len(p) for p in poses) >= n:
                break
        return np.concatenate(poses)[:n], np.concatenate(storeys)[:n]

    def screen_by_scan(self, n: int, poses: np.ndarray, storeys: np.ndarray, frame: FrameData) -> Poses:
        """n of the drawn (N, 3) poses, chosen without replacement in proportion to the frame's scan likelihood
        exp(score / T_scan), so that the walls in view pick among them; the first n when there is no scan term or
        scan. Returns min(n, N) poses."""
        if self.scan is None or not frame.has_scan or len(poses) <= n:
            return poses[:n], storeys[:n]
        log_p = self.scan.log_likelihood(poses, storeys, frame.scan)
        odds = np.exp(log_p - log_p.max())
        keep = self.rng.choice(len(poses), size=n, replace=False, p=odds / odds.sum())
        return poses[keep], storeys[keep]

    def add_motion_noise(self, poses: np.ndarray) -> None:
        """Perturb (n, 3) drawn poses in place by the motion model's σ_trans and σ_rot."""
        noise = self.rng.standard_normal(poses.shape)
        poses[:, :2] += self.motion.sigma_trans_m * noise[:, :2]
        poses[:, 2] = wrap_angle(poses[:, 2] + np.deg2rad(self.motion.sigma_rot_deg) * noise[:, 2])
