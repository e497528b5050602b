"""Boxes into instances: a box detector's box segmented by depth, and a detection embedded by its label.

A box detector (YOLOX, a detections file without masks) says where an object is in the image, not which pixels are
it. `box_mask` finds them in the depth: the box's returns above the floor, voxelised and clustered by DBSCAN, and the
cluster with the most pixels in the box's central part (a detector centres its box on its object; the wall behind it
fills the corners). `LabelEmbedder` gives a detection without a crop embedding its label's text embedding, in the
space of the prior's object embeddings.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bimfactor.config import PerceptionConfig
from bimfactor.embed.text import TextEmbedder
from bimfactor.perception.base import Detection, box_to_pixels, empty_masks
from bimfactor.perception.detections import runs_to_mask
from bimfactor.perception.lifting import backproject, pack_voxels
from bimfactor.types import CameraIntrinsics, Frame

BOX_CENTRE_SHARE = 0.5
"""Box segmentation: the object is the depth cluster with the most pixels in the central part of its box this wide."""
BOX_SAMPLES = 20_000
"""Box segmentation clusters at most about this many of a box's pixels: every k-th row and column of a larger box,
each sampled pixel standing for its k × k block (a 200 × 200 px monitor: k = 2; a whole 640 × 480 frame: k = 4, 2 cm
apart at 4 m, under the 5 cm voxels the lifting and the clustering use). On tum-fr1-rpy the nodes are those of every
pixel, at a third of the time (7 against 21 ms a frame); 12,000 lost a chair on slambook-dining."""
CORE_DEPTH_QUANTILE = 0.05
"""Box segmentation: the object spans the depths of its cluster's central pixels, from this quantile to its
complement (a screen's cluster also holds the desk it stands on, which runs from near to far in its box)."""


def box_mask(
    depth_m: np.ndarray,
    box_xyxy: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_base_camera: np.ndarray,
    cfg: PerceptionConfig,
    floor_z_m: float | None,
) -> np.ndarray:
    """(H, W) bool: the object's pixels in a box, found by depth clustering on a grid of `BOX_SAMPLES` pixels. The box's
    returns within `max_depth_m` and `floor_z_m` above the floor (None: every return) are clustered by DBSCAN; the
    object is the cluster with the most pixels in the box's centre (`BOX_CENTRE_SHARE`), spanning the depths of its
    central pixels (`CORE_DEPTH_QUANTILE`), not the wall behind it or the desk under it."""
    height, width = depth_m.shape
    x0, y0, x1, y1 = box_to_pixels(box_xyxy, width, height)
    mask = np.zeros((height, width), bool)
    if x1 <= x0 or y1 <= y0:
        return mask
    step = max(1, int(np.ceil(np.sqrt((y1 - y0) * (x1 - x0) / BOX_SAMPLES))))
    in_box = np.zeros((height, width), bool)
    in_box[y0:y1:step, x0:x1:step] = True
    points = backproject(depth_m, in_box, intrinsics, cfg.max_depth_m, int(in_box.sum()))
    if len(points) == 0:
        return mask
    with np.errstate(invalid="ignore"):
        flat = np.flatnonzero(in_box & (depth_m <= cfg.max_depth_m))  # backproject's pixels, in its order
    if floor_z_m is not None:
        T = np.asarray(T_base_camera, float)
        above_floor = points @ T[2, :3] + T[2, 3] >= floor_z_m
        points, flat = points[above_floor], flat[above_floor]
    if len(points) == 0:
        return mask
    keys, voxel_of = np.unique(pack_voxels(np.floor(points / cfg.voxel_size_m)), return_inverse=True)
    centres = np.zeros((len(keys), 3))
    np.add.at(centres, voxel_of, points)
    centres /= np.bincount(voxel_of, minlength=len(keys))[:, None]
    labels = _cluster_labels(centres, cfg.dbscan_eps_m, cfg.dbscan_min_points)[voxel_of]
    if labels.max(initial=-1) < 0:
        return mask
    v, u = np.divmod(flat, width)
    half_w, half_h = BOX_CENTRE_SHARE * (x1 - x0) / 2, BOX_CENTRE_SHARE * (y1 - y0) / 2
    central = (np.abs(u + 0.5 - (x0 + x1) / 2) <= half_w) & (np.abs(v + 0.5 - (y0 + y1) / 2) <= half_h)
    clustered = labels >= 0
    votes = np.bincount(labels[central & clustered], minlength=labels.max() + 1)
    if votes.max(initial=0) == 0:
        votes = np.bincount(labels[clustered])
    chosen = labels == int(np.argmax(votes))
    core = chosen & central
    if core.any():  # the surface it stands on joins the cluster: keep the depths its central part spans
        near, far = np.percentile(points[core, 2], [100 * CORE_DEPTH_QUANTILE, 100 * (1 - CORE_DEPTH_QUANTILE)])
        chosen &= (points[:, 2] >= near - cfg.voxel_size_m) & (points[:, 2] <= far + cfg.voxel_size_m)
    v, u = v[chosen], u[chosen]
    for dv in range(step):  # each sampled pixel stands for its step × step block, inside the box
        for du in range(step):
            mask[np.minimum(v + dv, y1 - 1), np.minimum(u + du, x1 - 1)] = True
    return mask


def _cluster_labels(points: np.ndarray, eps_m: float, min_points: int) -> np.ndarray:
    """(N,) DBSCAN cluster of each of (N, 3) points, −1 for noise (Open3D, as `lifting.largest_cluster`)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    return np.asarray(cloud.cluster_dbscan(eps=eps_m, min_points=min_points, print_progress=False))


class BoxSegmenter:
    """A detection's own mask where it has one (a detections file's `mask_runs`); otherwise its box segmented by depth
    clustering (`box_mask`)."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        T_base_camera: np.ndarray,
        cfg: PerceptionConfig,
        floor_z_m: float | None,
    ) -> None:
        self.intrinsics = intrinsics
        self.T_base_camera = np.asarray(T_base_camera, float)
        self.cfg = cfg
        self.floor_z_m = floor_z_m

    def segment(self, frame: Frame, detections: Sequence[Detection]) -> np.ndarray:
        """(N, H, W) bool masks, one per detection."""
        if not detections:
            return empty_masks(frame)
        height, width = frame.depth_m.shape
        masks = np.zeros((len(detections), height, width), bool)
        for k, d in enumerate(detections):
            runs = getattr(d, "mask_runs", None)
            if runs is not None:
                masks[k] = runs_to_mask(runs, height, width)
            else:
                masks[k] = box_mask(
                    frame.depth_m, d.box_xyxy, self.intrinsics, self.T_base_camera, self.cfg, self.floor_z_m
                )
        return masks


class LabelEmbedder:
    """A detection's own embedding where it has one (a detections file's `embedding`); otherwise its label's embedding
    by the prior's text encoder."""

    def __init__(self, text_embedder: TextEmbedder) -> None:
        self.name = f"label:{text_embedder.name}"
        self.dim = int(text_embedder.dim)
        self._text = text_embedder

    def embed(self, frame: Frame, detections: Sequence[Detection], masks: np.ndarray) -> np.ndarray:
        """(N, D) float32 unit rows."""
        out = np.zeros((len(detections), self.dim), np.float32)
        own = [getattr(d, "embedding", None) for d in detections]
        missing = [k for k, e in enumerate(own) if e is None]
        if missing:
            out[missing] = self._text.encode([detections[k].label for k in missing])
        for k, e in enumerate(own):
            if e is not None:
                out[k] = e
        return out
