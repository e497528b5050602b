"""The online open-set scene graph M (paper Sec. II.B), built frame by frame in the odometry frame.

One update reads like the paper:
1. lift:      each detection's mask is lifted to 3D and voxel-downsampled (`lifting.lift_mask`).
2. associate: a lifted instance j joins node k when cos(f_j, f_k) ≥ δ_sim AND its 3D overlap with the part of k the
              camera can see ≥ δ_IoU (`overlap_measure`: the paper's IoU, or the overlap coefficient); a one-to-one
              assignment maximising cos + overlap (Hungarian); the rest start new nodes.
3. fuse:      voxel sets are united, the embedding is the running mean, the label the majority vote.
4. prune:     every `prune_every` frames small and stale nodes go, and node pairs that pass both thresholds merge.
Edges join nodes whose centroids are closer than `edge_distance_m`. Why boxes and the overlap coefficient:
docs/perception.md.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from bimfactor.config import PerceptionConfig
from bimfactor.perception.base import Detection
from bimfactor.perception.lifting import T_odom_camera, lift_mask, transform_points, voxel_centres
from bimfactor.types import CameraIntrinsics, Frame, Observations, se2_to_matrix

log = logging.getLogger(__name__)

MIN_VISIBLE_VOXELS = 3  # a node with fewer voxels in the current view is not in view


@dataclass
class Instance3D:
    """A lifted detection: (M,) sorted int64 voxel keys in the odometry frame, (D,) unit embedding, label."""

    keys: np.ndarray
    embedding: np.ndarray
    label: str
    score: float = 1.0


@dataclass
class CameraView:
    """What the camera sees now: intrinsics, (4, 4) T_odom_camera and the (H, W) depth (NaN: no return)."""

    intrinsics: CameraIntrinsics
    T_odom_camera: np.ndarray
    depth_m: np.ndarray
    occlusion_tolerance_m: float

    def visible(self, points_odom: np.ndarray) -> np.ndarray:
        """(N,) bool: (N, 3) odometry-frame points in front of the camera, inside the image, and not hidden
        behind the observed depth by more than the tolerance (a pixel with no return hides nothing)."""
        T_camera_odom = np.linalg.inv(self.T_odom_camera)
        p = transform_points(T_camera_odom, points_odom)
        k = self.intrinsics
        z = p[:, 2]
        in_front = z > 1e-6
        safe_z = np.where(in_front, z, 1.0)
        u = np.floor(k.fx * p[:, 0] / safe_z + k.cx + 0.5).astype(np.int64)
        v = np.floor(k.fy * p[:, 1] / safe_z + k.cy + 0.5).astype(np.int64)
        inside = in_front & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        observed = np.full(len(p), np.nan)
        observed[inside] = self.depth_m[v[inside], u[inside]]
        with np.errstate(invalid="ignore"):
            hidden = z > observed + self.occlusion_tolerance_m
        return inside & ~hidden


@dataclass
class SceneNode:
    """An object node: voxel set, running-mean embedding with its count, label votes, when it was seen, and the
    highest detector confidence among its detections."""

    id: int
    keys: np.ndarray
    embedding_mean: np.ndarray
    n_observations: int
    label_votes: Counter[str]
    first_frame: int
    last_frame: int
    voxel_size_m: float
    score: float = 1.0
    _points: np.ndarray | None = field(default=None, init=False, repr=False)
    _bounds: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def embedding(self) -> np.ndarray:
        """(D,) float32 unit vector of the fused embedding, for cosine similarity."""
        return (self.embedding_mean / max(float(np.linalg.norm(self.embedding_mean)), 1e-12)).astype(np.float32)

    @property
    def label(self) -> str:
        """Majority vote of the fused labels (ties: the label seen first)."""
        return self.label_votes.most_common(1)[0][0]

    @property
    def n_voxels(self) -> int:
        return len(self.keys)

    @property
    def points_m(self) -> np.ndarray:
        """(M, 3) voxel centres in the odometry frame (cached until the node changes)."""
        if self._points is None:
            self._points = voxel_centres(self.keys, self.voxel_size_m)
        return self._points

    def box(self, padding_m: float) -> np.ndarray:
        """(2, 3) axis-aligned box of the voxel centres grown by `padding_m` (cached until the node changes)."""
        if self._bounds is None:
            self._bounds = aabb(self.points_m, 0.0)
        return self._bounds + np.array([[-padding_m], [padding_m]])

    def _changed(self) -> None:
        self._points = self._bounds = None

    @property
    def centroid_m(self) -> np.ndarray:
        """(3,) mean of the voxel centres in the odometry frame."""
        return self.points_m.mean(axis=0)

    def fuse(self, instance: Instance3D, frame_index: int) -> None:
        """Volumetric and embedding fusion: voxel union, f = (n f + f_new)/(n + 1), one more label vote."""
        n = self.n_observations
        self.keys = np.union1d(self.keys, instance.keys)
        self.embedding_mean = (n * self.embedding_mean + np.asarray(instance.embedding, np.float64)) / (n + 1)
        self.n_observations = n + 1
        self.label_votes[instance.label] += 1
        self.score = max(self.score, instance.score)
        self.last_frame = frame_index
        self._changed()

    def absorb(self, other: SceneNode) -> None:
        """Merge another node into this one: voxel union, count-weighted embedding mean, summed votes."""
        n, m = self.n_observations, other.n_observations
        self.keys = np.union1d(self.keys, other.keys)
        self.embedding_mean = (n * self.embedding_mean + m * other.embedding_mean) / (n + m)
        self.n_observations = n + m
        self.label_votes.update(other.label_votes)
        self.score = max(self.score, other.score)
        self.first_frame = min(self.first_frame, other.first_frame)
        self.last_frame = max(self.last_frame, other.last_frame)
        self._changed()


@dataclass
class UpdateStats:
    """What one graph update did and what it took (milliseconds, without the detector)."""

    frame_index: int
    n_detections: int = 0
    n_lifted: int = 0
    n_merged: int = 0
    n_new: int = 0
    n_pruned: int = 0
    n_nodes: int = 0
    lift_ms: float = 0.0
    associate_ms: float = 0.0
    merged_node_ids: list[int] = field(default_factory=list)
    new_node_ids: list[int] = field(default_factory=list)


def _voxel_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Shared voxels of two sorted key sets over their union's count."""
    shared = len(np.intersect1d(a, b, assume_unique=True))
    return shared / max(len(a) + len(b) - shared, 1)


