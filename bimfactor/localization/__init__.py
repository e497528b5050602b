"""Localization stage: the semantic Monte Carlo localizer (S-MCL) against a BimPrior, and the modes of its belief."""

from bimfactor.localization.likelihood import SemanticLikelihood
from bimfactor.localization.modes import Mode, ModeTracker, TrackedMode, extract_modes
from bimfactor.localization.smcl import PoseEstimate, SemanticMCL, StepResult

__all__ = [
    "Mode",
    "ModeTracker",
    "PoseEstimate",
    "SemanticLikelihood",
    "SemanticMCL",
    "StepResult",
    "TrackedMode",
    "extract_modes",
]
