"""The `yolox` perception backend: YOLOX-Nano, the detector that ships inside the package, run by ONNX Runtime.

YOLOX-Nano (Megvii, Apache-2.0; `bimfactor/models/yolox_nano.onnx`) is trained on COCO's 80 classes. A frame is
letterboxed into 416 × 416, decoded per grid cell of the strides 8, 16 and 32, thresholded at
`perception.box_threshold` and suppressed (`NMSBoxes`, IoU `NMS_IOU`); a COCO class becomes a label of the prior's
vocabulary by its rules, then by the nearest label within δ_sim, or is dropped (`coco_label_table`). Its boxes go
through the depth segmentation of any box detector (`perception.boxes`). What it sees: docs/perception.md.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from bimfactor import errors
from bimfactor.bim.vocabulary import Vocabulary, normalise
from bimfactor.embed.text import TextEmbedder
from bimfactor.perception.base import Detection
from bimfactor.types import Frame

MODEL_FILE = "yolox_nano.onnx"
"""The shipped network, in `bimfactor/models/` (sha256 `MODEL_SHA256`)."""
MODEL_SHA256 = "695e750a5d5754bb5a8d5325643b59282191a7e7a564e435a415fd3c578eab14"
INPUT_SIZE = 416
"""The network's square input side."""
PAD_VALUE = 114
"""The letterbox's grey."""
STRIDES = (8, 16, 32)
NMS_IOU = 0.45
"""Boxes overlapping more than this (IoU) are one object (YOLOX's own setting), whatever their classes: the network
scores its classes independently, and one screen comes out as both "tv" and "laptop"."""
INSTALL_HINT = "pip install onnxruntime (bash tools/setup.sh installs it)"

COCO_CLASSES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow", "elephant",
    "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard",
    "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange", "broccoli",
    "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant", "bed", "dining table", "toilet",
    "tv", "laptop", "mouse", "remote", "keyboard", "cell phone", "microwave", "oven", "toaster", "sink",
    "refrigerator", "book", "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip
"""YOLOX's 80 COCO classes, in the network's output order."""


def model_path() -> Path:
    """The shipped YOLOX-Nano file inside the installed package."""
    return Path(str(resources.files("bimfactor") / "models" / MODEL_FILE))


@dataclass(frozen=True)
class LabelTable:
    """What each COCO class is called in the prior's vocabulary: `labels[k]` the label of class k ("" when the class
    maps to nothing), `how[k]` "rule", "embedding (cos 0.71)" or "" (dropped)."""

    labels: tuple[str, ...]
    how: tuple[str, ...]

    @classmethod
    def coco(cls) -> LabelTable:
        """Every COCO class under its own name: the open-set labels of a scene graph built without a prior."""
        return cls(COCO_CLASSES, ("coco",) * len(COCO_CLASSES))

    @property
    def kept(self) -> dict[str, str]:
        """COCO class → vocabulary label, for the classes that map to one."""
        return {c: label for c, label in zip(COCO_CLASSES, self.labels, strict=True) if label}

    @property
    def vocabulary_labels(self) -> list[str]:
        """The labels the detector can report, in COCO order, without repeats."""
        return list(dict.fromkeys(label for label in self.labels if label))


def coco_label_table(vocabulary: Vocabulary, embedder: TextEmbedder, min_similarity: float) -> LabelTable:
    """Each COCO class's vocabulary label: by the vocabulary's rules, else the nearest label by `embedder` with a
    cosine of at least `min_similarity`, else none."""
    return _label_table(vocabulary, _CachedEncoder(embedder), float(min_similarity))


class _CachedEncoder:
    """A text embedder keyed by its name, so the table is built once per encoder, vocabulary and threshold."""

    def __init__(self, embedder: TextEmbedder) -> None:
        self.embedder = embedder

    def __hash__(self) -> int:
        return hash(self.embedder.name)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _CachedEncoder) and other.embedder.name == self.embedder.name


@functools.lru_cache(maxsize=8)
def _label_table(vocabulary: Vocabulary, encoder: _CachedEncoder, min_similarity: float) -> LabelTable:
    vocab_labels = vocabulary.labels
    labels, how = [], []
    pending = []
    for k, name in enumerate(COCO_CLASSES):
        label = vocabulary.match_text(name)
        labels.append(label or "")
        how.append("rule" if label else "")
        if label is None:
            pending.append(k)
    sims = (
        encoder.embedder.encode([normalise(COCO_CLASSES[k]) for k in pending]) @ encoder.embedder.encode(vocab_labels).T
    )
    for row, k in enumerate(pending):
        best = int(np.argmax(sims[row]))
        if sims[row, best] >= min_similarity:
            labels[k], how[k] = vocab_labels[best], f"embedding (cos {sims[row, best]:.2f})"
    return LabelTable(tuple(labels), tuple(how))


