"""The door-plate term of the measurement model (beyond the paper).

A reading t seen at range r and bearing b from pose x is explained by a plate j (`bim.plates`) on x's storey, in front
of x, whose text it matches:

    q_j(x) = exp(−cost(t, s_j)) · φ_dist(r, d_j(x)) · φ_ang(b, α_j(x))
    P(t | x) = ε + (1 − ε) · max_j q_j(x)

with ε = `smcl.text.unexplained`, φ_dist and φ_ang the semantic term's, and cost the cheapest edit of the normalised
texts, a look-alike substitution ("8" for "B") costing `smcl.text.look_alike_cost` and any other edit
`smcl.text.edit_cost`. A step's readings are independent: log P(z_text | x) = Σ_k log P(t_k | x). docs/filter.md.
"""

from __future__ import annotations

import numpy as np

from bimfactor.bim.plates import PLATE_REACH_M, door_plates, look_alikes, normalise_text
from bimfactor.bim.prior import BimPrior
from bimfactor.config import SmclConfig
from bimfactor.localization.measurements.base import FrameData, Term
from bimfactor.localization.measurements.semantic import bearing_similarity, distance_similarity, polar_coordinates
from bimfactor.types import TextObservations, wrap_angle

MIN_TEXT_MATCH = 1e-3  # plates whose text matches a reading less than this (one edit at c = 6: e^−6) are not weighed
MIN_PLATE_ASSOCIATION = 0.1  # a reading enters a pose graph only for a plate it fits this well (q; look-alike: e^−3.5)


def edit_distance(a: str, b: str, look_alike: float = 1.0) -> float:
    """Levenshtein distance: the fewest insertions, deletions and substitutions that turn `a` into `b`, where a
    substitution of look-alike characters (`bim.plates.look_alikes`) counts `look_alike` edits (1: plain)."""
    return _edit_table(a, b, look_alike)[-1][-1]


def edit_operations(truth: str, read: str, look_alike: float = 1.0) -> dict[str, int]:
    """How a cheapest edit (`edit_distance`) turns `truth` into `read`: the counts of characters read right
    ("same"), read as a look-alike ("look_alike"), as any other character ("other"), lost ("dropped"), and of
    characters read that are not there ("inserted")."""
    table = _edit_table(truth, read, look_alike)
    counts = dict.fromkeys(("same", "look_alike", "other", "dropped", "inserted"), 0)
    i, j = len(truth), len(read)
    while i or j:
        if i and j and table[i][j] == table[i - 1][j - 1] + _substitution(truth[i - 1], read[j - 1], look_alike):
            a, b = truth[i - 1], read[j - 1]
            counts["same" if a == b else "look_alike" if b in look_alikes(a) else "other"] += 1
            i, j = i - 1, j - 1
        elif i and table[i][j] == table[i - 1][j] + 1.0:
            counts["dropped"] += 1
            i -= 1
        else:
            counts["inserted"] += 1
            j -= 1
    return counts


def _substitution(a: str, b: str, look_alike: float) -> float:
    return 0.0 if a == b else look_alike if b in look_alikes(a) else 1.0


def _edit_table(a: str, b: str, look_alike: float) -> list[list[float]]:
    """The dynamic-programming table of `edit_distance`: entry [i][j] turns a[:i] into b[:j]."""
    table = [[float(j) for j in range(len(b) + 1)]]
    for i, ca in enumerate(a, start=1):
        previous, current = table[-1], [float(i)]
        for j, cb in enumerate(b, start=1):
            substituted = previous[j - 1] + _substitution(ca, cb, look_alike)
            current.append(min(previous[j] + 1.0, current[j - 1] + 1.0, substituted))
        table.append(current)
    return table


