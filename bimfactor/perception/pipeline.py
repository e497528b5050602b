"""The perception runner: detect ▸ segment ▸ embed ▸ lift ▸ online scene graph, frame by frame.

`make_perception` picks the backend that `perception.backend` names (`choose_backend`: `auto` picks from what the
sequence holds) and wires it to an `OnlineSceneGraph`; `Perception.step` runs one frame and returns what the graph
did and what the localizer should see.
"""

from __future__ import annotations

import logging
import time
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimfactor.bim.vocabulary import Vocabulary
from bimfactor.config import Config, PerceptionConfig, config_file, updated
from bimfactor.embed.text import TextEmbedder
from bimfactor.errors import DependencyError, InputError
from bimfactor.perception.base import Detection, Detector, Embedder, Segmenter, TextReader, TextReading
from bimfactor.perception.boxes import BoxSegmenter, LabelEmbedder
from bimfactor.perception.detections import DetectionsTable, FileDetector, detection_records, write_detections
from bimfactor.perception.scene_graph import OnlineSceneGraph, UpdateStats
from bimfactor.perception.sim import (
    LabelConfusion,
    SimDetector,
    SimEmbedder,
    SimSegmenter,
    load_sim_errors,
    reported_labels,
)
from bimfactor.perception.text import SimTextReader, locate_readings
from bimfactor.perception.yolox import LabelTable, YoloxDetector, coco_label_table
from bimfactor.progress import progress
from bimfactor.types import Frame, Observations, SequenceMeta

log = logging.getLogger(__name__)
_WARNED = {"no_ocr": False}  # a missing RapidOCR is said once a process, not once a sequence

# Independent random streams of the sim backend within one (seed, sequence).
DETECTOR_STREAM, SEGMENTER_STREAM, EMBEDDER_STREAM, READER_STREAM = 0xDE7, 0x5E6, 0xE3B, 0x7E7


def vocabulary_of(cfg: Config) -> Vocabulary:
    """The object vocabulary the prior's labels come from (`bim.objects.vocabulary_file`)."""
    return Vocabulary.load(config_file(cfg.bim.objects.vocabulary_file))


def household_vocabulary(cfg: Config) -> list[str]:
    """The open-vocabulary detector's classes: the labels of bimfactor/configs/vocabulary.yaml, in table order."""
    return vocabulary_of(cfg).labels


@dataclass
class FrameResult:
    """One frame through perception: the detections, masks (N, H, W), embeddings (N, D), graph stats, view
    (with the text read, placed in the robot frame), the text readings as the reader gave them, and the milliseconds
    each part took: `detector`, `lifting` (segmentation, embeddings and the scene graph) and `plates` (reading and
    placing text)."""

    detections: list[Detection]
    masks: np.ndarray
    embeddings: np.ndarray
    stats: UpdateStats
    observations: Observations
    readings: list[TextReading]
    timing_ms: dict[str, float]


