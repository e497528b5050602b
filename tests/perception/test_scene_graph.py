"""The online scene graph on hand-built instances: association thresholds, fusion, pruning, edges, observations."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.config import PerceptionConfig
from bimfactor.perception.base import Detection
from bimfactor.perception.lifting import pack_voxels
from bimfactor.perception.scene_graph import CameraView, Instance3D, OnlineSceneGraph, aabb_iou, aabb_overlap
from bimfactor.sim.sensors import R_BASE_CAMERA_LEVEL
from bimfactor.types import CameraIntrinsics, Frame
from tests.perception.conftest import perception_config

K = CameraIntrinsics.from_hfov(320, 240, 90.0)
MOUNT = np.eye(4)
MOUNT[:3, :3] = R_BASE_CAMERA_LEVEL
MOUNT[:3, 3] = [0.0, 0.0, 0.5]
DIM = 8


@pytest.fixture(autouse=True)
def exact(fixed_value) -> None:
    """Half a voxel of padding: a box of voxel centres grows to the voxels' outer faces, so IoUs are voxel ratios;
    no periodic pruning unless a test asks."""
    fixed_value("perception.iou_padding_m", 0.025)
    fixed_value("perception.prune_every", 1000)


def keys_box(x0: int, x1: int, y0: int = 0, y1: int = 1, z0: int = 0, z1: int = 1) -> np.ndarray:
    """Sorted keys of the solid voxel box [x0, x1) × [y0, y1) × [z0, z1)."""
    grid = np.stack(np.meshgrid(np.arange(x0, x1), np.arange(y0, y1), np.arange(z0, z1), indexing="ij"), -1)
    return np.sort(pack_voxels(grid.reshape(-1, 3)))


def unit(*values: float) -> np.ndarray:
    v = np.zeros(DIM, np.float32)
    v[: len(values)] = values
    return v / np.linalg.norm(v)


def with_cosine(c: float) -> np.ndarray:
    """A unit vector whose cosine with unit(1) is c."""
    return unit(c, np.sqrt(1 - c * c))


def graph(config_overrides: list[str], *overrides: str) -> OnlineSceneGraph:
    return OnlineSceneGraph(perception_config(config_overrides, *overrides), K, MOUNT)


def test_two_sightings_of_one_box_merge_and_the_embedding_is_the_running_mean(config_overrides) -> None:
    g = graph(config_overrides)
    f1, f2, f3 = unit(1.0, 0.1, 0.2), unit(1.0, -0.1, 0.1), unit(1.0, 0.05, -0.1)
    first = g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), f1, "chair", 0.4)], frame_index=0)
    assert g.nodes[0].score == 0.4
    second = g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), f2, "armchair", 0.7)], frame_index=1)
    assert first.new_node_ids == [0] and second.merged_node_ids == [0] and len(g.nodes) == 1
    node = g.nodes[0]
    np.testing.assert_array_equal(node.embedding_mean, (f1.astype(np.float64) + f2) / 2)
    g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), f3, "chair", 0.5)], frame_index=2)
    assert node.score == 0.7  # the node's confidence: its best detection's box score
    mean2 = (f1.astype(np.float64) + f2) / 2
    np.testing.assert_array_equal(node.embedding_mean, (2 * mean2 + f3) / 3)
    assert node.n_observations == 3 and node.label == "chair" and (node.first_frame, node.last_frame) == (0, 2)
    np.testing.assert_allclose(np.linalg.norm(node.embedding), 1.0, rtol=1e-6)


def test_the_box_ratios_are_exact() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    b = np.array([[0.5, 0.0, 0.0], [1.5, 1.0, 1.0]])
    assert aabb_iou(a, b) == pytest.approx(1 / 3)
    assert aabb_overlap(a, b) == pytest.approx(0.5)
    assert aabb_iou(a, a + 2.0) == 0.0


@pytest.mark.parametrize(("inner_voxels", "merges"), [(69, False), (71, True)])
def test_iou_below_the_threshold_starts_a_new_node(config_overrides, inner_voxels: int, merges: bool) -> None:
    """IoU 0.69 (69 of 100 voxels, nested) → new node; 0.71 → fused. Similarity is 1 in both."""
    g = graph(config_overrides, "overlap_measure=iou")
    g.integrate([Instance3D(keys_box(0, 100), unit(1.0), "table")], 0)
    stats = g.integrate([Instance3D(keys_box(0, inner_voxels), unit(1.0), "table")], 1)
    assert (stats.n_merged, stats.n_new, len(g.nodes)) == ((1, 0, 1) if merges else (0, 1, 2))


@pytest.mark.parametrize(("shift", "merges"), [(31, False), (29, True)])
def test_overlap_below_the_threshold_starts_a_new_node(config_overrides, shift: int, merges: bool) -> None:
    """Overlap coefficient 69/100 → new node; 71/100 → fused."""
    g = graph(config_overrides, "overlap_measure=overlap")
    g.integrate([Instance3D(keys_box(0, 100), unit(1.0), "table")], 0)
    stats = g.integrate([Instance3D(keys_box(shift, shift + 100), unit(1.0), "table")], 1)
    assert (stats.n_merged, len(g.nodes)) == ((1, 1) if merges else (0, 2))


@pytest.mark.parametrize(("cosine", "merges"), [(0.69, False), (0.71, True)])
def test_similarity_below_the_threshold_starts_a_new_node(config_overrides, cosine: float, merges: bool) -> None:
    g = graph(config_overrides)
    g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), unit(1.0), "sofa")], 0)
    stats = g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), with_cosine(cosine), "sofa")], 1)
    assert (stats.n_merged, len(g.nodes)) == ((1, 1) if merges else (0, 2))


def test_one_detection_fuses_into_at_most_one_node_and_the_better_pair_wins(config_overrides) -> None:
    g = graph(config_overrides)
    g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), unit(1.0), "chair")], 0)
    stats = g.integrate(
        [
            Instance3D(keys_box(0, 10, 0, 10, 0, 10), with_cosine(0.8), "chair"),
            Instance3D(keys_box(0, 10, 0, 10, 0, 10), with_cosine(0.95), "chair"),
        ],
        1,
    )
    assert stats.merged_node_ids == [0] and stats.new_node_ids == [1]
    np.testing.assert_array_equal(g.nodes[0].embedding_mean, (unit(1.0).astype(np.float64) + with_cosine(0.95)) / 2)


def test_pruning_removes_exactly_the_tiny_node(config_overrides) -> None:
    """Sizes 1000, 1200, 1100 and 5 voxels: the median is 1050, a tenth of it 105; only the 5-voxel node goes."""
    g = graph(config_overrides)
    sizes = {0: (0, 10, 0, 10, 0, 10), 1: (20, 32, 0, 10, 0, 10), 2: (40, 51, 0, 10, 0, 10), 3: (60, 65)}
    for frame, box in sizes.items():
        g.integrate([Instance3D(keys_box(*box), unit(1.0, frame), "x")], frame)
        g.integrate([Instance3D(keys_box(*box), unit(1.0, frame), "x")], frame)  # seen twice: not stale
    assert [n.n_voxels for n in g.nodes.values()] == [1000, 1200, 1100, 5]
    assert g.prune(frame_index=4) == [3]
    assert sorted(g.nodes) == [0, 1, 2]


def test_nodes_seen_once_long_ago_are_pruned(config_overrides) -> None:
    g = graph(config_overrides)  # pruned when seen once and not in the last 10 frames
    g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), unit(1.0), "a")], 0)  # seen once, at frame 0
    g.integrate([Instance3D(keys_box(20, 30, 0, 10, 0, 10), unit(0.0, 1.0), "b")], 0)
    g.integrate([Instance3D(keys_box(20, 30, 0, 10, 0, 10), unit(0.0, 1.0), "b")], 1)  # seen twice
    g.integrate([Instance3D(keys_box(40, 50, 0, 10, 0, 10), unit(0.0, 0.0, 1.0), "c")], 5)  # once, recently
    assert g.prune(frame_index=9) == []
    assert g.prune(frame_index=10) == [0]
    assert sorted(g.nodes) == [1, 2]


def test_periodic_pruning_runs_every_prune_every_updates(config_overrides, fixed_value) -> None:
    fixed_value("perception.prune_every", 3)
    fixed_value("perception.prune_stale_frames", 1)
    g = OnlineSceneGraph(perception_config(config_overrides), K, MOUNT)
    g.integrate([Instance3D(keys_box(0, 10, 0, 10, 0, 10), unit(1.0), "a")], 0)
    assert g.integrate([], 1).n_pruned == 0
    assert g.integrate([], 2).n_pruned == 1 and not g.nodes


def test_edges_connect_exactly_the_close_pairs(config_overrides) -> None:
    """Centroids at x = 0, 1.5, 10 and 11.9 m (edge distance 2 m): two edges."""
    g = graph(config_overrides)
    for i, x in enumerate((0, 30, 200, 238)):  # voxel index × 0.05 m: 0, 1.5, 10, 11.9
        g.integrate([Instance3D(keys_box(x, x + 1), unit(1.0, i), "x")], i)
    np.testing.assert_allclose([n.centroid_m[0] for n in g.nodes.values()], [0.025, 1.525, 10.025, 11.925])
    assert g.edges() == [(0, 1), (2, 3)]


def test_duplicate_nodes_from_partial_views_are_merged_later(config_overrides) -> None:
    """Two nodes of one table (front half, then the whole top seen after the front node was made)."""
    g = graph(config_overrides, "overlap_measure=iou")
    g.integrate([Instance3D(keys_box(0, 40), unit(1.0, 0.1), "table")], 0)
    g.integrate([Instance3D(keys_box(0, 100), unit(1.0, -0.1), "table")], 1)  # IoU 0.4: a new node
    assert len(g.nodes) == 2
    g.integrate([Instance3D(keys_box(0, 100), unit(1.0), "table")], 2)  # node 1 (IoU 1), not node 0 (0.4)
    g.nodes[0].fuse(Instance3D(keys_box(40, 95), unit(1.0), "table"), 3)  # node 0 grows over the top
    assert g.merge_nodes() == [(0, 1)]
    node = g.nodes[0]
    assert node.n_observations == 4 and node.n_voxels == 100 and node.last_frame == 3


def test_observations_are_the_nodes_in_view_with_range_and_bearing_in_the_base_frame(config_overrides) -> None:
    g = graph(config_overrides)
    voxels = {"ahead": (60, 0), "left": (60, 30), "wide left": (60, 60), "behind": (-60, 0), "far": (300, 0)}
    for i, (x, y) in enumerate(voxels.values()):
        g.integrate([Instance3D(keys_box(x, x + 1, y, y + 1), unit(1.0, i), f"label{i}", 0.3 + 0.1 * i)], i)
    robot = np.array([1.0, 0.0, 0.0])  # at x = 1 m looking along +x; nodes 2.025 m ahead, 0.025 / 1.525 m left
    obs = g.observations(robot, fov_rad=np.deg2rad(90.0), max_range_m=6.0)
    assert obs.labels == ["label0", "label1"] and obs.node_ids.tolist() == [0, 1]
    np.testing.assert_allclose(obs.range_m, [np.hypot(2.025, 0.025), np.hypot(2.025, 1.525)])
    np.testing.assert_allclose(obs.bearing_rad, [np.arctan2(0.025, 2.025), np.arctan2(1.525, 2.025)])
    assert obs.bearing_rad[1] > 0  # left of the robot is counter-clockwise
    np.testing.assert_allclose(obs.confidence, [0.3, 0.4])  # each node's detector confidence
    np.testing.assert_array_equal(obs.embeddings, np.stack([g.nodes[0].embedding, g.nodes[1].embedding]))
    wide = g.observations(robot, fov_rad=np.deg2rad(120.0), max_range_m=6.0)
    assert wide.node_ids.tolist() == [0, 1, 2]  # 56° to the left is in a 120° view; behind and 14 m off never
    # Only the nodes detected in frame 1 or later (node 0 was last detected in frame 0).
    recent = g.observations(robot, fov_rad=np.deg2rad(120.0), max_range_m=6.0, since_frame=1)
    assert recent.node_ids.tolist() == [1, 2]


def test_update_lifts_masks_and_fuses_two_views_of_a_wall_patch(config_overrides) -> None:
    """The same 3 m-away patch, masked in two frames taken from the same pose: one node, two observations."""
    g = OnlineSceneGraph(perception_config(config_overrides), K, MOUNT)
    depth = np.full((240, 320), 3.0, np.float32)
    mask = np.zeros((1, 240, 320), bool)
    mask[0, 100:140, 140:180] = True
    detection = Detection(np.array([140.0, 100, 180, 140]), "television", 0.9, 0.9)
    for i in range(2):
        frame = Frame(i, float(i), np.zeros((240, 320, 3), np.uint8), depth, np.array([0.0, 0.0, 0.0]))
        stats = g.update(frame, [detection], mask, unit(1.0)[None])
    assert (stats.n_detections, stats.n_lifted, stats.n_merged, len(g.nodes)) == (1, 1, 1, 1)
    centroid = g.nodes[0].centroid_m
    assert centroid[0] == pytest.approx(3.0, abs=0.05) and centroid[2] == pytest.approx(0.5, abs=0.05)
    view = g.view(depth, g.camera_pose(np.zeros(3)))
    assert isinstance(view, CameraView) and view.visible(g.nodes[0].points_m).all()
    hidden = g.view(np.full((240, 320), 1.0, np.float32), g.camera_pose(np.zeros(3)))  # a closer surface hides it
    assert not hidden.visible(g.nodes[0].points_m).any()
    assert len(g.observations(np.zeros(3), view=hidden)) == 0 and len(g.observations(np.zeros(3), view=view)) == 1


def test_empty_graph_observations_have_the_right_shapes(config_overrides) -> None:
    obs = OnlineSceneGraph(perception_config(config_overrides), K, MOUNT).observations(np.zeros(3))
    assert len(obs) == 0 and obs.embeddings.shape[0] == 0 and obs.node_ids.shape == obs.confidence.shape == (0,)


def test_perception_config_validates(config_overrides) -> None:
    assert isinstance(perception_config(config_overrides), PerceptionConfig)
