"""The filter's measurement models, one factor of P(z | x) each, behind the `MeasurementModel` protocol:
`semantic` (the paper's Hungarian score, Eqs. 1-4), `text` (door plates read) and `scan` (the depth scan against
the BIM's likelihood field). `make_measurements` picks them from `smcl`'s sub-configs."""

from __future__ import annotations

from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import SmclConfig
from bimfactor.localization.measurements.base import FrameData, MeasurementModel, Term
from bimfactor.localization.measurements.scan import ScanLikelihood
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.measurements.text import PlateLikelihood

__all__ = ["FrameData", "MeasurementModel", "Term", "make_measurements"]


def make_measurements(prior: BimPrior, visibility: VisibilityTable, cfg: SmclConfig) -> list[MeasurementModel]:
    """The measurement models `cfg` asks for, in the order their log-likelihoods are summed: semantic (always: the
    paper's), text (weighs only frames that read a plate) and scan (`scan.enabled`)."""
    models: list[MeasurementModel] = [SemanticLikelihood(prior, visibility, cfg.semantic), PlateLikelihood(prior, cfg)]
    if cfg.scan.enabled:
        models.append(ScanLikelihood(prior, cfg.scan))
    return models
