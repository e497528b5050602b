"""The vlm backend's plumbing: config checks, missing libraries and weights (through the CLI too: exit 3, one line
naming the file, its key and where to download it, before the prior or the sequence is read), and (where the
libraries are installed) forward passes through randomly initialised models, which need no weight files."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from bimfactor import errors
from bimfactor.config import Config, load_config
from bimfactor.embed.text import ClipTextEmbedder
from bimfactor.errors import ConfigError, DependencyError
from bimfactor.perception.base import Detection, Detector, Embedder, Segmenter
from bimfactor.perception.pipeline import make_perception
from bimfactor.perception.vlm import (
    INSTALL_HINT,
    LIBRARIES,
    ClipVisualEmbedder,
    SamSegmenter,
    YoloWorldDetector,
    check_clip_text,
    check_vlm_ready,
    clip_source,
    import_optional,
    make_vlm_backends,
    sam_source,
)
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta
from tests.cli import assert_one_line_error, invoke

YOLO_URL = "https://github.com/ultralytics/assets/releases"
CLIP_URL = "https://huggingface.co/laion/CLIP-ViT-L-14-DataComp.XL-s13B-b90K"


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


@pytest.fixture
def weight_files(tmp_path: Path) -> list[str]:
    """`--set` overrides naming three (dummy) weight files that exist."""
    files = {
        "perception.vlm.yolo_world_weights": "yolov8s-worldv2.pt",
        "perception.vlm.sam_weights": "sam_vit_b_01ec64.pth",
        "embed.clip_weights": "open_clip_pytorch_model.bin",
    }
    for name in files.values():
        (tmp_path / name).write_bytes(b"not really weights")
    return [f"{key}={tmp_path / name}" for key, name in files.items()]


def test_clip_crops_with_minilm_text_is_a_config_error(config_overrides, text_embedder, weight_files) -> None:
    cfg = vlm_config(config_overrides, *weight_files)
    meta = SequenceMeta("x", "sim", CameraIntrinsics.from_hfov(160, 120, 90.0), np.eye(4))
    with pytest.raises(ConfigError, match=r"embed\.text_model=clip"):
        make_perception(cfg, meta, text_embedder)
    with pytest.raises(ConfigError, match="needs the text embedder clip:ViT-L-14"):
        check_clip_text(vlm_config(config_overrides, "embed.text_model=clip"), text_embedder)
    check_clip_text(vlm_config(config_overrides, "embed.text_model=clip"), FakeClipText())


def test_unset_weights_name_the_config_key(config_overrides) -> None:
    cfg = vlm_config(config_overrides, "embed.text_model=clip")
    with pytest.raises(DependencyError, match=r"set perception\.vlm\.yolo_world_weights") as info:
        make_vlm_backends(cfg, ["chair"], FakeClipText())
    # all three in the one line, each with where its file is downloaded
    message = str(info.value)
    assert "\n" not in message
    for key, source in [
        ("perception.vlm.yolo_world_weights", f"yolov8s-worldv2.pt (or the m, l, x one) from {YOLO_URL}"),
        ("perception.vlm.sam_weights", "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth"),
        ("embed.clip_weights", f"open_clip_pytorch_model.bin from {CLIP_URL}"),
    ]:
        assert f"set {key} (download {source})" in message


def test_missing_weight_files_are_named_exactly(config_overrides, tmp_path: Path) -> None:
    yolo, sam, clip = tmp_path / "yolov8s-worldv2.pt", tmp_path / "sam_vit_b.pth", tmp_path / "clip-vit-l-14.bin"
    keys = (
        "embed.text_model=clip",
        f"perception.vlm.yolo_world_weights={yolo}",
        f"perception.vlm.sam_weights={sam}",
        f"embed.clip_weights={clip}",
    )
    cfg = vlm_config(config_overrides, *keys)
    for missing, key in zip((yolo, sam, clip), keys[1:], strict=True):
        with pytest.raises(DependencyError) as info:
            make_vlm_backends(cfg, ["chair"], FakeClipText())
        assert f"not found: {missing} (from {key.split('=')[0]}; download " in str(info.value)
        missing.write_bytes(b"not really weights")


def test_clip_weights_asked_for_in_the_vlm_block_name_the_key(cli_config_args, tmp_path: Path) -> None:
    """CLIP's checkpoint is the text encoder's (embed.clip_weights): looking for it beside YOLO-World's says so."""
    config = tmp_path / "vlm.yaml"
    config.write_text("perception:\n  vlm:\n    clip_weights: weights/clip.bin\n")
    result = invoke("config", "-c", config)
    assert_one_line_error(
        result, exit_code=2, contains="'perception.vlm.clip_weights': the key is 'embed.clip_weights'"
    )
    result = invoke("config", *cli_config_args, "--set", "perception.vlm.clip_model=ViT-B-32")
    assert_one_line_error(result, exit_code=2, contains="the key is 'embed.clip_model'")


def test_weight_sources_follow_the_configured_model() -> None:
    """SAM's checkpoint by backbone (the segment-anything repository's links), CLIP's by open_clip architecture."""
    assert sam_source("vit_l").endswith("/segment_anything/sam_vit_l_0b3195.pth")
    assert sam_source("vit_h").endswith("/segment_anything/sam_vit_h_4b8939.pth")
    assert "timm/vit_large_patch14_clip_224.openai" in clip_source("ViT-L-14-quickgelu")
    other = clip_source("ViT-H-14")
    assert "list_pretrained_tags_by_model('ViT-H-14')" in other and "https://huggingface.co" in other
    with pytest.raises(
        DependencyError, match=re.escape(f"(from embed.clip_weights; download {clip_source('ViT-L-14')})")
    ):
        ClipTextEmbedder("ViT-L-14", "no/such/clip.bin")  # the text encoder says the same


