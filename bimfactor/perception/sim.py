"""The `sim` perception backend: detections, masks and crop embeddings from the simulator's instance buffer.

It turns the simulator's ground truth into what a YOLO-World + SAM + CLIP front end would report, with errors drawn
from a named preset (`bimfactor/configs/perception_sim.yaml`, chosen by `perception.sim_preset`): detection quality
by range, visible fraction and area (`SimDetector`), mask errors (`SimSegmenter`) and crop embeddings with a chosen
separation d′ (`SimEmbedder`). The model, its derivation and its measured rates: docs/perception.md, "The sim
backend's model".
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from pydantic import ValidationError

from bimfactor.config import PerceptionConfig, SimPerceptionErrors, config_file
from bimfactor.embed.text import TextEmbedder
from bimfactor.errors import ConfigError, InputError
from bimfactor.perception.base import Detection, box_to_pixels, passes_thresholds
from bimfactor.types import Frame, SequenceMeta

log = logging.getLogger(__name__)

CLUTTER_LABEL = "clutter"  # as-built boxes the BIM does not contain (bimfactor.sim.world)
MIN_DETECTABLE_PX = 10  # an instance with fewer visible pixels is never detected
OCCLUSION_MARGIN_M = 0.10  # a neighbour this much closer (plus 3 % of the depth) occludes
OCCLUSION_MARGIN_REL = 0.03
_APPEARANCE_STREAM, _CLASS_STREAM, _MODALITY_STREAM = 0xA99, 0xC1A, 0x30D

# Crop-to-text cosines of the `paper` preset with MiniLM against the vocabulary labels (28 then, 37 now: the test
# still finds these within 0.015), measured by `bimfactor.evaluation.graph.sim_detector_statistics` on the duplex's
# six standard trajectories and a 100-frame paper-floor furniture tour (677 true detections; the standard paper-floor
# trajectories come within 6 m of only 2 objects). d' = (0.116 − 0.039) / 0.0245 ≈ 3.2 (2.8 on the tour, 3.4 on the
# duplex). Over detections the detector labelled right: a confused crop is drawn as the class it was taken for.
MEASURED_PAPER: dict[str, float] = {
    "matched_mean": 0.116,
    "matched_std": 0.024,
    "unmatched_mean": 0.039,
    "unmatched_std": 0.025,
    "dprime": 3.2,
}


def load_sim_errors(cfg: PerceptionConfig, preset: str | None = None) -> SimPerceptionErrors:
    """The error preset `preset` (default `cfg.sim_preset`) from `cfg.sim_presets_file` in bimfactor/configs/."""
    name = preset if preset is not None else cfg.sim_preset
    path = Path(cfg.sim_presets_file)
    path = path if path.is_absolute() else config_file(cfg.sim_presets_file)
    try:
        table = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the sim perception presets ({exc.__class__.__name__})") from exc
    if not isinstance(table, dict) or name not in table:
        names = ", ".join(table) if isinstance(table, dict) else "none"
        raise ConfigError(f"unknown sim perception preset '{name}' in {path}; valid presets: {names}")
    try:
        return SimPerceptionErrors.model_validate(table[name])
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ConfigError(f"{path}: preset '{name}', key '{where}': {err['msg']}") from None


def _logistic(x: np.ndarray | float) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, float)))


def detection_quality(
    depth_m: np.ndarray, visible_fraction: np.ndarray, area_px: np.ndarray, errors: SimPerceptionErrors
) -> np.ndarray:
    """q ∈ (0, 1) per instance: falls with distance, occlusion and small image area; arrays of shape (N,)."""
    by_range = _logistic((errors.range_half_m - np.asarray(depth_m)) / errors.range_width_m)
    by_visibility = _logistic((np.asarray(visible_fraction) - errors.visible_half) / errors.visible_width)
    log_area = np.log(np.maximum(np.asarray(area_px, float), 1.0))
    by_area = _logistic((log_area - np.log(errors.area_half_px)) / errors.area_width_log)
    return by_range * by_visibility * by_area


def visible_fractions(instance_ids: np.ndarray, depth_m: np.ndarray, n_instances: int) -> np.ndarray:
    """(n_instances,) estimated visible share of each instance, from the (H, W) instance buffer and depth.

    An instance's boundary pixel is occluded when its 4-neighbour is outside the image or a different surface
    closer by more than 0.1 m + 3 % of the depth; visible share = 1 − occluded / boundary pixels (1 when absent).
    """
    height, width = instance_ids.shape
    ids = np.full((height + 2, width + 2), -2, np.int32)  # -2: outside the image
    ids[1:-1, 1:-1] = instance_ids
    depth = np.full((height + 2, width + 2), np.nan, np.float32)
    depth[1:-1, 1:-1] = depth_m
    centre_ids, centre_depth = ids[1:-1, 1:-1], depth[1:-1, 1:-1]
    margin = OCCLUSION_MARGIN_M + OCCLUSION_MARGIN_REL * centre_depth
    boundary = np.zeros((height, width), bool)
    occluded = np.zeros((height, width), bool)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        n_ids = ids[1 + dy : height + 1 + dy, 1 + dx : width + 1 + dx]
        n_depth = depth[1 + dy : height + 1 + dy, 1 + dx : width + 1 + dx]
        edge = n_ids != centre_ids
        boundary |= edge
        with np.errstate(invalid="ignore"):
            occluded |= edge & ((n_ids == -2) | (n_depth < centre_depth - margin))
    mine = centre_ids >= 0
    n_boundary = np.bincount(centre_ids[mine & boundary], minlength=n_instances)[:n_instances]
    n_occluded = np.bincount(centre_ids[mine & occluded], minlength=n_instances)[:n_instances]
    return 1.0 - n_occluded / np.maximum(n_boundary, 1)


class LabelConfusion:
    """Draws a wrong label for a true one from a vocabulary, p ∝ exp(cos(t_true, t_label) / τ)."""

    def __init__(self, vocabulary: Sequence[str], text_embedder: TextEmbedder, temperature: float) -> None:
        self.vocabulary = list(dict.fromkeys(vocabulary))
        if len(self.vocabulary) < 2:
            raise ConfigError("label confusion needs a vocabulary of at least two labels")
        self.temperature = temperature
        self._text = text_embedder
        self._vocab_vectors = text_embedder.encode(self.vocabulary)
        self._rows: dict[str, np.ndarray] = {}

    def probabilities(self, true_label: str) -> np.ndarray:
        """(V,) probability of each vocabulary label replacing `true_label` (0 for the true label itself)."""
        if true_label not in self._rows:
            sims = self._vocab_vectors @ self._text.encode([true_label])[0]
            logits = sims.astype(np.float64) / self.temperature
            logits[[label == true_label for label in self.vocabulary]] = -np.inf
            weights = np.exp(logits - logits[np.isfinite(logits)].max())
            self._rows[true_label] = weights / weights.sum()
        return self._rows[true_label]

    def sample(self, true_label: str, rng: np.random.Generator) -> str:
        """A label other than `true_label`, drawn towards semantically similar ones."""
        return self.vocabulary[int(rng.choice(len(self.vocabulary), p=self.probabilities(true_label)))]


def _instance_tables(meta: SequenceMeta) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Per instance id: (I,) object id, labels, (I,) bool 'an object a detector reports' (BIM object or clutter)."""
    if not meta.instances:
        raise InputError(f"sequence {meta.name}: the sim perception backend needs the simulator's instance table")
    n = max(int(rec["id"]) for rec in meta.instances) + 1
    object_ids = np.full(n, -1, np.int64)
    labels = [""] * n
    for rec in meta.instances:
        object_ids[int(rec["id"])] = int(rec["object_id"])
        labels[int(rec["id"])] = str(rec["label"])
    is_object = (object_ids >= 0) | np.asarray([label == CLUTTER_LABEL for label in labels])
    return object_ids, labels, is_object


