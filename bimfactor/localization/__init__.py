"""Localization stage: the semantic Monte Carlo localizer (S-MCL) against a BimPrior."""

from bimfactor.localization.likelihood import SemanticLikelihood
from bimfactor.localization.smcl import PoseEstimate, SemanticMCL, StepResult, benchmark_step

__all__ = ["PoseEstimate", "SemanticLikelihood", "SemanticMCL", "StepResult", "benchmark_step"]
