"""The filter's recoveries from a wrong belief, by role (`recovery.base`): door-plate resets and augmented MCL inject
particles, relocalization detects a lost belief, the challenger verifies a converged one. `make_recoveries` picks
them from `smcl`'s sub-configs."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from bimfactor.config import SmclConfig
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.particles import ParticleSampler
from bimfactor.localization.recovery.augmented import AugmentedMCL
from bimfactor.localization.recovery.base import Injection, Recoveries, WeightedSet
from bimfactor.localization.recovery.challenger import Challenger
from bimfactor.localization.recovery.relocalize import LostMonitor, Relocalize
from bimfactor.localization.recovery.text_reset import TextReset

if TYPE_CHECKING:
    from bimfactor.localization.filter import SemanticMCL

__all__ = ["LostMonitor", "Recoveries", "WeightedSet", "make_recoveries"]


def make_recoveries(
    cfg: SmclConfig,
    plates: PlateLikelihood,
    sampler: ParticleSampler,
    rival: Callable[[SmclConfig, int], SemanticMCL],
) -> Recoveries:
    """The recoveries `cfg` enables. The injections redraw in this order at a resampling: door-plate resets before
    augmented MCL's random particles. `rival(cfg, n)` makes the challenger's filter of n particles."""
    injections: list[Injection] = []
    if cfg.text_reset.enabled:
        injections.append(TextReset(cfg.text_reset, plates, sampler))
    if cfg.augmented.enabled:
        injections.append(AugmentedMCL(cfg.augmented, cfg.semantic.temperature, sampler))
    out = Recoveries(injections, Relocalize(cfg.relocalize) if cfg.relocalize.enabled else None)
    if cfg.challenger.enabled:
        solo = cfg.model_copy(
            update={
                "challenger": cfg.challenger.model_copy(update={"enabled": False}),
                "relocalize": cfg.relocalize.model_copy(update={"enabled": False}),
            }
        )
        out.verification = Challenger(cfg.challenger, rival(solo, cfg.challenger.particles))
    return out