def _require_buffer(frame: Frame) -> np.ndarray:
    if frame.instance_ids is None:
        raise InputError(f"frame {frame.index} has no instance buffer: the sim perception backend needs one")
    return frame.instance_ids


def reported_labels(
    labels: Sequence[str], emitted: Sequence[str], text_embedder: TextEmbedder, min_similarity: float
) -> dict[str, str]:
    """What a closed-set detector that reports only the `emitted` labels calls an object of each of `labels`: the
    label itself when emitted, else the emitted label nearest by the text encoder where their cosine reaches
    `min_similarity` (an armchair is a chair to YOLOX); a label left out of the dict is never detected (a door, a
    radiator, a cabinet)."""
    emitted = list(dict.fromkeys(emitted))
    others = [label for label in dict.fromkeys(labels) if label not in emitted]
    out = {label: label for label in emitted}
    if others and emitted:
        sims = text_embedder.encode(others) @ text_embedder.encode(emitted).T
        for row, label in enumerate(others):
            best = int(np.argmax(sims[row]))
            if sims[row, best] >= min_similarity:
                out[label] = emitted[best]
    return out


class SimDetector:
    """Detector driven by the instance buffer, with range / occlusion / area misses, confusions, false positives.

    `reported` (a closed-set detector's eyes, `reported_labels`) maps the label of each object class it can see to
    the label it reports; objects of other classes are never detected. None: every object, under its own label."""

    def __init__(
        self,
        meta: SequenceMeta,
        errors: SimPerceptionErrors,
        confusion: LabelConfusion,
        box_threshold: float,
        text_threshold: float,
        rng: np.random.Generator,
        reported: dict[str, str] | None = None,
    ) -> None:
        self.errors = errors
        self.confusion = confusion
        self.box_threshold = box_threshold
        self.text_threshold = text_threshold
        self.rng = rng
        self.reported = reported
        self._object_ids, self._labels, self._is_object = _instance_tables(meta)
        if reported is not None:
            self._is_object &= np.asarray([label in reported for label in self._labels])

    def detect(self, frame: Frame) -> list[Detection]:
        """Thresholded detections of the objects in view plus false positives; see the module docstring."""
        ids = _require_buffer(frame)
        n = len(self._labels)
        counts = np.bincount(ids[ids >= 0].ravel(), minlength=n)[:n]
        present = np.flatnonzero((counts >= MIN_DETECTABLE_PX) & self._is_object)
        detections: list[Detection] = []
        if len(present):
            visible = visible_fractions(ids, frame.depth_m, n)
            for iid in present:
                detection = self._detect_instance(frame, ids, int(iid), float(visible[iid]), int(counts[iid]))
                if detection is not None:
                    detections.append(detection)
        detections.extend(self._false_positives(frame, ids))
        return detections

    def _detect_instance(
        self, frame: Frame, ids: np.ndarray, iid: int, visible: float, area_px: int
    ) -> Detection | None:
        e, rng = self.errors, self.rng
        rows, cols = np.nonzero(ids == iid)
        depth = frame.depth_m[rows, cols]
        depth = depth[np.isfinite(depth)]
        # The same draws for every instance in view, whatever is decided (only a confusion draws more).
        u_miss, z_box, z_text, u_conf = rng.random(), rng.standard_normal(), rng.standard_normal(), rng.random()
        jitter = rng.standard_normal(4)
        if len(depth) == 0:
            return None
        q = float(detection_quality(np.median(depth), visible, area_px, e))
        box_score = float(np.clip(e.box_score_max * q + e.box_score_std * z_box, 0.0, 1.0))
        text_score = float(np.clip(e.text_score_mean + e.text_score_std * z_text, 0.0, 1.0))
        label = self._labels[iid] if self.reported is None else self.reported[self._labels[iid]]
        if u_conf < e.confusion_rate or label not in self.confusion.vocabulary:
            label = self.confusion.sample(label, rng)  # clutter has no vocabulary label: always a guess
        box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
        side = np.array([box[2] - box[0], box[3] - box[1]] * 2)
        box = self._clip_box(box + e.box_jitter * side * jitter, frame)
        detection = Detection(box, label, box_score, text_score, gt_instance_id=iid)
        if u_miss < e.miss_prob or not passes_thresholds(detection, self.box_threshold, self.text_threshold):
            return None
        return detection

    def _false_positives(self, frame: Frame, ids: np.ndarray) -> list[Detection]:
        e, rng = self.errors, self.rng
        count = int(rng.poisson(e.false_positive_candidates))
        if count == 0:
            return []
        structure = np.zeros(len(self._labels) + 1, bool)
        structure[:-1] = ~self._is_object | (np.asarray(self._labels) == CLUTTER_LABEL)
        candidates = np.flatnonzero((ids >= 0).ravel() & structure[ids.ravel()] & np.isfinite(frame.depth_m).ravel())
        out = []
        lo, hi = np.log(e.false_positive_side_px[0]), np.log(e.false_positive_side_px[1])
        for _ in range(count):
            pixel, sides = rng.random(), np.exp(rng.uniform(lo, hi, 2))
            box_score, z_text = rng.uniform(0.0, e.false_positive_score_max), rng.standard_normal()
            if len(candidates) == 0:
                continue
            flat = int(candidates[min(int(pixel * len(candidates)), len(candidates) - 1)])
            v, u = divmod(flat, ids.shape[1])
            box = self._clip_box(
                np.array([u - sides[0] / 2, v - sides[1] / 2, u + sides[0] / 2, v + sides[1] / 2]), frame
            )
            label = self.confusion.sample(self._labels[ids[v, u]], rng)
            text_score = float(np.clip(e.text_score_mean + e.text_score_std * z_text, 0.0, 1.0))
            detection = Detection(box, label, float(box_score), text_score, gt_instance_id=-1)
            if passes_thresholds(detection, self.box_threshold, self.text_threshold):
                out.append(detection)
        return out

    @staticmethod
    def _clip_box(box: np.ndarray, frame: Frame) -> np.ndarray:
        height, width = frame.depth_m.shape
        x0, x1 = np.clip(sorted(box[[0, 2]]), 0.0, width)
        y0, y1 = np.clip(sorted(box[[1, 3]]), 0.0, height)
        return np.array([x0, y0, max(x1, x0 + 1.0), max(y1, y0 + 1.0)])


