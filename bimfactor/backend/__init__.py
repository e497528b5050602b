"""Back end: particle-filter modes, one GTSAM pose graph per mode with semantic-landmark factors to BIM objects."""

from bimfactor.backend.modes import Mode, ModeTracker, TrackedMode, extract_modes
from bimfactor.backend.posegraph import (
    BackendStep,
    BatchResult,
    ModeEstimate,
    ModeGraph,
    MultiHypothesisBackend,
    batch_refine,
    benchmark_backend,
    semantic_associator,
)

__all__ = [
    "BackendStep",
    "BatchResult",
    "Mode",
    "ModeEstimate",
    "ModeGraph",
    "ModeTracker",
    "MultiHypothesisBackend",
    "TrackedMode",
    "batch_refine",
    "benchmark_backend",
    "extract_modes",
    "semantic_associator",
]
