"""The sim backend: visibility estimate, label confusion, embedding model, and the presets' measured rates."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import Config, SimPerceptionErrors
from bimfactor.errors import ConfigError, InputError
from bimfactor.evaluation.graph import sim_detector_statistics
from bimfactor.perception.base import Detector, Embedder, Segmenter
from bimfactor.perception.pipeline import household_vocabulary, make_perception
from bimfactor.perception.sim import (
    MEASURED_PAPER,
    EmbeddingNoise,
    LabelConfusion,
    label_cosine_statistics,
    load_sim_errors,
    visible_fractions,
)
from bimfactor.sim.simulate import SimResult
from bimfactor.types import Frame


def test_visible_fraction_counts_closer_neighbours_and_the_image_border() -> None:
    ids = np.ones((6, 6), np.int32)  # instance 1: a wall at 4 m
    depth = np.full((6, 6), 4.0, np.float32)
    ids[2:4, 2:4], depth[2:4, 2:4] = 0, 2.0  # instance 0: an object at 2 m
    assert visible_fractions(ids, depth, 4)[[0, 3]].tolist() == [1.0, 1.0]  # 3: absent
    ids[2:4, 4], depth[2:4, 4] = 2, 1.0  # instance 2: a post at 1 m right of the object
    assert visible_fractions(ids, depth, 3)[0] == 0.5  # 2 of its 4 boundary pixels touch the post
    ids = np.ones((6, 6), np.int32)
    ids[2:4, 0:2] = 0  # now at the left image border, nothing in front
    assert visible_fractions(ids, np.full((6, 6), 3.0, np.float32), 2)[0] == 0.5


def test_confusion_prefers_semantically_close_labels(test_config: Config, text_embedder) -> None:
    confusion = LabelConfusion(household_vocabulary(test_config), text_embedder, temperature=0.1)
    p = confusion.probabilities("chair")
    vocab = confusion.vocabulary
    assert p.sum() == pytest.approx(1.0) and p[vocab.index("chair")] == 0.0
    assert p[vocab.index("armchair")] > 10 * p[vocab.index("bathtub")]
    rng = np.random.default_rng(0)
    draws = [confusion.sample("chair", rng) for _ in range(300)]
    assert "chair" not in draws and draws.count("armchair") > draws.count("bathtub")
    assert confusion.probabilities("wall").sum() == pytest.approx(1.0)  # a label outside the vocabulary


def test_embedding_coefficients_give_the_preset_statistics_in_closed_form(test_config: Config) -> None:
    errors = load_sim_errors(test_config.perception, "paper")
    mu, s, dim = 0.31, 0.104, 384
    n = EmbeddingNoise.solve(errors, mu, s, dim)
    total = 1 + n.g**2 + n.b**2 + n.sigma_instance**2 + n.sigma_view**2
    sigma_n2 = n.sigma_instance**2 + n.sigma_view**2
    assert (1 + n.g**2 + n.b**2 + n.sigma_instance**2) / total == pytest.approx(errors.embedding_same_instance)
    assert (1 + n.g**2 + n.b**2) / total == pytest.approx(errors.embedding_same_class)
    assert (mu + n.g**2) / total == pytest.approx(errors.embedding_other_class)
    assert (1 - mu) / np.sqrt(s**2 / 2 + sigma_n2 / dim) == pytest.approx(errors.embedding_dprime)
    unreachable = errors.model_copy(update={"embedding_dprime": 20.0})
    with pytest.raises(ConfigError, match="out of reach"):
        EmbeddingNoise.solve(unreachable, mu, s, dim)


def test_presets_load_and_unknown_ones_are_named(test_config: Config) -> None:
    for name in ("yolox", "clean", "paper", "harsh"):
        assert isinstance(load_sim_errors(test_config.perception, name), SimPerceptionErrors)
    assert test_config.perception.sim_preset == "yolox"  # the benchmark sees with the shipped detector's eyes
    with pytest.raises(ConfigError, match="valid presets: yolox, clean, paper, harsh"):
        load_sim_errors(test_config.perception, "perfect")
    paper = load_sim_errors(test_config.perception, "paper").model_dump()
    with pytest.raises(ValueError, match="detector yolox has no masks or crop embeddings to model: drop mask_"):
        SimPerceptionErrors.model_validate({**paper, "detector": "yolox"})
    with pytest.raises(ValueError, match="open_vocabulary needs its masks' and crop embeddings' keys: mask_bleed"):
        SimPerceptionErrors.model_validate({k: v for k, v in paper.items() if k != "mask_bleed"})


def test_the_shipped_detectors_eyes_see_only_its_classes_as_boxes_embedded_by_label(
    test_config: Config, text_embedder, meeting_orbit: SimResult
) -> None:
    """The `yolox` preset: every detection carries a label the shipped detector can report under the vocabulary (an
    armchair is a chair, a door or a cabinet is never seen), its mask comes from the depth in its box, and its
    embedding is its label's text embedding (no crop embedding of the true class)."""
    from bimfactor.perception.boxes import BoxSegmenter, LabelEmbedder
    from bimfactor.perception.pipeline import vocabulary_of
    from bimfactor.perception.sim import reported_labels
    from bimfactor.perception.yolox import coco_label_table

    p = test_config.perception
    emitted = set(coco_label_table(vocabulary_of(test_config), text_embedder, p.sim_threshold).vocabulary_labels)
    perception = make_perception(test_config, meeting_orbit.meta, text_embedder, sim_preset="yolox")
    assert isinstance(perception.segmenter, BoxSegmenter) and isinstance(perception.embedder, LabelEmbedder)
    labels, true_labels = [], []
    truth = {int(r["id"]): str(r["label"]) for r in meeting_orbit.meta.instances}
    for frame in meeting_orbit.frames:
        detections, masks, embeddings = perception.perceive(frame)
        for d, mask in zip(detections, masks, strict=True):  # segmented by depth inside the box alone
            outside = mask.copy()
            outside[
                int(d.box_xyxy[1]) : int(np.ceil(d.box_xyxy[3])), int(d.box_xyxy[0]) : int(np.ceil(d.box_xyxy[2]))
            ] = False
            assert not outside.any()
        labels += [d.label for d in detections]
        true_labels += [
            truth[d.gt_instance_id] for d in detections if d.gt_instance_id is not None and d.gt_instance_id >= 0
        ]
        np.testing.assert_allclose(embeddings, text_embedder.encode([d.label for d in detections]), atol=1e-6)
    assert labels and set(labels) <= emitted
    assert not {"door", "window", "cabinet", "radiator", "stairs"} & set(true_labels)
    seen = reported_labels(["armchair", "door", "chair"], sorted(emitted), text_embedder, p.sim_threshold)
    assert seen == {**{label: label for label in emitted}, "armchair": "chair"}


