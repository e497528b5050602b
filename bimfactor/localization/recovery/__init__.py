"""The filter's recoveries from a wrong belief, behind the `Recovery` protocol (`recovery.base`): door-plate resets,
augmented MCL, relocalization and the challenger. `make_recoveries` picks them from `smcl`'s sub-configs."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from bimfactor.config import SmclConfig
from bimfactor.localization.measurements.text import PlateLikelihood
from bimfactor.localization.particles import ParticleSampler
from bimfactor.localization.recovery.augmented import AugmentedMCL
from bimfactor.localization.recovery.base import Recovery, RecoveryBase, WeightedSet
from bimfactor.localization.recovery.challenger import Challenger
from bimfactor.localization.recovery.relocalize import LostMonitor, Relocalize
from bimfactor.localization.recovery.text_reset import TextReset

if TYPE_CHECKING:
    from bimfactor.localization.filter import SemanticMCL

__all__ = ["LostMonitor", "Recovery", "RecoveryBase", "WeightedSet", "make_recoveries"]


def make_recoveries(
    cfg: SmclConfig,
    plates: PlateLikelihood,
    sampler: ParticleSampler,
    rival: Callable[[SmclConfig, int], SemanticMCL],
) -> list[Recovery]:
    """The recoveries `cfg` enables. Their order is the order of the redraws at a resampling (door-plate resets
    before augmented MCL's random particles). `rival(cfg, n)` makes the challenger's filter of n particles."""
    out: list[Recovery] = []
    if cfg.text_reset.enabled:
        out.append(TextReset(cfg.text_reset, plates, sampler))
    if cfg.augmented.enabled:
        out.append(AugmentedMCL(cfg.augmented, cfg.semantic.temperature, sampler))
    if cfg.relocalize.enabled:
        out.append(Relocalize(cfg.relocalize))
    if cfg.challenger.enabled:
        solo = cfg.model_copy(
            update={
                "challenger": cfg.challenger.model_copy(update={"enabled": False}),
                "relocalize": cfg.relocalize.model_copy(update={"enabled": False}),
            }
        )
        out.append(Challenger(cfg.challenger, rival(solo, cfg.challenger.particles)))
    return out
