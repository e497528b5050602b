"""The `vlm` perception backend of the paper: YOLO-World detections, SAM masks, CLIP ViT-L crop embeddings.

Weights are local files named in the config (never downloaded); the text embedder must be CLIP's text tower of the
same model (ConfigError otherwise). `check_vlm_ready` checks files, pairing and libraries before any heavy work: a
missing file is a DependencyError naming it, its config key and where to get it. Each class has `from_model`, for
tests with randomly initialised models.
"""

from __future__ import annotations

import importlib.util
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from bimfactor import errors
from bimfactor.config import Config
from bimfactor.embed.text import VLM_INSTALL_HINT, TextEmbedder, clip_source
from bimfactor.errors import ConfigError, DependencyError, require_weights, weights_problem
from bimfactor.perception.base import Detection, box_to_pixels, empty_masks, passes_thresholds
from bimfactor.types import Frame

log = logging.getLogger(__name__)

INSTALL_HINT = VLM_INSTALL_HINT
LIBRARIES = {"ultralytics": "YOLO-World", "segment_anything": "SAM", "open_clip": "CLIP"}
"""The vlm extra's modules and what needs each."""
CROP_MARGIN = 0.1  # CLIP sees the box grown by this share of its side: a little context helps zero-shot

YOLO_WORLD_SOURCE = "yolov8s-worldv2.pt (or the m, l, x one) from https://github.com/ultralytics/assets/releases"
SAM_SOURCES = {
    "vit_b": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth",
    "vit_l": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth",
    "vit_h": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth",
}
"""Segment Anything's checkpoints by `perception.vlm.sam_model_type` (github.com/facebookresearch/segment-anything)."""


def sam_source(model_type: str) -> str:
    """Where the Segment Anything checkpoint of the backbone `model_type` can be downloaded."""
    return SAM_SOURCES.get(model_type, "https://github.com/facebookresearch/segment-anything#model-checkpoints")


def import_optional(module: str, what: str) -> ModuleType:
    """Import an optional library of the vlm backend, or raise DependencyError with the install hint; also when the
    library is there but does not load (a torchvision built for another torch: 'operator torchvision::nms does not
    exist')."""
    try:
        return errors.import_optional(module, what, INSTALL_HINT)
    except (RuntimeError, OSError) as exc:
        reason = " ".join(str(exc).split())
        raise DependencyError(
            f"{what}: the Python package '{module}' is installed but does not load ({type(exc).__name__}: {reason}); "
            f"torchvision must be the build for the installed torch: {INSTALL_HINT}"
        ) from exc


class YoloWorldDetector:
    """YOLO-World (ultralytics) with the household vocabulary as its classes.

    YOLO-World scores a region by one class confidence, its region-to-text similarity after the objectness
    prior; it serves as both the box score and the text score, so δ_box and δ_text both apply to it.
    """

    def __init__(
        self, weights: str, vocabulary: Sequence[str], box_threshold: float, text_threshold: float, device: str = "cpu"
    ) -> None:
        path = require_weights(weights, "YOLO-World", "perception.vlm.yolo_world_weights", YOLO_WORLD_SOURCE)
        ultralytics = import_optional("ultralytics", "YOLO-World")
        model = ultralytics.YOLOWorld(str(path))
        try:
            model.set_classes(list(vocabulary))
        except (OSError, RuntimeError, ImportError) as exc:
            # set_classes embeds the class names with ultralytics' own CLIP text model, fetched on first use.
            raise DependencyError(
                f"YOLO-World could not embed its vocabulary offline ({exc.__class__.__name__}: {exc}); "
                "its CLIP text weights must be in ultralytics' cache"
            ) from exc
        self._init(model, box_threshold, text_threshold, device)

    @classmethod
    def from_model(
        cls, model: Any, box_threshold: float, text_threshold: float, device: str = "cpu"
    ) -> YoloWorldDetector:
        """Wrap an already built ultralytics YOLO-World model (its classes already set)."""
        detector = cls.__new__(cls)
        detector._init(model, box_threshold, text_threshold, device)
        return detector

    def _init(self, model: Any, box_threshold: float, text_threshold: float, device: str) -> None:
        self.model = model
        self.box_threshold = box_threshold
        self.text_threshold = text_threshold
        self.device = device

    def detect(self, frame: Frame) -> list[Detection]:
        """Boxes whose confidence passes both thresholds, labelled with the vocabulary."""
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])  # ultralytics reads numpy images as OpenCV BGR
        threshold = min(self.box_threshold, self.text_threshold)
        result = self.model.predict(bgr, conf=threshold, device=self.device, verbose=False)[0]
        boxes = result.boxes
        xyxy = boxes.xyxy.cpu().numpy().astype(float)
        conf = boxes.conf.cpu().numpy().astype(float)
        cls = boxes.cls.cpu().numpy().astype(int)
        out = []
        for box, score, c in zip(xyxy, conf, cls, strict=True):
            detection = Detection(box, str(result.names[int(c)]), float(score), float(score))
            if passes_thresholds(detection, self.box_threshold, self.text_threshold):
                out.append(detection)
        return out