def test_sim_backends_satisfy_the_protocols_and_are_reproducible(
    test_config: Config, text_embedder, meeting_orbit: SimResult
) -> None:
    runs = []
    for _ in range(2):
        p = make_perception(test_config, meeting_orbit.meta, text_embedder, seed=3)
        assert isinstance(p.detector, Detector) and isinstance(p.segmenter, Segmenter)
        assert isinstance(p.embedder, Embedder) and p.embedder.dim == text_embedder.dim
        runs.append([p.perceive(frame) for frame in meeting_orbit.frames[:5]])
    for (d1, m1, e1), (d2, m2, e2) in zip(*runs, strict=True):
        assert [(d.label, d.gt_instance_id, d.box_score) for d in d1] == [
            (d.label, d.gt_instance_id, d.box_score) for d in d2
        ]
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_array_equal(e1, e2)
        np.testing.assert_allclose(np.linalg.norm(e1, axis=1), 1.0, rtol=1e-5)
        assert m1.shape == (len(d1), *meeting_orbit.frames[0].depth_m.shape)


def test_sim_backend_needs_the_instance_buffer(test_config: Config, text_embedder, meeting_orbit: SimResult) -> None:
    frame = meeting_orbit.frames[0]
    bare = Frame(0, 0.0, frame.rgb, frame.depth_m, frame.odom_pose)
    with pytest.raises(InputError, match="instance buffer"):
        make_perception(test_config, meeting_orbit.meta, text_embedder).detector.detect(bare)


