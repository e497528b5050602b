"""Mode extraction (yaw seam, storeys, separate clusters) and the tracker's spawn / continue / merge / prune."""

import numpy as np
import pytest

from bimfactor.config import load_config
from bimfactor.localization.modes import Mode, ModeTracker, extract_modes
from bimfactor.types import wrap_angle

CFG = load_config().backend
POS_STD_M = 0.1
YAW_STD_RAD = np.deg2rad(2.0)


def _blob(rng: np.random.Generator, centre: tuple[float, float, float], n: int) -> np.ndarray:
    poses = np.asarray(centre) + rng.standard_normal((n, 3)) * [POS_STD_M, POS_STD_M, YAW_STD_RAD]
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def test_particles_across_the_yaw_seam_form_one_mode_at_180_degrees():
    rng = np.random.default_rng(0)
    particles = _blob(rng, (2.0, 3.0, np.pi), 400)
    assert (particles[:, 2] > 0).any() and (particles[:, 2] < 0).any()  # both sides of ±π
    modes = extract_modes(particles, np.full(400, 1 / 400), CFG)
    assert len(modes) == 1
    mode = modes[0]
    assert mode.weight == pytest.approx(1.0)
    assert abs(wrap_angle(mode.mean[2] - np.pi)) < np.deg2rad(0.5)
    np.testing.assert_allclose(mode.mean[:2], [2.0, 3.0], atol=0.02)
    # The yaw variance is the blob's, not the ~π² of a naive mean over ±179°.
    assert np.sqrt(mode.covariance[2, 2]) == pytest.approx(YAW_STD_RAD, rel=0.15)


def test_two_separated_clusters_are_two_modes_weighted_by_their_share():
    rng = np.random.default_rng(1)
    particles = np.concatenate([_blob(rng, (0.0, 0.0, 0.5), 300), _blob(rng, (5.0, 1.0, -2.0), 100)])
    modes = extract_modes(particles, np.full(400, 1 / 400), CFG)
    assert len(modes) == 2
    np.testing.assert_allclose(modes[0].mean, [0.0, 0.0, 0.5], atol=0.02)
    np.testing.assert_allclose(modes[1].mean, [5.0, 1.0, -2.0], atol=0.03)
    assert [m.weight for m in modes] == pytest.approx([0.75, 0.25])
    assert [m.n_particles for m in modes] == [300, 100]


def test_same_place_opposite_heading_and_other_storey_are_separate_modes():
    rng = np.random.default_rng(2)
    particles = np.concatenate(
        [_blob(rng, (1.0, 1.0, 0.0), 200), _blob(rng, (1.0, 1.0, np.pi), 100), _blob(rng, (1.0, 1.0, 0.0), 100)]
    )
    storeys = np.repeat([0, 0, 1], [200, 100, 100])
    modes = extract_modes(particles, np.full(400, 1 / 400), CFG, storeys)
    assert len(modes) == 3
    assert sorted((m.storey, round(float(abs(m.mean[2])), 1)) for m in modes) == [(0, 0.0), (0, 3.1), (1, 0.0)]


def test_only_the_strongest_k_modes_are_kept():
    rng = np.random.default_rng(3)
    centres = [(4.0 * k, 0.0, 0.0) for k in range(8)]
    counts = [80, 70, 60, 50, 40, 30, 20, 10]
    particles = np.concatenate([_blob(rng, c, n) for c, n in zip(centres, counts, strict=True)])
    modes = extract_modes(particles, np.full(len(particles), 1 / len(particles)), CFG)
    assert len(modes) == CFG.max_modes
    assert [m.n_particles for m in modes] == counts[: CFG.max_modes]


def _cluster(x: float, y: float, yaw: float, weight: float) -> Mode:
    return Mode(np.array([x, y, yaw]), np.diag([0.01, 0.01, 0.001]), weight)


def test_tracker_keeps_ids_through_motion_and_spawns_new_clusters():
    tracker = ModeTracker(CFG)
    events = tracker.update([_cluster(0, 0, 0, 0.7), _cluster(10, 0, np.pi, 0.3)])
    assert events.spawned == [0, 1]
    # Both move 0.5 m forward in their own heading; a new strong cluster appears elsewhere.
    step = np.array([0.5, 0.0, 0.0])
    events = tracker.update([_cluster(0.5, 0, 0, 0.5), _cluster(9.5, 0, np.pi, 0.3), _cluster(0, 8, 0, 0.2)], step)
    assert events.spawned == [2]
    np.testing.assert_allclose(tracker.get(0).mean, [0.5, 0, 0])
    np.testing.assert_allclose(tracker.get(1).mean[:2], [9.5, 0])
    # A light cluster does not spawn a mode.
    events = tracker.update([_cluster(1.0, 0, 0, 0.97), _cluster(-20, 0, 0, CFG.spawn_weight / 2)], step)
    assert events.spawned == []


def test_tracker_merges_modes_that_converge_to_the_same_pose():
    tracker = ModeTracker(CFG)
    tracker.update([_cluster(0, 0, 0, 0.6), _cluster(0.8, 0, 0.1, 0.4)])
    assert [m.id for m in tracker.modes] == [0, 1]
    events = tracker.update([_cluster(0.0, 0, 0, 0.6), _cluster(0.6, 0, 0.05, 0.4)])
    assert events.merged == []
    events = tracker.update([_cluster(0.0, 0, 0, 0.6), _cluster(0.1, 0.05, 0.02, 0.4)])
    assert events.merged == [(0, 1)]
    assert [m.id for m in tracker.modes] == [0]
    assert tracker.get(0).weight == pytest.approx(1.0)


def test_tracker_prunes_a_weak_mode_but_never_the_best():
    tracker = ModeTracker(CFG)
    tracker.update([_cluster(0, 0, 0, 0.6), _cluster(5, 0, 0, 0.4)])
    tracker.set_probabilities({0: 0.995, 1: 0.005})
    assert tracker.prune() == [1]
    assert [m.id for m in tracker.modes] == [0]
    assert tracker.get(0).probability == pytest.approx(1.0)
    tracker.set_probabilities({0: 0.001})
    assert tracker.prune() == []


def test_a_mode_no_cluster_continues_decays():
    tracker = ModeTracker(CFG)
    tracker.update([_cluster(0, 0, 0, 0.5), _cluster(5, 0, 0, 0.5)])
    tracker.update([_cluster(0, 0, 0, 0.5)])
    assert tracker.get(1).missed == 1
    assert tracker.get(1).weight == pytest.approx(0.5 * CFG.missed_decay)