class SimSegmenter:
    """Box-prompted masks from the instance buffer, grown or shrunk at the edge and leaking into the background."""

    def __init__(self, errors: SimPerceptionErrors, rng: np.random.Generator) -> None:
        self.errors = errors
        self.rng = rng

    def segment(self, frame: Frame, detections: Sequence[Detection]) -> np.ndarray:
        """(N, H, W) bool masks; a false positive segments the surface under its box centre."""
        ids = _require_buffer(frame)
        height, width = ids.shape
        masks = np.zeros((len(detections), height, width), bool)
        for k, detection in enumerate(detections):
            x0, y0, x1, y1 = box_to_pixels(detection.box_xyxy, width, height)
            if x1 <= x0 or y1 <= y0:
                continue
            crop = ids[y0:y1, x0:x1]
            target = detection.gt_instance_id
            if target is None or target < 0:
                target = int(crop[(y1 - y0) // 2, (x1 - x0) // 2])
            mask = crop == target if target >= 0 else np.isfinite(frame.depth_m[y0:y1, x0:x1])
            masks[k, y0:y1, x0:x1] = self._perturb(mask)
        return masks

    def _perturb(self, mask: np.ndarray) -> np.ndarray:
        e, rng = self.errors, self.rng
        u_op, radius = rng.random(), int(rng.integers(1, e.mask_radius_px + 1)) if e.mask_radius_px > 0 else 0
        if radius > 0 and u_op < e.mask_dilate_prob + e.mask_erode_prob:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
            op = cv2.dilate if u_op < e.mask_dilate_prob else cv2.erode
            mask = op(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
        outside = np.flatnonzero(~mask.ravel())
        n_bleed = min(round(e.mask_bleed * int(mask.sum())), len(outside))
        if n_bleed > 0:
            mask = mask.copy()
            mask.ravel()[rng.choice(outside, n_bleed, replace=False)] = True
        return mask


@dataclass(frozen=True)
class EmbeddingNoise:
    """Coefficients of the crop-embedding model A = t_c + g·m + b·v_c + σ_i·u_i, e = A + σ_v·u_view (see module)."""

    g: float
    b: float
    sigma_instance: float
    sigma_view: float

    @classmethod
    def solve(
        cls, errors: SimPerceptionErrors, label_cos_mean: float, label_cos_std: float, dim: int
    ) -> EmbeddingNoise:
        """Coefficients that give the preset's d' and crop-to-crop cosines in a text space whose distinct labels
        have cosines `label_cos_mean` ± `label_cos_std`, in `dim` dimensions."""
        mu, s, d = label_cos_mean, label_cos_std, errors.embedding_dprime
        sigma_n2 = dim * ((1.0 - mu) ** 2 / d**2 - s**2 / 2.0)
        if sigma_n2 <= 0:
            best = (1.0 - mu) / (s / np.sqrt(2.0))
            raise ConfigError(f"embedding_dprime {d} is out of reach in this text space (at most {best:.2f})")
        same_inst, same_cls, other = (
            errors.embedding_same_instance,
            errors.embedding_same_class,
            errors.embedding_other_class,
        )
        if not other <= same_cls <= same_inst:
            raise ConfigError("sim embedding cosines must satisfy other_class ≤ same_class ≤ same_instance")
        n2 = sigma_n2 / (1.0 - same_cls)
        g2 = other * n2 - mu
        b2 = (same_cls - other) * n2 - 1.0 + mu
        if g2 < 0 or b2 < 0:
            raise ConfigError("sim embedding cosines out of reach: raise same_class/other_class or lower d'")
        sigma_i2 = (same_inst - same_cls) * n2
        return cls(
            float(np.sqrt(g2)), float(np.sqrt(b2)), float(np.sqrt(sigma_i2)), float(np.sqrt(sigma_n2 - sigma_i2))
        )


def label_cosine_statistics(vectors: np.ndarray) -> tuple[float, float]:
    """Mean and std of the cosines between distinct rows of (V, D) unit vectors."""
    sims = vectors @ vectors.T
    off = sims[~np.eye(len(vectors), dtype=bool)]
    return float(off.mean()), float(off.std())


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


class SimEmbedder:
    """Crop embeddings in the text embedder's space with CLIP-like statistics (module docstring)."""

    def __init__(
        self,
        meta: SequenceMeta,
        text_embedder: TextEmbedder,
        vocabulary: Sequence[str],
        errors: SimPerceptionErrors,
        seed: int,
        rng: np.random.Generator,
    ) -> None:
        self.name = f"sim-visual:{text_embedder.name}"
        self.dim = int(text_embedder.dim)
        self.rng = rng
        self._seed = seed
        _, self._labels, _ = _instance_tables(meta)
        vocabulary = list(dict.fromkeys(vocabulary))
        mean, std = label_cosine_statistics(text_embedder.encode(vocabulary))
        self.noise = EmbeddingNoise.solve(errors, mean, std, self.dim)
        known = list(dict.fromkeys([*vocabulary, *self._labels]))
        self._text = dict(zip(known, text_embedder.encode(known).astype(np.float64), strict=True))
        # Directions orthogonal to every label text: they shape crop-to-crop cosines only.
        basis, singular, _ = np.linalg.svd(np.stack(list(self._text.values())).T, full_matrices=False)
        self._text_basis = basis[:, singular > 1e-6 * singular[0]]
        self._modality = self._orthogonal(np.random.default_rng([seed, _MODALITY_STREAM]))
        self._class_dirs: dict[str, np.ndarray] = {}
        self._appearance: dict[tuple[int, str], np.ndarray] = {}  # by (instance, the class it is seen as)
        log.debug("sim embedder: μ=%.3f σ=%.3f over %d labels → %s", mean, std, len(vocabulary), self.noise)

    def _orthogonal(self, rng: np.random.Generator) -> np.ndarray:
        v = rng.standard_normal(self.dim)
        return _unit(v - self._text_basis @ (self._text_basis.T @ v))

    def appearance(self, instance_id: int, label: str | None = None) -> np.ndarray:
        """(D,) the persistent, unnormalised appearance vector A of an instance, as the class `label` (default: its
        own). A confused detection's crop looks like what the detector took it for: its class terms are the
        confused label's, its instance term the object's own."""
        label = label or self._labels[instance_id]
        key = (instance_id, label)
        if key not in self._appearance:
            if label not in self._class_dirs:
                checksum = zlib.crc32(label.encode())
                self._class_dirs[label] = self._orthogonal(np.random.default_rng([self._seed, _CLASS_STREAM, checksum]))
            u = _unit(np.random.default_rng([self._seed, _APPEARANCE_STREAM, instance_id]).standard_normal(self.dim))
            n = self.noise
            self._appearance[key] = (
                self._text[label] + n.g * self._modality + n.b * self._class_dirs[label] + n.sigma_instance * u
            )
        return self._appearance[key]

    def embed(self, frame: Frame, detections: Sequence[Detection], masks: np.ndarray) -> np.ndarray:
        """(N, D) float32 unit rows: the instances under each mask mixed by pixel share, plus view noise."""
        ids = _require_buffer(frame)
        out = np.zeros((len(detections), self.dim), np.float32)
        for k, detection in enumerate(detections):
            under = ids[masks[k]] if masks[k].any() else ids[self._box_slice(detection, ids.shape)].ravel()
            under = under[under >= 0]
            view = _unit(self.rng.standard_normal(self.dim)) * self.noise.sigma_view
            if len(under):
                iids, counts = np.unique(under, return_counts=True)
                target = detection.gt_instance_id
                mixed = (
                    sum(
                        c * self.appearance(int(i), detection.label if i == target else None)
                        for i, c in zip(iids, counts, strict=True)
                    )
                    / counts.sum()
                )
            else:
                mixed = self.noise.g * self._modality
            out[k] = _unit(mixed + view)
        return out

    @staticmethod
    def _box_slice(detection: Detection, shape: tuple[int, int]) -> tuple[slice, slice]:
        x0, y0, x1, y1 = box_to_pixels(detection.box_xyxy, shape[1], shape[0])
        return slice(y0, y1), slice(x0, x1)
