"""Twin evidence, beyond the paper: what the frames say about a belief against its image in the building's twin place.

In a building with twin places (`bim.symmetry.twin_motions`), a belief's image under the twin motion T explains the
objects and walls as well; only what T does not carry (a door plate) tells them apart. `TwinEvidence` sums, since the
belief last started over, ln Σ w_i p(z | x_i) − ln Σ w_i p(z | T(x_i)); a compact belief on a storey with a twin is
reported converged only once that sum reaches `SETTLED_NATS` (about one plate read in front of the right door).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import logsumexp

from bimfactor.bim.symmetry import Motion
from bimfactor.localization.measurements.base import FrameData

SETTLED_NATS = 3.0  # e³ ≈ 20 : 1 for the belief's place over its twin's

LogLikelihood = Callable[[np.ndarray, np.ndarray, FrameData], np.ndarray | None]


class TwinEvidence:
    """The summed log Bayes factor of a belief against its twin image (module docstring)."""

    def __init__(self, twins: dict[int, Motion], log_likelihood: LogLikelihood) -> None:
        self.twins = twins
        self.log_likelihood = log_likelihood  # (particles, storeys, frame) → (M,) Σ_m ln p_m(z | x), or None
        self.nats = 0.0
        back = {storey: motion.inverse() for storey, motion in twins.items()}
        half_turns = all(_same(back[s], m) for s, m in twins.items())  # T⁻¹ = T: one image
        self._both_ways = [twins] if half_turns else [twins, back]

    def reset(self) -> None:
        """The belief started over (a start, a relocalization, a set taken over)."""
        self.nats = 0.0

    def observe(
        self, particles: np.ndarray, storeys: np.ndarray, weights: np.ndarray, log_likelihood: np.ndarray,
        frame: FrameData,
    ) -> None:  # fmt: skip
        """Add one frame: the belief's (M,) `log_likelihood` over `weights` (before the update) against its image's.
        The image is taken both ways (T and T⁻¹: a twin may lie on either side of a motion that is not a half-turn),
        and the likelier one is the rival; only the particles on a storey with a twin are weighed again."""
        twin = np.isin(storeys, list(self.twins))
        if not twin.any():
            return
        own, rival = _log_sum(weights, log_likelihood), -np.inf
        for motions in self._both_ways:
            images = particles[twin].copy()
            for storey, motion in motions.items():
                on = storeys[twin] == storey
                images[on] = motion.apply(images[on])
            at_images = self.log_likelihood(images, storeys[twin], frame)
            if at_images is None:
                return
            image_ll = log_likelihood.copy()
            image_ll[twin] = at_images
            rival = max(rival, _log_sum(weights, image_ll))
        if np.isfinite(own) and np.isfinite(rival):
            self.nats += own - rival

    def settled(self, storey: int) -> bool:
        """Whether a belief on `storey` is told from its twin: no twin there, or the frames favour it enough."""
        return storey not in self.twins or self.nats >= SETTLED_NATS


def _log_sum(weights: np.ndarray, log_likelihood: np.ndarray) -> float:
    """ln Σ w_i exp(ℓ_i); −inf when every term is 0."""
    return float(logsumexp(log_likelihood, b=weights))


def _same(a: Motion, b: Motion) -> bool:
    """Whether two motions carry every point to the same place."""
    turn = (a.theta_rad - b.theta_rad + np.pi) % (2 * np.pi) - np.pi
    return abs(turn) < 1e-9 and np.allclose(a.translation, b.translation, atol=1e-9)