def aabb(points: np.ndarray, padding_m: float) -> np.ndarray:
    """(2, 3) min and max corners of (N, 3) points, grown by `padding_m` on every side."""
    return np.stack([points.min(axis=0) - padding_m, points.max(axis=0) + padding_m])


def aabb_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Volume IoU of two (2, 3) axis-aligned boxes."""
    inter = np.clip(np.minimum(a[1], b[1]) - np.maximum(a[0], b[0]), 0.0, None).prod()
    union = (a[1] - a[0]).prod() + (b[1] - b[0]).prod() - inter
    return float(inter / union) if union > 0 else 0.0


def aabb_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection volume over the smaller volume of two (2, 3) axis-aligned boxes (overlap coefficient)."""
    inter = np.clip(np.minimum(a[1], b[1]) - np.maximum(a[0], b[0]), 0.0, None).prod()
    smaller = min((a[1] - a[0]).prod(), (b[1] - b[0]).prod())
    return float(inter / smaller) if smaller > 0 else 0.0


class OnlineSceneGraph:
    """The incremental open-set scene graph: nodes in the odometry frame, fused across frames."""

    def __init__(
        self, cfg: PerceptionConfig, intrinsics: CameraIntrinsics, T_base_camera: np.ndarray, embedding_dim: int = 0
    ) -> None:
        """`embedding_dim` is the width of the (0, D) embeddings an empty graph reports (0: unknown)."""
        self.cfg = cfg
        self.embedding_dim = embedding_dim
        self.intrinsics = intrinsics
        self.T_base_camera = np.asarray(T_base_camera, float)
        self.nodes: dict[int, SceneNode] = {}
        self._next_id = 0
        self._updates = 0

    # -------------------------------------------------------------------------------- the update

    def camera_pose(self, T_odom_base: np.ndarray) -> np.ndarray:
        """(4, 4) T_odom_camera of a ground robot at (3,) planar odometry pose T_odom_base, through the mount."""
        return T_odom_camera(T_odom_base, self.T_base_camera)

    def view(self, depth_m: np.ndarray, T_odom_cam: np.ndarray) -> CameraView:
        """The camera view of a frame's depth from the (4, 4) camera pose T_odom_camera."""
        return CameraView(self.intrinsics, np.asarray(T_odom_cam, float), depth_m, self.cfg.occlusion_tolerance_m)

    def lift(
        self,
        depth_m: np.ndarray,
        detections: Sequence[Detection],
        masks: np.ndarray,
        embeddings: np.ndarray,
        T_odom_cam: np.ndarray,
    ) -> list[Instance3D]:
        """Lift each detection's mask from the (4, 4) camera pose to a denoised voxel set; instances under
        `min_instance_voxels` are dropped, and so is an instance whose voxels are one volume with a better-scored
        one's of the same frame (their voxel sets' IoU reaches δ_IoU): one object is one detection in a frame, and a
        box detector's second box on it (a table's box whose depth cluster is the chair in front of it) is not a
        second object, while a chair whose voxels lie inside a table's larger set is."""
        c = self.cfg
        out: list[Instance3D] = []
        for k in np.argsort([-d.box_score for d in detections], kind="stable"):
            detection, mask, embedding = detections[k], masks[k], embeddings[k]
            keys = lift_mask(depth_m, mask, self.intrinsics, T_odom_cam, c)
            if len(keys) < c.min_instance_voxels or any(_voxel_iou(keys, i.keys) >= c.iou_threshold for i in out):
                continue
            out.append(Instance3D(keys, np.asarray(embedding, np.float32), detection.label, detection.box_score))
        return out

    def update(
        self,
        frame: Frame,
        detections: Sequence[Detection],
        masks: np.ndarray,
        embeddings: np.ndarray,
        T_odom_cam: np.ndarray | None = None,
    ) -> UpdateStats:
        """Lift, associate, fuse and (every `prune_every` frames) prune, from the (4, 4) camera pose T_odom_camera: any
        6-DoF pose (a hand-held camera's), by default the ground robot's at the frame's odometry pose."""
        T = self.camera_pose(frame.odom_pose) if T_odom_cam is None else np.asarray(T_odom_cam, float)
        t0 = time.perf_counter()
        instances = self.lift(frame.depth_m, detections, masks, embeddings, T)
        t1 = time.perf_counter()
        stats = self.integrate(instances, frame.index, self.view(frame.depth_m, T))
        t2 = time.perf_counter()
        stats.n_detections = len(detections)
        stats.lift_ms, stats.associate_ms = (t1 - t0) * 1e3, (t2 - t1) * 1e3
        return stats

    def integrate(
        self, instances: Sequence[Instance3D], frame_index: int, view: CameraView | None = None
    ) -> UpdateStats:
        """Associate lifted instances with the nodes, fuse or create, prune when due; `view` limits IoU_3 to
        the part of each node the camera sees (None: the whole node)."""
        stats = UpdateStats(frame_index, n_lifted=len(instances))
        assignment = self.associate(instances, view)
        for j, instance in enumerate(instances):
            k = assignment.get(j)
            if k is None:
                stats.new_node_ids.append(self._new_node(instance, frame_index))
            else:
                self.nodes[k].fuse(instance, frame_index)
                stats.merged_node_ids.append(k)
        stats.n_merged, stats.n_new = len(stats.merged_node_ids), len(stats.new_node_ids)
        self._updates += 1
        if self._updates % self.cfg.prune_every == 0:
            self.merge_nodes()
            stats.n_pruned = len(self.prune(frame_index))
        stats.n_nodes = len(self.nodes)
        return stats

    def similarity_and_iou(
        self, instances: Sequence[Instance3D], view: CameraView | None = None
    ) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """(J, K) cosine similarities and IoU_3 of instances against nodes, and the K node ids (IoU 0: no overlap)."""
        node_ids = list(self.nodes)
        sim = np.zeros((len(instances), len(node_ids)))
        iou = np.zeros_like(sim)
        if not instances or not node_ids:
            return sim, iou, node_ids
        pad = self.cfg.iou_padding_m
        node_boxes = np.stack([self.nodes[k].box(pad) for k in node_ids])
        node_embeddings = np.stack([self.nodes[k].embedding for k in node_ids])
        visible_boxes: dict[int, np.ndarray] = {}
        for j, instance in enumerate(instances):
            box = aabb(voxel_centres(instance.keys, self.cfg.voxel_size_m), pad)
            overlaps = np.all((node_boxes[:, 0] < box[1]) & (node_boxes[:, 1] > box[0]), axis=1)
            sim[j] = node_embeddings @ np.asarray(instance.embedding, np.float32)
            for col in np.flatnonzero(overlaps):
                if col not in visible_boxes:
                    visible_boxes[col] = self._visible_box(self.nodes[node_ids[col]], view)
                iou[j, col] = self._overlap(box, visible_boxes[col])
        return sim, iou, node_ids

    def associate(self, instances: Sequence[Instance3D], view: CameraView | None = None) -> dict[int, int]:
        """{instance index: node id} for the pairs with cos ≥ δ_sim and IoU_3 ≥ δ_IoU, one-to-one (Hungarian)."""
        sim, iou, node_ids = self.similarity_and_iou(instances, view)
        valid = (sim >= self.cfg.sim_threshold) & (iou >= self.cfg.iou_threshold)
        if not valid.any():
            return {}
        cost = np.where(valid, -(sim + iou), 1e6)
        rows, cols = linear_sum_assignment(cost)
        return {int(j): node_ids[int(k)] for j, k in zip(rows, cols, strict=True) if valid[j, k]}

    def _overlap(self, a: np.ndarray, b: np.ndarray) -> float:
        return aabb_iou(a, b) if self.cfg.overlap_measure == "iou" else aabb_overlap(a, b)

    def _visible_box(self, node: SceneNode, view: CameraView | None) -> np.ndarray:
        if view is not None:
            seen = view.visible(node.points_m)
            if seen.sum() >= MIN_VISIBLE_VOXELS:
                return aabb(node.points_m[seen], self.cfg.iou_padding_m)
        return node.box(self.cfg.iou_padding_m)

    def _new_node(self, instance: Instance3D, frame_index: int) -> int:
        node_id = self._next_id
        self._next_id += 1
        self.nodes[node_id] = SceneNode(
            node_id,
            np.asarray(instance.keys, np.int64),
            np.asarray(instance.embedding, np.float64).copy(),
            1,
            Counter([instance.label]),
            frame_index,
            frame_index,
            self.cfg.voxel_size_m,
            instance.score,
        )
        return node_id

    # -------------------------------------------------------------------------------- pruning and edges

    def prune(self, frame_index: int) -> list[int]:
        """Remove nodes below `prune_size_ratio` × the median node size and stale single sightings; their ids."""
        if not self.nodes:
            return []
        sizes = np.array([n.n_voxels for n in self.nodes.values()])
        min_voxels = self.cfg.prune_size_ratio * float(np.median(sizes))
        stale = self.cfg.prune_stale_frames
        doomed = [
            k
            for k, n in self.nodes.items()
            if n.n_voxels < min_voxels or (n.n_observations == 1 and frame_index - n.last_frame >= stale)
        ]
        for k in doomed:
            del self.nodes[k]
        if doomed:
            log.debug("frame %d: pruned %d nodes (size < %.1f voxels or stale)", frame_index, len(doomed), min_voxels)
        return doomed

    def merge_nodes(self) -> list[tuple[int, int]]:
        """Fuse node pairs that pass both thresholds on their whole boxes (duplicates from partial views);
        the younger node goes into the older. Returns the (kept, removed) id pairs."""
        merged: list[tuple[int, int]] = []
        while True:
            pair = self._best_duplicate_pair()
            if pair is None:
                return merged
            keep, drop = pair
            self.nodes[keep].absorb(self.nodes.pop(drop))
            merged.append(pair)

    def _best_duplicate_pair(self) -> tuple[int, int] | None:
        """The pair of nodes most alike (cosine + overlap) among those that pass both thresholds, or whose boxes are
        one volume (IoU_3 ≥ δ_IoU whatever their labels: a closed-set detector calls one screen "tv" in one frame and
        "laptop" in the next, while a chair tucked under a table fills a fraction of its box)."""
        node_ids = list(self.nodes)
        if len(node_ids) < 2:
            return None
        pad = self.cfg.iou_padding_m
        boxes = np.stack([self.nodes[k].box(pad) for k in node_ids])
        embeddings = np.stack([self.nodes[k].embedding for k in node_ids])
        sims = embeddings @ embeddings.T
        touching = np.all((boxes[:, None, 0] < boxes[None, :, 1]) & (boxes[:, None, 1] > boxes[None, :, 0]), axis=2)
        best, best_score = None, -np.inf
        for a, b in zip(*np.nonzero(np.triu(touching, k=1)), strict=True):
            overlap = self._overlap(boxes[a], boxes[b])
            alike = sims[a, b] >= self.cfg.sim_threshold and overlap >= self.cfg.iou_threshold
            if (alike or aabb_iou(boxes[a], boxes[b]) >= self.cfg.iou_threshold) and sims[a, b] + overlap > best_score:
                best, best_score = (node_ids[a], node_ids[b]), sims[a, b] + overlap
        return best

    def edges(self) -> list[tuple[int, int]]:
        """Node-id pairs (a < b) whose centroids are closer than `edge_distance_m`."""
        node_ids = list(self.nodes)
        if len(node_ids) < 2:
            return []
        tree = cKDTree(np.stack([self.nodes[k].centroid_m for k in node_ids]))
        pairs = tree.query_pairs(self.cfg.edge_distance_m, output_type="ndarray")
        return sorted((min(node_ids[a], node_ids[b]), max(node_ids[a], node_ids[b])) for a, b in pairs)

    # -------------------------------------------------------------------------------- what the localizer sees

    def observations(
        self,
        T_odom_base: np.ndarray,
        fov_rad: float | None = None,
        max_range_m: float | None = None,
        view: CameraView | None = None,
        since_frame: int | None = None,
    ) -> Observations:
        """The nodes in the current view sector (FOV default: the camera's; range default: `max_depth_m`), with
        fused embedding, label, and range / bearing in the robot base frame; `view` also drops hidden nodes and
        `since_frame` nodes not detected in that frame or later."""
        fov = self.intrinsics.hfov_rad if fov_rad is None else fov_rad
        max_range = self.cfg.max_depth_m if max_range_m is None else max_range_m
        dim = next(iter(self.nodes.values())).embedding_mean.shape[0] if self.nodes else self.embedding_dim
        node_ids = list(self.nodes)
        if not node_ids:
            return Observations(
                np.zeros((0, dim), np.float32), np.zeros(0), np.zeros(0), [], np.zeros(0, np.int64), np.zeros(0)
            )
        centroids = np.stack([self.nodes[k].centroid_m for k in node_ids])
        in_base = transform_points(np.linalg.inv(se2_to_matrix(T_odom_base)), centroids)
        ranges = np.hypot(in_base[:, 0], in_base[:, 1])
        bearings = np.arctan2(in_base[:, 1], in_base[:, 0])
        keep = (ranges <= max_range) & (np.abs(bearings) <= fov / 2)
        if since_frame is not None:
            keep &= np.asarray([self.nodes[k].last_frame >= since_frame for k in node_ids])
        if view is not None:
            for i in np.flatnonzero(keep):
                node = self.nodes[node_ids[i]]
                keep[i] = view.visible(node.points_m).sum() >= min(MIN_VISIBLE_VOXELS, node.n_voxels)
        idx = np.flatnonzero(keep)
        return Observations(
            np.asarray([self.nodes[node_ids[i]].embedding for i in idx], np.float32).reshape(len(idx), dim),
            ranges[idx],
            bearings[idx],
            [self.nodes[node_ids[i]].label for i in idx],
            np.asarray([node_ids[i] for i in idx], np.int64),
            np.asarray([self.nodes[node_ids[i]].score for i in idx], float),
        )