class Perception:
    """Detector, segmenter and visual embedder feeding one online scene graph; optionally a text reader."""

    def __init__(
        self,
        detector: Detector,
        segmenter: Segmenter,
        embedder: Embedder,
        graph: OnlineSceneGraph,
        reader: TextReader | None = None,
        backend: str = "",
    ) -> None:
        self.detector = detector
        self.segmenter = segmenter
        self.embedder = embedder
        self.graph = graph
        self.reader = reader
        self.backend = backend  # the `perception.backend` it runs (`auto` resolved)

    def perceive(self, frame: Frame) -> tuple[list[Detection], np.ndarray, np.ndarray]:
        """The 2D front end alone: detections, (N, H, W) masks, (N, D) embeddings."""
        detections = self.detector.detect(frame)
        return detections, *self._describe(frame, detections)

    def _describe(self, frame: Frame, detections: list[Detection]) -> tuple[np.ndarray, np.ndarray]:
        """The detections' (N, H, W) masks and (N, D) embeddings."""
        masks = self.segmenter.segment(frame, detections)
        return masks, self.embedder.embed(frame, detections, masks)

    def fuse(
        self, frame: Frame, T_world_camera: np.ndarray
    ) -> tuple[list[Detection], np.ndarray, np.ndarray, UpdateStats, dict[str, float]]:
        """Detect, lift and fuse one frame into the graph seen from the (4, 4) camera pose: the detections, masks,
        embeddings and graph stats, and the milliseconds of the `detector` and of the `lifting` (segmentation,
        embeddings, graph update)."""
        started = time.perf_counter()
        detections = self.detector.detect(frame)
        detected = time.perf_counter()
        masks, embeddings = self._describe(frame, detections)
        stats = self.graph.update(frame, detections, masks, embeddings, T_world_camera)
        timing = {"detector": (detected - started) * 1000, "lifting": (time.perf_counter() - detected) * 1000}
        return detections, masks, embeddings, stats, timing

    def step(self, frame: Frame, plate_columns: np.ndarray | None = None) -> FrameResult:
        """Perceive one frame, update the graph at the frame's odometry pose, and list the nodes in view; read text
        where the reader can (`plate_columns` (W,) bool: the image columns a plate can be in, None: anywhere)."""
        T_odom_cam = self.graph.camera_pose(frame.odom_pose)
        detections, masks, embeddings, stats, timing_ms = self.fuse(frame, T_odom_cam)
        started = time.perf_counter()
        view = self.graph.view(frame.depth_m, T_odom_cam)
        # the nodes in view detected in this frame: the paper's "whenever new observations arrive"
        observations = self.graph.observations(frame.odom_pose, view=view, since_frame=frame.index)
        viewed = time.perf_counter()
        readings = self.reader.read(frame, plate_columns) if self.reader is not None else []
        if readings:
            g = self.graph
            observations.texts = locate_readings(
                readings, frame.depth_m, g.intrinsics, g.T_base_camera, g.cfg.max_depth_m
            )
        timing_ms["lifting"] += (viewed - started) * 1000
        timing_ms["plates"] = (time.perf_counter() - viewed) * 1000
        return FrameResult(detections, masks, embeddings, stats, observations, readings, timing_ms)

    def run(self, frames: Iterable[Frame], show_progress: bool = False) -> list[FrameResult]:
        """`step` over a sequence of frames."""
        frames = list(frames)
        it = progress(frames, desc="perception", unit="frame") if show_progress else frames
        return [self.step(frame) for frame in it]


def sim_rng(seed: int, meta: SequenceMeta, stream: int) -> np.random.Generator:
    """The generator of one sim-backend stream for a (seed, sequence)."""
    return np.random.default_rng([seed, zlib.crc32(meta.name.encode()), stream])


def choose_backend(p: PerceptionConfig, meta: SequenceMeta, has_detections: bool) -> str:
    """The backend `perception.backend` names; `auto` picks from what the sequence holds: the simulator's instance
    table → sim, a detections file → detections, else the shipped detector (yolox)."""
    if p.backend == "detections" and not has_detections:
        raise InputError(
            f"sequence {meta.name}: perception.backend=detections needs a detections file "
            "(SEQ_DIR/detections.jsonl or localize --detections FILE)"
        )
    if p.backend != "auto":
        return p.backend
    if meta.instances:
        return "sim"
    return "detections" if has_detections else "yolox"


