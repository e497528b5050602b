"""The door-plate term of the measurement model (beyond the paper).

A reading t seen at range r and bearing b from pose x is explained by a plate j (`bim.plates`) on x's storey,
in front of x (x is on the side its wall faces), whose text it matches:

    q_j(x) = exp(−c · edits(t, s_j)) · φ_dist(r, d_j(x)) · φ_ang(b, α_j(x))
    P(t | x) = ε + (1 − ε) · max_j q_j(x)

with c = `smcl.text_edit_cost`, ε = `smcl.text_unexplained`, edits the Levenshtein distance of the normalised
texts (`bim.plates.normalise_text`), and φ_dist, φ_ang the paper's terms with its σ_d and κ_α. The readings of a
step are independent, log P(z_text | x) = Σ_k log P(t_k | x). ε is the chance that a reading is a misread or a
plate the model does not know: one reading moves a particle's weight by at most 1/ε against another's, and a
reading that no plate near any particle matches moves nothing. Plates repeat their room's number at every door
into it, so a particle is matched to the best of them (no one-to-one assignment: a frame reads one or two).
"""

from __future__ import annotations

import numpy as np

from bimfactor.bim.plates import door_plates, normalise_text
from bimfactor.bim.prior import BimPrior
from bimfactor.config import SmclConfig
from bimfactor.localization.likelihood import bearing_similarity, distance_similarity, polar_coordinates
from bimfactor.types import TextObservations

MIN_TEXT_MATCH = 1e-3  # plates whose text matches a reading less than this (3 edits at c = 3) are not weighed


def edit_distance(a: str, b: str) -> int:
    """Levenshtein distance: the fewest insertions, deletions and substitutions that turn `a` into `b`."""
    previous = list(range(len(b) + 1))
    for i, ca in enumerate(a, start=1):
        current = [i]
        for j, cb in enumerate(b, start=1):
            current.append(min(previous[j] + 1, current[j - 1] + 1, previous[j - 1] + (ca != cb)))
        previous = current
    return previous[-1]


class PlateLikelihood:
    """log P(readings | x) of particles against the prior's door plates; 0 for a prior without plates."""

    def __init__(self, prior: BimPrior, cfg: SmclConfig) -> None:
        self.cfg = cfg
        plates = door_plates(prior)
        self.texts = [normalise_text(p.text) for p in plates]
        self.xy = np.asarray([p.xy for p in plates], float).reshape(-1, 2)
        self.normal = np.asarray([p.normal_xy for p in plates], float).reshape(-1, 2)
        self.storey = np.asarray([p.storey_index for p in plates], np.int64)
        self._matches: dict[str, np.ndarray] = {}  # text → `text_match`: refine weighs one reading at many poses

    def __len__(self) -> int:
        return len(self.texts)

    def text_match(self, text: str) -> np.ndarray:
        """(P,) exp(−c · edits) of one reading against every plate's text (0 for a reading with no letter or digit)."""
        t = normalise_text(text)
        if t not in self._matches:
            edits = np.asarray([edit_distance(t, s) for s in self.texts], float)
            self._matches[t] = np.exp(-self.cfg.text_edit_cost * edits) if t else np.zeros(len(self.texts))
        return self._matches[t]

    def log_likelihood(self, particles: np.ndarray, storeys: np.ndarray, texts: TextObservations) -> np.ndarray:
        """(M,) Σ_k log(ε + (1 − ε) · max_j q_j(x)) over the step's readings (see the module docstring)."""
        particles = np.asarray(particles, np.float64).reshape(-1, 3)
        storeys = np.broadcast_to(np.asarray(storeys, np.int64), len(particles))
        eps = self.cfg.text_unexplained
        out = np.zeros(len(particles))
        if not len(self) or texts is None:
            return out
        for text, r, b in zip(texts.texts, texts.range_m, texts.bearing_rad, strict=True):
            match = self.text_match(text)
            candidates = np.flatnonzero(match >= MIN_TEXT_MATCH)
            best = np.zeros(len(particles))
            if len(candidates):
                xy, normal = self.xy[candidates], self.normal[candidates]
                d, alpha = polar_coordinates(particles[:, None, :], xy[None])
                in_front = np.einsum("mcj,cj->mc", particles[:, None, :2] - xy[None], normal) > 0.0
                here = storeys[:, None] == self.storey[candidates][None]
                q = match[candidates] * distance_similarity(r, d, self.cfg.sigma_d_m)
                q = q * bearing_similarity(b, alpha, self.cfg.kappa_alpha) * (in_front & here)
                best = q.max(axis=1)
            out += np.log(eps + (1.0 - eps) * best)
        return out
