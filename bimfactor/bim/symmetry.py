"""Twin places: rigid motions of a storey that carry its labelled objects onto other objects of the same label.

A semantic localizer cannot tell two places apart when such a motion also carries the walls onto walls (twin flats,
a repeated bay). `symmetries` finds motions from pairs of objects, `twin_motions` keeps per storey the best one that
carries nearly everything; the evaluation also scores up to it, and `tools/building_symmetry.py` lists them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.distance import cdist

if TYPE_CHECKING:
    from bimfactor.bim.prior import BimPrior


@dataclass
class Motion:
    """A planar rigid motion x ↦ R(θ) x + t and how many objects it maps onto another object of their label."""

    theta_rad: float
    translation: np.ndarray
    matched: int
    total: int

    @property
    def share(self) -> float:
        return self.matched / self.total

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """(N, 3) poses (x, y, yaw) carried by the motion: where each pose's twin stands and faces."""
        poses = np.asarray(poses, float)
        out = np.empty_like(poses)
        out[:, :2] = self.move(poses[:, :2])
        out[:, 2] = np.arctan2(np.sin(poses[:, 2] + self.theta_rad), np.cos(poses[:, 2] + self.theta_rad))
        return out

    def inverse(self) -> Motion:
        """The motion back: x ↦ R(−θ)(x − t)."""
        back = -(_rotation(-self.theta_rad) @ np.asarray(self.translation, float))
        return Motion(-self.theta_rad, back, self.matched, self.total)

    def move(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) points carried by the motion."""
        return _move(xy, self.theta_rad, self.translation)

    def describe(self) -> str:
        deg = float(np.rad2deg(self.theta_rad))
        deg = 180.0 if deg <= -179.5 else deg
        if abs(deg) < 1.0:
            where = f"translation by ({self.translation[0]:.2f}, {self.translation[1]:.2f}) m"
        else:
            # the fixed point c of R c + t = c
            c = np.linalg.solve(np.eye(2) - _rotation(self.theta_rad), self.translation)
            where = f"rotation by {deg:.0f}° about ({c[0]:.2f}, {c[1]:.2f}) m"
        return f"{where}: {self.matched} of {self.total} objects ({100 * self.share:.0f} %)"


def _rotation(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _move(xy: np.ndarray, theta: float, t: np.ndarray) -> np.ndarray:
    return np.asarray(xy, float) @ _rotation(theta).T + t


def _partner_distances(points: np.ndarray, same_label: np.ndarray, theta: float, t: np.ndarray) -> np.ndarray:
    """(N, N): from each object carried by the motion to every other object of its label; inf elsewhere (onto
    itself does not count: a motion near the identity is no twin)."""
    d = cdist(_move(points, theta, t), points)
    np.fill_diagonal(d, np.inf)
    return np.where(same_label, d, np.inf)


def _matched(points: np.ndarray, same_label: np.ndarray, theta: float, t: np.ndarray, tolerance: float) -> int:
    """Objects the motion carries within `tolerance` of another object of their label."""
    return int((_partner_distances(points, same_label, theta, t).min(axis=1) < tolerance).sum())


def symmetries(
    points: np.ndarray,
    labels: list[str],
    tolerance: float = 0.3,
    neighbours: int = 2,
    keep: int = 3,
    anchors: int = 12,
) -> list[Motion]:
    """The `keep` best non-identity rigid motions of (N, 2) labelled points, best first; a motion that moves the
    points to where a better one does (`_alike`) is left out.

    Hypotheses pair each of the `anchors` objects of the rarest labels (a twin carries them onto the few objects of
    their label, so they propose few motions) and its `neighbours` nearest objects with every pair of the same
    labels at the same distance: a motion that carries most objects onto their like is proposed by nearly every
    anchor, and a storey of 150 objects with 54 windows takes a second, not the hours all pairs would."""
    points = np.asarray(points, float)
    n = len(points)
    if n < 2:
        return []
    labels_arr = np.asarray(labels)
    same_label = labels_arr[:, None] == labels_arr[None, :]
    dist = cdist(points, points)
    count = same_label.sum(axis=1)
    rarest = [int(i) for i in np.argsort(count, kind="stable") if count[i] >= 2][:anchors]
    seen: set[tuple[int, int, int]] = set()
    scored: list[Motion] = []
    for i in rarest:
        for j in np.argsort(dist[i])[1 : neighbours + 1]:
            for k in np.flatnonzero(same_label[i]):
                for m in np.flatnonzero(same_label[j] & (np.abs(dist[k] - dist[i, j]) < tolerance)):
                    if m == k or (k == i and m == j):
                        continue
                    a, b = points[j] - points[i], points[m] - points[k]
                    theta = float(np.arctan2(b[1], b[0]) - np.arctan2(a[1], a[0]))
                    theta = float(np.arctan2(np.sin(theta), np.cos(theta)))
                    t = points[k] - _rotation(theta) @ points[i]
                    if _identity(theta, t, tolerance):
                        continue
                    key = (round(np.rad2deg(theta) / 5) % 72, round(t[0] / 0.5), round(t[1] / 0.5))
                    if key not in seen:
                        seen.add(key)
                        scored.append(Motion(theta, t, _matched(points, same_label, theta, t, tolerance), n))
    # A two-object hypothesis has the angle of a short baseline; refit the best ones to all the pairs they match.
    best = sorted(scored, key=lambda m: -m.matched)[: 4 * keep]
    refined = [_refit(motion, points, same_label, tolerance) for motion in best]
    distinct: list[Motion] = []
    for motion in sorted(refined, key=lambda m: -m.matched):
        if _identity(motion.theta_rad, motion.translation, tolerance):
            continue  # a refit can slide onto it where objects stand in pairs
        if not any(_alike(motion, kept, points, tolerance) for kept in distinct):
            distinct.append(motion)
            if len(distinct) == keep:
                break
    return distinct


def _identity(theta: float, t: np.ndarray, tolerance: float) -> bool:
    return bool(abs(theta) < np.deg2rad(1.0) and np.hypot(*t) < tolerance)


def _refit(motion: Motion, points: np.ndarray, same_label: np.ndarray, tolerance: float, rounds: int = 2) -> Motion:
    """The least-squares rigid motion (2-D Kabsch) of the pairs `motion` matches, re-matched `rounds` times; the
    better-matching of it and `motion`."""
    best = motion
    for _ in range(rounds):
        d = _partner_distances(points, same_label, best.theta_rad, best.translation)
        partner = d.argmin(axis=1)
        pairs = d[np.arange(len(points)), partner] < 2 * tolerance
        if pairs.sum() < 2:
            break
        src, dst = points[pairs], points[partner[pairs]]
        src_c, dst_c = src - src.mean(axis=0), dst - dst.mean(axis=0)
        h = src_c.T @ dst_c
        theta = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
        t = dst.mean(axis=0) - _rotation(theta) @ src.mean(axis=0)
        candidate = Motion(theta, t, _matched(points, same_label, theta, t, tolerance), len(points))
        if candidate.matched < best.matched:
            break
        best = candidate
    return best


def _alike(a: Motion, b: Motion, points: np.ndarray, tolerance: float) -> bool:
    """The same motion, as far as the objects tell: it puts them, on the median, within 2 × `tolerance` of where
    the other does."""
    return bool(np.median(np.hypot(*(a.move(points) - b.move(points)).T)) < 2 * tolerance)


def wall_share(prior: BimPrior, storey_index: int, motion: Motion, tolerance: float = 0.1) -> float:
    """Share of the storey's structure cells (walls, columns) that `motion` carries within `tolerance` metres of a
    structure cell: 1.0 when the walls repeat as the objects do."""
    from scipy.ndimage import binary_dilation

    grid = prior.grid
    structure = np.asarray(prior.storeys[storey_index].structure, bool)
    rows, cols = np.nonzero(structure)
    if len(rows) == 0:
        return float("nan")
    xy = np.stack(
        [grid.origin_x + (cols + 0.5) * grid.resolution_m, grid.origin_y + (rows + 0.5) * grid.resolution_m], 1
    )
    rc = grid.world_to_cell(motion.move(xy))
    inside = grid.contains(rc)
    near = binary_dilation(structure, iterations=max(1, round(tolerance / grid.resolution_m)))
    hit = np.zeros(len(rc), bool)
    hit[inside] = near[rc[inside, 0], rc[inside, 1]]
    return float(hit.mean())


def twin_motions(prior: BimPrior, min_object_share: float = 0.9, min_wall_share: float = 0.9) -> dict[int, Motion]:
    """Per storey, the best non-identity motion that carries at least `min_object_share` of its objects (at least
    four) onto other objects of their label and `min_wall_share` of its wall cells onto walls; storeys without one
    are left out."""
    twins = {}
    for index in range(len(prior.storeys)):
        objects = [o for o in prior.objects if o.storey_index == index]
        if len(objects) < 4:
            continue
        motions = symmetries(np.array([o.position_m[:2] for o in objects]), [o.label for o in objects], keep=1)
        if motions and motions[0].share >= min_object_share and wall_share(prior, index, motions[0]) >= min_wall_share:
            twins[index] = motions[0]
    return twins