def letterbox(bgr: np.ndarray, size: int = INPUT_SIZE) -> tuple[np.ndarray, float]:
    """(1, 3, size, size) float32 network input of an (H, W, 3) uint8 BGR image, and its scale r."""
    height, width = bgr.shape[:2]
    r = min(size / height, size / width)
    new_w, new_h = max(1, round(width * r)), max(1, round(height * r))
    padded = np.full((size, size, 3), PAD_VALUE, np.uint8)
    padded[:new_h, :new_w] = cv2.resize(bgr, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(padded.transpose(2, 0, 1)[None], dtype=np.float32), r


@functools.cache
def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(A, 2) cell corners and (A, 1) strides of the network's rows, strides 8, 16, 32 in order, row-major."""
    cells, strides = [], []
    for stride in STRIDES:
        n = size // stride
        ys, xs = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        cells.append(np.stack([xs, ys], -1).reshape(-1, 2))
        strides.append(np.full((n * n, 1), stride))
    return np.concatenate(cells).astype(np.float32), np.concatenate(strides).astype(np.float32)


def decode(
    output: np.ndarray, r: float, score_threshold: float, keep_class: np.ndarray, size: int = INPUT_SIZE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The network's (A, 85) rows → (N, 4) boxes x0, y0, x1, y1 in image pixels, (N,) scores and (N,) class indices,
    best first, after the score threshold and non-maximum suppression over all classes (`NMS_IOU`); only classes
    where (80,) bool `keep_class`."""
    cells, strides = _grid(size)
    scores_all = output[:, 4:5] * output[:, 5:]
    scores_all[:, ~keep_class] = 0.0
    classes = np.argmax(scores_all, axis=1)
    scores = scores_all[np.arange(len(classes)), classes]
    rows = np.flatnonzero(scores >= score_threshold)
    if len(rows) == 0:
        return np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)
    centre = (output[rows, :2] + cells[rows]) * strides[rows]
    size_px = np.exp(np.minimum(output[rows, 2:4], 20.0)) * strides[rows]
    xywh = np.concatenate([centre - size_px / 2, size_px], axis=1) / r
    keep = cv2.dnn.NMSBoxes(xywh.tolist(), scores[rows].tolist(), float(score_threshold), NMS_IOU)
    keep = np.asarray(keep, np.int64).reshape(-1)
    keep = keep[np.argsort(-scores[rows][keep], kind="stable")]
    boxes = xywh[keep].astype(np.float64)
    boxes[:, 2:] += boxes[:, :2]
    kept = rows[keep]
    return boxes, scores[kept].astype(np.float64), classes[kept].astype(np.int64)


class YoloxDetector:
    """YOLOX-Nano on a frame's colour image; a detection carries the vocabulary label of its class and that class's
    score as both the box and the text score (a closed-set detector has one)."""

    def __init__(self, table: LabelTable, score_threshold: float, path: str | Path | None = None) -> None:
        ort = errors.import_optional("onnxruntime", "The shipped YOLOX detector", INSTALL_HINT)
        path = Path(path) if path is not None else model_path()
        if not path.is_file():
            raise errors.DependencyError(f"the YOLOX model file is missing: {path} (reinstall bimfactor)")
        options = ort.SessionOptions()
        options.log_severity_level = 3  # no warnings about unused initialisers on every start
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.input_name = self.session.get_inputs()[0].name
        self.table = table
        self.score_threshold = float(score_threshold)
        self._keep = np.asarray([bool(label) for label in table.labels])

    def raw(self, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boxes, scores and COCO class indices of an (H, W, 3) BGR image (`decode`), the mapped classes only."""
        blob, r = letterbox(bgr)
        output = self.session.run(None, {self.input_name: blob})[0][0]
        return decode(output, r, self.score_threshold, self._keep)

    def detect(self, frame: Frame) -> list[Detection]:
        """The mapped detections of one frame whose score reaches the threshold, best first."""
        boxes, scores, classes = self.raw(np.ascontiguousarray(frame.rgb[..., ::-1]))
        height, width = frame.rgb.shape[:2]
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, width)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, height)
        return [
            Detection(box, self.table.labels[int(c)], float(s), float(s))
            for box, s, c in zip(boxes, scores, classes, strict=True)
            if box[2] > box[0] and box[3] > box[1]
        ]