class PlateLikelihood:
    """log P(readings | x) of particles against the prior's door plates; 0 for a prior without plates.

    The plates are also landmarks of the pose graphs: plate p is landmark `first_landmark_id + p`, after the prior's
    objects (`backend.factors.Landmarks.from_prior` lists them in the same order).
    """

    name = "text"

    def __init__(self, prior: BimPrior, cfg: SmclConfig) -> None:
        self.cfg = cfg.text
        self.sigma_d_m, self.kappa_alpha = cfg.semantic.sigma_d_m, cfg.semantic.kappa_alpha  # the paper's φ_dist, φ_ang
        plates = door_plates(prior)
        self.texts = [normalise_text(p.text) for p in plates]
        self.xy = np.asarray([p.xy for p in plates], float).reshape(-1, 2)
        self.normal = np.asarray([p.normal_xy for p in plates], float).reshape(-1, 2)
        self.storey = np.asarray([p.storey_index for p in plates], np.int64)
        # where on its door's wall face each plate can hang: the door's width and `PLATE_REACH_M` beyond either edge
        axis = np.asarray([p.axis_xy for p in plates], float).reshape(-1, 2)
        reach = np.asarray([p.door_width_m / 2 + PLATE_REACH_M for p in plates], float)[:, None] * axis
        self.ends = np.stack([self.xy - reach, self.xy + reach], axis=1)  # (P, 2, 2)
        self.first_landmark_id = len(prior.object_positions())
        self._matches: dict[str, np.ndarray] = {}  # text → `text_match`: refine weighs one reading at many poses

    def __len__(self) -> int:
        return len(self.texts)

    def text_match(self, text: str) -> np.ndarray:
        """(P,) exp(−cost) of one reading against every plate's text (0 for a reading with no letter or digit)."""
        t = normalise_text(text)
        if t not in self._matches:
            c = self.cfg.edit_cost
            edits = np.asarray([edit_distance(t, s, self.cfg.look_alike_cost / c) for s in self.texts], float)
            self._matches[t] = np.exp(-c * edits) if t else np.zeros(len(self.texts))
        return self._matches[t]

    def scores(
        self, particles: np.ndarray, storeys: np.ndarray, text: str, range_m: float, bearing_rad: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """q (M, C) of one reading against the C plates whose text it matches at all (≥ `MIN_TEXT_MATCH`) at M
        (3,) poses, and those plates' (C,) indices; q is 0 where a plate is behind x's wall or on another storey."""
        particles = np.asarray(particles, np.float64).reshape(-1, 3)
        storeys = np.broadcast_to(np.asarray(storeys, np.int64), len(particles))
        match = self.text_match(text)
        candidates = np.flatnonzero(match >= MIN_TEXT_MATCH)
        if not len(candidates):
            return np.zeros((len(particles), 0)), candidates
        xy, normal = self.xy[candidates], self.normal[candidates]
        d, alpha = polar_coordinates(particles[:, None, :], xy[None])
        in_front = np.einsum("mcj,cj->mc", particles[:, None, :2] - xy[None], normal) > 0.0
        here = storeys[:, None] == self.storey[candidates][None]
        q = match[candidates] * distance_similarity(range_m, d, self.sigma_d_m)
        q = q * bearing_similarity(bearing_rad, alpha, self.kappa_alpha) * (in_front & here)
        return q, candidates

    def reading_likelihoods(self, particles: np.ndarray, storeys: np.ndarray, texts: TextObservations) -> np.ndarray:
        """(K, M) P(t_k | x) = ε + (1 − ε) · max_j q_j(x) of each of the step's K readings at M poses."""
        particles = np.asarray(particles, np.float64).reshape(-1, 3)
        eps = self.cfg.unexplained
        out = np.full((len(texts.texts), len(particles)), eps)
        if not len(self):
            return out
        for k, (text, r, b) in enumerate(zip(texts.texts, texts.range_m, texts.bearing_rad, strict=True)):
            q, _ = self.scores(particles, storeys, text, float(r), float(b))
            if q.shape[1]:
                out[k] += (1.0 - eps) * q.max(axis=1)
        return out

    def log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, texts: TextObservations) -> np.ndarray:
        """(M,) Σ_k log P(t_k | x) over the step's readings (see the module docstring)."""
        if texts is None or not len(texts.texts) or not len(self):
            return np.zeros(len(np.asarray(particles).reshape(-1, 3)))
        return np.log(self.reading_likelihoods(particles, storeys, texts)).sum(axis=0)

    def weigh(self, particles: np.ndarray, storeys: np.ndarray, frame: FrameData) -> Term | None:
        """The frame's door-plate term, with the (K, M) P(t_k | x) of its readings as evidence (the text reset
        looks for readings the belief does not explain); None when nothing was read."""
        observations = frame.observations
        if observations is None or not observations.n_texts:
            return None
        per_reading = self.reading_likelihoods(particles, storeys, observations.texts)
        return Term(np.log(per_reading).sum(axis=0), per_reading)

    def named_plates(self, text: str) -> np.ndarray:
        """Indices of the plates a reading names: their text matches it within one look-alike character."""
        return np.flatnonzero(self.text_match(text) >= np.exp(-self.cfg.look_alike_cost) * (1 - 1e-9))

    def sample_poses(
        self, text: str, range_m: float, bearing_rad: float, n: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """n (3,) poses, and their storeys, from which one reading is explained: in front of a plate whose text it
        matches within one look-alike (drawn in proportion to the match), at the read range in a direction within
        60° of the plate's normal, turned so the plate is at the read bearing. No pose for a reading no plate
        matches that well. Returns (n', 3) and (n',) with n' = n or 0."""
        match = self.text_match(text)
        candidates = self.named_plates(text)
        if n <= 0 or not len(candidates):
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        plate = rng.choice(candidates, size=n, p=match[candidates] / match[candidates].sum())
        direction = np.arctan2(self.normal[plate, 1], self.normal[plate, 0]) + rng.uniform(-1.0, 1.0, n) * np.pi / 3
        poses = np.empty((n, 3))
        poses[:, 0] = self.xy[plate, 0] + range_m * np.cos(direction)
        poses[:, 1] = self.xy[plate, 1] + range_m * np.sin(direction)
        poses[:, 2] = wrap_angle(direction + np.pi - bearing_rad)
        return poses, self.storey[plate]

    def associate(self, pose: np.ndarray, storey: int, texts: TextObservations | None) -> list[tuple[int, int]]:
        """(reading index, plate index) pairs at one (3,) pose: each reading's best plate there, if its q exceeds
        `MIN_PLATE_ASSOCIATION` (the plate its text, distance and bearing point to; several readings may name one)."""
        pairs: list[tuple[int, int]] = []
        if not len(self) or texts is None:
            return pairs
        for k, (text, r, b) in enumerate(zip(texts.texts, texts.range_m, texts.bearing_rad, strict=True)):
            q, candidates = self.scores(np.asarray(pose, np.float64)[None], storey, text, float(r), float(b))
            if q.shape[1] and q[0].max() > MIN_PLATE_ASSOCIATION:
                pairs.append((k, int(candidates[int(np.argmax(q[0]))])))
        return pairs