def _pooled(sim: SimResult, cfg: Config, text_embedder, preset: str, seeds: range) -> dict[str, float]:
    """Rates over the same frames seen with several seeds (independent detector draws)."""
    runs = [sim_detector_statistics([sim], cfg, text_embedder, preset, seed) for seed in seeds]
    in_view = sum(r["objects_in_view_6m"] for r in runs)
    tp = sum(r["true_positives"] for r in runs)
    return {
        "recall_6m": sum(r["recall_6m"] * r["objects_in_view_6m"] for r in runs) / in_view,
        "confusion_rate": sum(r["confusion_rate"] * r["true_positives"] for r in runs) / tp,
        "false_positives_per_frame": float(np.mean([r["false_positives_per_frame"] for r in runs])),
        "objects_in_view": in_view,
        "runs": runs,
    }


def test_paper_preset_rates_over_many_frames(test_config: Config, text_embedder, furniture_tour: SimResult) -> None:
    """Recall ≈ 0.7 within 6 m, 20 % confused labels, 0.3 false positives per frame (180 frame draws)."""
    rates = _pooled(furniture_tour, test_config, text_embedder, "paper", range(3))
    assert rates["objects_in_view"] > 400
    assert rates["recall_6m"] == pytest.approx(0.7, abs=0.1)
    assert rates["confusion_rate"] == pytest.approx(0.2, abs=0.07)
    assert rates["false_positives_per_frame"] == pytest.approx(0.3, abs=0.1)


def test_clean_preset_sees_everything_in_range(test_config: Config, text_embedder, furniture_tour: SimResult) -> None:
    stats = sim_detector_statistics([furniture_tour], test_config, text_embedder, "clean")
    assert stats["recall_6m"] >= 0.98
    assert stats["confusion_rate"] == 0.0 and stats["false_positives_per_frame"] == 0.0


def test_harsh_preset_is_worse_than_paper(test_config: Config, text_embedder, furniture_tour: SimResult) -> None:
    harsh = sim_detector_statistics([furniture_tour], test_config, text_embedder, "harsh")
    paper = sim_detector_statistics([furniture_tour], test_config, text_embedder, "paper")
    assert harsh["recall_6m"] < paper["recall_6m"]
    assert harsh["false_positives_per_frame"] > paper["false_positives_per_frame"]
    assert harsh["vs_vocabulary"]["dprime"] < paper["vs_vocabulary"]["dprime"]


def test_matched_and_unmatched_similarities_are_as_documented(
    test_config: Config, text_embedder, furniture_tour: SimResult
) -> None:
    """Crop-to-text cosines against the vocabulary labels: d' ≈ 3 as CLIP ViT-L/14, in MiniLM's scale; a confused
    crop is nearer its confused label than its own."""
    stats = sim_detector_statistics([furniture_tour], test_config, text_embedder, "paper")
    sims = stats["vs_vocabulary"]
    assert sims["dprime"] == pytest.approx(3.0, abs=0.5)
    for key in ("matched_mean", "matched_std", "unmatched_mean", "unmatched_std"):
        assert sims[key] == pytest.approx(MEASURED_PAPER[key], abs=0.015), key
    crops = stats["crop_to_crop"]
    assert crops["same_instance"] == pytest.approx(0.90, abs=0.02)
    assert crops["same_class"] == pytest.approx(0.78, abs=0.03)
    assert crops["other_class"] == pytest.approx(0.55, abs=0.05)
    mean, std = label_cosine_statistics(text_embedder.encode(household_vocabulary(test_config)))
    assert (mean, std) == pytest.approx((0.300, 0.098), abs=0.005)
    assert stats["confused_crop_to_true_text"] < sims["matched_mean"] - 2 * sims["matched_std"]
