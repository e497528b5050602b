"""Perception: detect ▸ segment ▸ embed ▸ lift ▸ online open-set scene graph (paper Sec. II.B)."""

from bimfactor.perception.base import Detection, Detector, Embedder, Segmenter
from bimfactor.perception.pipeline import Perception, household_vocabulary, make_perception
from bimfactor.perception.scene_graph import OnlineSceneGraph, SceneNode, UpdateStats

__all__ = [
    "Detection",
    "Detector",
    "Embedder",
    "OnlineSceneGraph",
    "Perception",
    "SceneNode",
    "Segmenter",
    "UpdateStats",
    "household_vocabulary",
    "make_perception",
]
