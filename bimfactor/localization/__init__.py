"""Localization stage: the semantic Monte Carlo localizer (S-MCL) against a BimPrior, and the modes of its belief."""

from bimfactor.localization.filter import PoseEstimate, SemanticMCL, StepResult
from bimfactor.localization.measurements.semantic import SemanticLikelihood
from bimfactor.localization.modes import Mode, ModeTracker, TrackedMode, extract_modes

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
