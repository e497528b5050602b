"""The vlm backend's plumbing: config checks, missing libraries and weights, and (where the libraries are
installed) forward passes through randomly initialised models, which need no weight files."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import Config, load_config
from bimfactor.errors import ConfigError, DependencyError
from bimfactor.perception.base import Detection, Detector, Embedder, Segmenter
from bimfactor.perception.pipeline import make_perception
from bimfactor.perception.vlm import (
    INSTALL_HINT,
    ClipVisualEmbedder,
    SamSegmenter,
    YoloWorldDetector,
    check_clip_text,
    make_vlm_backends,
)
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta


class FakeClipText:
    """Stands in for CLIP's text tower in the config checks (no weights needed)."""

    name = "clip:ViT-L-14"
    dim = 768

    def encode(self, texts):
        return np.zeros((len(texts), self.dim), np.float32)


def vlm_config(config_overrides: list[str], *overrides: str) -> Config:
    return load_config(None, [*config_overrides, "perception.backend=vlm", *overrides])


def frame(height: int = 120, width: int = 160) -> Frame:
    rgb = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    return Frame(0, 0.0, rgb, np.full((height, width), 2.0, np.float32), np.zeros(3))


def test_clip_crops_with_minilm_text_is_a_config_error(config_overrides, text_embedder) -> None:
    cfg = vlm_config(config_overrides)
    meta = SequenceMeta("x", "sim", CameraIntrinsics.from_hfov(160, 120, 90.0), np.eye(4))
    with pytest.raises(ConfigError, match=r"embed\.text_model=clip"):
        make_perception(cfg, meta, text_embedder)
    with pytest.raises(ConfigError, match="needs the text embedder clip:ViT-L-14"):
        check_clip_text(vlm_config(config_overrides, "embed.text_model=clip"), text_embedder)
    check_clip_text(vlm_config(config_overrides, "embed.text_model=clip"), FakeClipText())


def test_unset_weights_name_the_config_key(config_overrides) -> None:
    cfg = vlm_config(config_overrides, "embed.text_model=clip")
    with pytest.raises(DependencyError, match=r"set perception\.vlm\.yolo_world_weights"):
        make_vlm_backends(cfg, ["chair"], FakeClipText())


def test_missing_weight_files_are_named_exactly(config_overrides, tmp_path: Path) -> None:
    yolo, sam, clip = tmp_path / "yolov8s-worldv2.pt", tmp_path / "sam_vit_b.pth", tmp_path / "clip-vit-l-14.bin"
    keys = (
        "embed.text_model=clip",
        f"perception.vlm.yolo_world_weights={yolo}",
        f"perception.vlm.sam_weights={sam}",
        f"embed.clip_weights={clip}",
    )
    cfg = vlm_config(config_overrides, *keys)
    for missing in (yolo, sam, clip):
        with pytest.raises(DependencyError) as info:
            make_vlm_backends(cfg, ["chair"], FakeClipText())
        assert f"not found: {missing} " in str(info.value)
        missing.write_bytes(b"not really weights")


@pytest.mark.parametrize(
    ("module", "build"),
    [
        ("ultralytics", lambda p: YoloWorldDetector(str(p), ["chair"], 0.25, 0.25)),
        ("segment_anything", lambda p: SamSegmenter("vit_b", str(p))),
        ("open_clip", lambda p: ClipVisualEmbedder("ViT-B-32", str(p))),
    ],
)
def test_a_missing_library_names_the_install_extra(module: str, build, tmp_path: Path) -> None:
    if importlib.util.find_spec(module) is not None:
        pytest.skip(f"{module} is installed")
    weights = tmp_path / "weights.pt"
    weights.write_bytes(b"x")
    with pytest.raises(DependencyError, match=f"'{module}'.*{re.escape(INSTALL_HINT)}"):
        build(weights)


def test_clip_image_tower_forward_pass_random_weights() -> None:
    open_clip = pytest.importorskip("open_clip")
    model, _, preprocess = open_clip.create_model_and_transforms("ViT-B-32", pretrained=None)
    embedder = ClipVisualEmbedder.from_model(model, preprocess, "clip:ViT-B-32")
    assert isinstance(embedder, Embedder) and embedder.dim == 512
    f = frame()
    boxes = [Detection(np.array([10.0, 10, 60, 50]), "chair", 0.9, 0.9), Detection(np.array([0.0, 0, 5, 5]), "x", 1, 1)]
    out = embedder.embed(f, boxes, np.zeros((2, 120, 160), bool))
    assert out.shape == (2, 512) and out.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-5)
    assert embedder.embed(f, [], np.zeros((0, 120, 160), bool)).shape == (0, 512)


def test_sam_box_prompt_forward_pass_random_weights() -> None:
    segment_anything = pytest.importorskip("segment_anything")
    sam = segment_anything.sam_model_registry["vit_b"](checkpoint=None)
    segmenter = SamSegmenter.from_model(sam)
    assert isinstance(segmenter, Segmenter)
    masks = segmenter.segment(frame(), [Detection(np.array([20.0, 20, 100, 90]), "chair", 0.9, 0.9)])
    assert masks.shape == (1, 120, 160) and masks.dtype == bool
    assert segmenter.segment(frame(), []).shape == (0, 120, 160)


def test_yolo_world_forward_pass_random_weights() -> None:
    ultralytics = pytest.importorskip("ultralytics")
    model = ultralytics.YOLOWorld("yolov8s-worldv2.yaml")  # built from the architecture file, random weights
    detector = YoloWorldDetector.from_model(model, 0.25, 0.25)
    assert isinstance(detector, Detector)
    detections = detector.detect(frame(160, 160))
    assert all(d.box_score >= 0.25 and d.text_score >= 0.25 for d in detections)
