"""Back end: one GTSAM pose graph per particle-filter mode, with semantic-landmark factors to BIM objects."""

from bimfactor.backend.posegraph import (
    BackendStep,
    BatchResult,
    ModeEstimate,
    ModeGraph,
    MultiHypothesisBackend,
    batch_refine,
    semantic_associator,
)

__all__ = [
    "BackendStep",
    "BatchResult",
    "ModeEstimate",
    "ModeGraph",
    "MultiHypothesisBackend",
    "batch_refine",
    "semantic_associator",
]