class SamSegmenter:
    """Segment Anything, prompted with each detection's box; one mask per box."""

    def __init__(self, model_type: str, weights: str, device: str = "cpu") -> None:
        path = require_weights(weights, f"SAM ({model_type})", "perception.vlm.sam_weights", sam_source(model_type))
        segment_anything = import_optional("segment_anything", "SAM")
        sam = segment_anything.sam_model_registry[model_type](checkpoint=str(path))
        self._init(sam, device)

    @classmethod
    def from_model(cls, sam: Any, device: str = "cpu") -> SamSegmenter:
        """Wrap an already built SAM model (e.g. `sam_model_registry['vit_b'](checkpoint=None)`)."""
        segmenter = cls.__new__(cls)
        segmenter._init(sam, device)
        return segmenter

    def _init(self, sam: Any, device: str) -> None:
        segment_anything = import_optional("segment_anything", "SAM")
        sam.to(device)
        sam.eval()
        self.predictor = segment_anything.SamPredictor(sam)

    def segment(self, frame: Frame, detections: Sequence[Detection]) -> np.ndarray:
        """(N, H, W) bool masks; the image is encoded once per frame."""
        if not detections:
            return empty_masks(frame)
        self.predictor.set_image(np.ascontiguousarray(frame.rgb), image_format="RGB")
        masks = []
        for detection in detections:
            mask, _, _ = self.predictor.predict(box=np.asarray(detection.box_xyxy, float), multimask_output=False)
            masks.append(np.asarray(mask[0], bool))
        return np.stack(masks)


class ClipVisualEmbedder:
    """CLIP's image tower (open_clip) on box crops; unit rows in the space of CLIP's text tower."""

    def __init__(self, model_name: str, weights: str, device: str = "cpu") -> None:
        path = require_weights(weights, f"CLIP {model_name}", "embed.clip_weights", clip_source(model_name))
        open_clip = import_optional("open_clip", "CLIP")
        model, _, preprocess = open_clip.create_model_and_transforms(model_name, pretrained=str(path), device=device)
        self._init(model, preprocess, f"clip:{model_name}", device)

    @classmethod
    def from_model(cls, model: Any, preprocess: Any, name: str, device: str = "cpu") -> ClipVisualEmbedder:
        """Wrap an already built open_clip model and its image transform."""
        embedder = cls.__new__(cls)
        embedder._init(model, preprocess, name, device)
        return embedder

    def _init(self, model: Any, preprocess: Any, name: str, device: str) -> None:
        self.model = model.eval()
        self.preprocess = preprocess
        self.name = name
        self.device = device
        self.dim = int(getattr(model.visual, "output_dim", 0)) or self._probe_dim()

    def _probe_dim(self) -> int:
        return int(self._encode([np.zeros((8, 8, 3), np.uint8)]).shape[1])

    def _encode(self, crops: list[np.ndarray]) -> np.ndarray:
        import torch
        from PIL import Image

        batch = torch.stack([self.preprocess(Image.fromarray(c)) for c in crops]).to(self.device)
        with torch.no_grad():
            features = self.model.encode_image(batch).float().cpu().numpy()
        return features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-12)

    def embed(self, frame: Frame, detections: Sequence[Detection], masks: np.ndarray) -> np.ndarray:
        """(N, D) float32 unit rows of the box crops (grown by 10 %)."""
        if not detections:
            return np.zeros((0, self.dim), np.float32)
        height, width = frame.rgb.shape[:2]
        crops = []
        for detection in detections:
            x0, y0, x1, y1 = np.asarray(detection.box_xyxy, float)
            grow = CROP_MARGIN * np.array([x1 - x0, y1 - y0])
            box = np.array([x0 - grow[0], y0 - grow[1], x1 + grow[0], y1 + grow[1]])
            ix0, iy0, ix1, iy1 = box_to_pixels(box, width, height)
            crops.append(np.ascontiguousarray(frame.rgb[iy0 : max(iy1, iy0 + 1), ix0 : max(ix1, ix0 + 1)]))
        return self._encode(crops).astype(np.float32)