def make_perception(
    cfg: Config,
    meta: SequenceMeta,
    text_embedder: TextEmbedder,
    seed: int | None = None,
    sim_preset: str | None = None,
    detections: DetectionsTable | None = None,
    read_text: bool | None = None,
    mapping: bool = False,
) -> Perception:
    """The perception stack `cfg.perception.backend` names for a sequence (`choose_backend`); `seed` defaults to
    `cfg.seed`.

    The sim backend needs the simulator's instance table in `meta`; `sim_preset` overrides `perception.sim_preset`.
    The detections backend reads `detections` (`detections.read_detections`). `read_text` (default
    `perception.text.enabled`) says whether door plates are read: the localizer reads none when its prior has none.
    With `perception.text.reader: auto` on real frames and RapidOCR not installed, it reads none and says so once.
    `mapping`: a recording's graph from 6-DoF camera poses with no prior to match (`perception.mapping`): the shipped
    detector keeps COCO's class names, and boxes are segmented with no floor cut (a hand-held camera has no base).
    """
    p = cfg.perception
    seed = cfg.seed if seed is None else seed
    backend = choose_backend(p, meta, detections is not None)
    vocabulary = household_vocabulary(cfg)
    graph = OnlineSceneGraph(p, meta.intrinsics, meta.T_base_camera, embedding_dim=text_embedder.dim)
    reader: TextReader | None = None
    read_text = p.text.enabled if read_text is None else read_text
    if read_text and (p.text.reader == "rapidocr" or (p.text.reader == "auto" and backend != "sim")):
        from bimfactor.perception.ocr import PlateReader

        try:
            reader = PlateReader(meta.intrinsics, meta.T_base_camera, p.text.min_score)
        except DependencyError as exc:
            if p.text.reader == "rapidocr":
                raise
            if not _WARNED["no_ocr"]:
                log.warning("door plates are not read: %s", exc)
                _WARNED["no_ocr"] = True
    elif read_text:
        reader = SimTextReader(meta, p.text, sim_rng(seed, meta, READER_STREAM))
    if backend == "vlm":
        from bimfactor.perception.vlm import make_vlm_backends

        vlm = make_vlm_backends(cfg, vocabulary, text_embedder)
        return Perception(vlm.detector, vlm.segmenter, vlm.embedder, graph, reader, backend)
    if backend in ("detections", "yolox"):
        detector: Detector
        if backend == "detections":
            assert detections is not None  # choose_backend checked it
            if detections.embedding_dim not in (None, text_embedder.dim):
                raise InputError(
                    f"{detections.path}: embeddings have {detections.embedding_dim} values, the text encoder "
                    f"({text_embedder.name}) gives {text_embedder.dim}"
                )
            detector = FileDetector(detections, p.box_threshold, p.text_threshold)
        else:
            table = (
                LabelTable.coco() if mapping else coco_label_table(vocabulary_of(cfg), text_embedder, p.sim_threshold)
            )
            detector = YoloxDetector(table, max(p.box_threshold, p.text_threshold))
        return Perception(
            detector,
            box_segmenter(cfg, meta, mapping),
            LabelEmbedder(text_embedder),
            graph,
            reader,
            backend,
        )
    errors = load_sim_errors(p, sim_preset)
    if errors.detector == "yolox":  # the shipped detector's eyes: its classes, boxes segmented by depth, labels
        emitted = coco_label_table(vocabulary_of(cfg), text_embedder, p.sim_threshold).vocabulary_labels
        reported = reported_labels([str(r["label"]) for r in meta.instances], emitted, text_embedder, p.sim_threshold)
        confusion = LabelConfusion(emitted, text_embedder, errors.confusion_temperature)
        detector = SimDetector(
            meta, errors, confusion, p.box_threshold, p.text_threshold, sim_rng(seed, meta, DETECTOR_STREAM), reported
        )
        return Perception(detector, box_segmenter(cfg, meta), LabelEmbedder(text_embedder), graph, reader, backend)
    confusion = LabelConfusion(vocabulary, text_embedder, errors.confusion_temperature)
    detector = SimDetector(
        meta, errors, confusion, p.box_threshold, p.text_threshold, sim_rng(seed, meta, DETECTOR_STREAM)
    )
    segmenter = SimSegmenter(errors, sim_rng(seed, meta, SEGMENTER_STREAM))
    embedder = SimEmbedder(meta, text_embedder, vocabulary, errors, seed, sim_rng(seed, meta, EMBEDDER_STREAM))
    return Perception(detector, segmenter, embedder, graph, reader, backend)


def box_segmenter(cfg: Config, meta: SequenceMeta, mapping: bool = False) -> BoxSegmenter:
    """The depth segmentation of a box detector's boxes: above the floor of a robot's base frame, or (`mapping`, a
    camera with no base) every return."""
    return BoxSegmenter(meta.intrinsics, meta.T_base_camera, cfg.perception, None if mapping else cfg.sensor.min_z_m)


def write_sim_detections(
    path: str | Path, cfg: Config, meta: SequenceMeta, frames: Iterable[Frame], text_embedder: TextEmbedder, seed: int
) -> int:
    """Write the sim backend's detections of a simulated sequence's frames as a detections file (what `bimfactor
    simulate` puts beside the frames): its noisy detector's labels, box scores and boxes, its masks and its crop
    embeddings, drawn from the streams the sim backend draws from with `seed`. Returns the number of detections."""
    sim = updated(cfg, {"perception.backend": "sim", "perception.text.enabled": False})
    perception = make_perception(sim, meta, text_embedder, seed)
    count = 0

    def perceive(frame: Frame) -> tuple[list[Detection], np.ndarray, np.ndarray]:
        nonlocal count
        detections, masks, embeddings = perception.perceive(frame)
        count += len(detections)
        return detections, masks, embeddings

    write_detections(path, detection_records(frames, perceive))
    return count