def test_a_folder_is_not_a_weights_file(config_overrides, weight_files, tmp_path: Path) -> None:
    cfg = vlm_config(config_overrides, *weight_files, "embed.text_model=clip", f"perception.vlm.sam_weights={tmp_path}")
    with pytest.raises(
        DependencyError, match=re.escape(f"SAM (vit_b) weights file is a folder, not a weights file: {tmp_path}")
    ):
        check_vlm_ready(cfg)


def localize(tmp_path: Path, cli_config_args: list[str], sets: list[str]):
    """`bimfactor localize` with `--set` for each of `sets`, tmp_path as prior and sequence (read only after the
    vlm backend's checks)."""
    options = [arg for assignment in sets for arg in ("--set", assignment)]
    return invoke("localize", tmp_path, tmp_path, "-o", tmp_path / "run", *cli_config_args, *options)


def test_localize_without_weights_fails_fast_with_exit_3(cli_config_args, tmp_path: Path) -> None:
    """Before the prior and the sequence are read: empty folders would be exit 2 were they read first."""
    prior, sequence = tmp_path / "prior", tmp_path / "sequence"
    prior.mkdir()
    sequence.mkdir()
    for command in ("localize", "refine"):
        result = invoke(
            command,
            prior,
            sequence,
            "-o",
            tmp_path / f"run-{command}",
            *cli_config_args,
            "--set",
            "perception.backend=vlm",
        )
        line = assert_one_line_error(result, exit_code=3, contains="perception.backend=vlm: YOLO-World needs")
        for text in (
            "perception.vlm.yolo_world_weights",
            YOLO_URL,
            "sam_vit_b_01ec64.pth",
            "embed.clip_weights",
            CLIP_URL,
        ):
            assert text in line
        assert not (tmp_path / f"run-{command}").exists()


def test_localize_names_the_one_missing_file(cli_config_args, weight_files, tmp_path: Path) -> None:
    missing = tmp_path / "sam_vit_l_0b3195.pth"
    sets = [
        *weight_files,
        "perception.backend=vlm",
        "perception.vlm.sam_model_type=vit_l",
        f"perception.vlm.sam_weights={missing}",
    ]
    result = localize(tmp_path, cli_config_args, sets)
    line = assert_one_line_error(result, exit_code=3)
    assert line.endswith(
        f"SAM (vit_l) weights file not found: {missing} (from perception.vlm.sam_weights; download "
        "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth)"
    )


def test_localize_with_weights_but_minilm_text_is_exit_2(cli_config_args, weight_files, tmp_path: Path) -> None:
    sets = [*weight_files, "perception.backend=vlm"]
    result = localize(tmp_path, cli_config_args, sets)
    assert_one_line_error(result, exit_code=2, contains="embed.text_model=clip")


@pytest.mark.parametrize("module", list(LIBRARIES))
def test_localize_without_a_vlm_library_names_setup(
    module: str, cli_config_args, weight_files, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed, whether it is or not
    sets = [*weight_files, "perception.backend=vlm", "embed.text_model=clip"]
    result = localize(tmp_path, cli_config_args, sets)
    line = assert_one_line_error(result, exit_code=3, contains="bash tools/setup.sh --vlm")
    assert f"'{module}' ({LIBRARIES[module]})" in line


def test_auto_never_picks_vlm_it_takes_the_shipped_detector(config_overrides, tmp_path: Path) -> None:
    """A recorded sequence without detections runs the shipped detector under auto, even where vlm weights are set
    (missing ones here): vlm is asked for by name, and auto is never an error for lack of weights."""
    from bimfactor.workflows import _perception_source

    class Recorded:
        meta = SequenceMeta("office", "tum", CameraIntrinsics.from_hfov(160, 120, 90.0), np.eye(4))

    cfg = load_config(None, [*config_overrides, f"perception.vlm.yolo_world_weights={tmp_path / 'yw.pt'}"])
    resolved, table, line = _perception_source(cfg, Recorded(), tmp_path, None, None)
    assert resolved.perception.backend == "yolox" and table is None and line.startswith("perception: yolox")


def test_a_library_that_does_not_load_is_a_dependency_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """PyPI's torchvision beside a CPU torch: importing ultralytics raises RuntimeError, not ImportError."""

    def broken(module: str, what: str, install_hint: str):
        raise RuntimeError("operator torchvision::nms does not exist")

    monkeypatch.setattr(errors, "import_optional", broken)
    with pytest.raises(
        DependencyError, match=r"'ultralytics' is installed but does not load \(RuntimeError: operator"
    ) as info:
        import_optional("ultralytics", "YOLO-World")
    assert str(info.value).endswith(f"torchvision must be the build for the installed torch: {INSTALL_HINT}")


@pytest.mark.parametrize(
    ("module", "build"),
    [
        ("ultralytics", lambda p: YoloWorldDetector(str(p), ["chair"], 0.25, 0.25)),
        ("segment_anything", lambda p: SamSegmenter("vit_b", str(p))),
        ("open_clip", lambda p: ClipVisualEmbedder("ViT-B-32", str(p))),
    ],
)
def test_a_missing_library_names_the_install_extra(
    module: str, build, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed, whether it is or not
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
    pytest.importorskip("segment_anything")
    from segment_anything.build_sam import _build_sam  # the registry's builder, here with a 2-block encoder

    # SAM's real ViT-B encoder takes 20 s on two CPU cores; the prompt path is the same with a tiny one
    sam = _build_sam(encoder_embed_dim=64, encoder_depth=2, encoder_num_heads=2, encoder_global_attn_indexes=[1])
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