@dataclass
class VlmBackends:
    detector: YoloWorldDetector
    segmenter: SamSegmenter
    embedder: ClipVisualEmbedder


def check_clip_text(cfg: Config, text_embedder: TextEmbedder | None = None) -> None:
    """ConfigError unless the BIM text embeddings come from CLIP's text tower of `embed.clip_model`."""
    if cfg.embed.text_model != "clip":
        raise ConfigError(
            f"perception.backend=vlm embeds crops with CLIP's image tower, but embed.text_model is "
            f"'{cfg.embed.text_model}': the BIM text embeddings must come from CLIP's text tower "
            "(set embed.text_model=clip and embed.clip_weights, and rebuild the prior with it)"
        )
    expected = f"clip:{cfg.embed.clip_model}"
    if text_embedder is not None and text_embedder.name != expected:
        raise ConfigError(f"the vlm backend needs the text embedder {expected}, got {text_embedder.name}")


def check_vlm_ready(cfg: Config, text_embedder: TextEmbedder | None = None) -> None:
    """Everything the vlm backend needs that can be checked without loading a model, in milliseconds: its three
    weight files (one DependencyError line naming each unusable file, its key and where to download it), CLIP text
    for the BIM (ConfigError), then its libraries (DependencyError naming `bash tools/setup.sh --vlm`)."""
    vlm, clip = cfg.perception.vlm, cfg.embed.clip_model
    problems = [
        weights_problem(vlm.yolo_world_weights, "YOLO-World", "perception.vlm.yolo_world_weights", YOLO_WORLD_SOURCE),
        weights_problem(
            vlm.sam_weights, f"SAM ({vlm.sam_model_type})", "perception.vlm.sam_weights", sam_source(vlm.sam_model_type)
        ),
        weights_problem(cfg.embed.clip_weights, f"CLIP {clip}", "embed.clip_weights", clip_source(clip)),
    ]
    found = [problem for problem in problems if problem is not None]
    if found:
        raise DependencyError("perception.backend=vlm: " + "; ".join(found))
    check_clip_text(cfg, text_embedder)
    missing = [module for module in LIBRARIES if not _installed(module)]
    if missing:
        names = ", ".join(f"'{module}' ({LIBRARIES[module]})" for module in missing)
        raise DependencyError(f"perception.backend=vlm needs the Python packages {names}: {INSTALL_HINT}")


def _installed(module: str) -> bool:
    """Whether `module` can be found without importing it (a module set to None in sys.modules cannot)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def make_vlm_backends(cfg: Config, vocabulary: Sequence[str], text_embedder: TextEmbedder | None = None) -> VlmBackends:
    """YOLO-World + SAM + CLIP from the config's weight files, on `perception.device`."""
    # Files, libraries and the text encoder are checked before any heavy import: found in milliseconds.
    check_vlm_ready(cfg, text_embedder)
    p = cfg.perception
    log.info("loading YOLO-World, SAM %s and CLIP %s on %s", p.vlm.sam_model_type, cfg.embed.clip_model, p.device)
    return VlmBackends(
        YoloWorldDetector(p.vlm.yolo_world_weights, vocabulary, p.box_threshold, p.text_threshold, p.device),
        SamSegmenter(p.vlm.sam_model_type, p.vlm.sam_weights, p.device),
        ClipVisualEmbedder(cfg.embed.clip_model, cfg.embed.clip_weights, p.device),
    )
