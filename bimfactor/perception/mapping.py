"""The online open-set scene graph of a whole recording from its camera poses (`bimfactor scene-graph`).

Built in the world frame from 6-DoF camera poses (a TUM folder's motion capture, or a sequence's ground truth, else
odometry, through its camera mount), each frame perceived, lifted and fused as the localizer does; at the end
duplicates merge and nodes seen once are dropped. `fused_cloud` is the figure's cloud, `graph_record` scene_graph.json.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bimfactor.errors import InputError
from bimfactor.perception.lifting import backproject, transform_points, voxel_centres, voxelize
from bimfactor.perception.pipeline import Perception
from bimfactor.perception.scene_graph import OnlineSceneGraph
from bimfactor.progress import progress
from bimfactor.types import Frame, se2_to_matrix

CLOUD_VOXEL_M = 0.05
"""The fused cloud's voxel."""
CLOUD_POINTS_PER_FRAME = 20_000
"""At most this many depth pixels of a frame go into the fused cloud (evenly strided)."""


def sequence_camera_poses(frames: Sequence[Frame], T_base_camera: np.ndarray) -> tuple[np.ndarray, str]:
    """(N, 4, 4) T_world_camera of a robot's frames: the ground-truth base pose where every frame has one, else the
    odometry pose, composed with the camera mount; and which of the two it was. InputError when neither is known."""
    mount = np.asarray(T_base_camera, float)
    if all(f.gt_pose is not None and np.all(np.isfinite(f.gt_pose)) for f in frames):
        planar, source = [f.gt_pose for f in frames], "ground truth"
    elif all(np.all(np.isfinite(f.odom_pose)) for f in frames):
        planar, source = [f.odom_pose for f in frames], "odometry"
    else:
        raise InputError("the recording has neither ground-truth nor odometry poses for every frame")
    return np.stack([se2_to_matrix(np.asarray(p, float)) @ mount for p in planar]), source


def map_recording(
    frames: Sequence[Frame], T_world_cameras: np.ndarray, perception: Perception, show_progress: bool = False
) -> tuple[OnlineSceneGraph, list[dict[str, float]]]:
    """The scene graph of `frames` seen from (N, 4, 4) camera poses (a frame whose pose is not finite is left out),
    and per frame used the milliseconds of its detector and lifting (`Perception.fuse`)."""
    graph = perception.graph
    timing = []
    rows = list(zip(frames, T_world_cameras, strict=True))
    for frame, T in progress(rows, desc="scene graph", unit="frame") if show_progress else rows:
        if np.all(np.isfinite(T)):
            timing.append(perception.fuse(frame, T)[-1])
    if not timing:
        raise InputError("no frame of the recording has a camera pose")
    last = max(f.index for f in frames)
    graph.merge_nodes()
    graph.prune(last + graph.cfg.prune_stale_frames)  # the end of the recording: a single sighting is stale
    return graph, timing


def fused_cloud(
    frames: Sequence[Frame], T_world_cameras: np.ndarray, intrinsics: Any, max_depth_m: float
) -> np.ndarray:
    """(M, 3) world-frame centres of the voxels (`CLOUD_VOXEL_M`) that the frames' depth falls in."""
    keys = []
    for frame, T in zip(frames, T_world_cameras, strict=True):
        if not np.all(np.isfinite(T)):
            continue
        points = backproject(frame.depth_m, np.ones(frame.depth_m.shape, bool), intrinsics, max_depth_m,
                             CLOUD_POINTS_PER_FRAME)  # fmt: skip
        keys.append(voxelize(transform_points(T, points), CLOUD_VOXEL_M))
    if not keys:
        return np.zeros((0, 3))
    return voxel_centres(np.unique(np.concatenate(keys)), CLOUD_VOXEL_M)


def up_direction(T_world_cameras: np.ndarray) -> np.ndarray:
    """(3,) the world's up as the recording saw it: against the mean of its cameras' down axes (OpenCV's y), which
    a ground robot's level camera and a hand-held one held upright both point at the floor."""
    finite = np.all(np.isfinite(T_world_cameras), axis=(1, 2))
    down = T_world_cameras[finite, :3, 1].mean(axis=0)
    return -down / max(float(np.linalg.norm(down)), 1e-12)


def graph_record(graph: OnlineSceneGraph, recording: str | Path, poses: str, frames_used: int, detector: str) -> dict:
    """What scene_graph.json holds: where the poses came from, and each node's label, centre and extent (its voxels'
    axis-aligned box in the world frame, metres), observations, voxels, first and last frame and best score; the
    edges between nodes closer than `perception.edge_distance_m`."""
    nodes = []
    for node in sorted(graph.nodes.values(), key=lambda n: n.id):
        lo, hi = node.box(0.0)
        nodes.append(
            {
                "id": int(node.id),
                "label": node.label,
                "centre_m": [round(float(v), 4) for v in node.centroid_m],
                "extent_m": [round(float(v), 4) for v in hi - lo + graph.cfg.voxel_size_m],
                "n_observations": int(node.n_observations),
                "n_voxels": int(node.n_voxels),
                "first_frame": int(node.first_frame),
                "last_frame": int(node.last_frame),
                "score": round(float(node.score), 4),
                "labels": dict(node.label_votes.most_common()),
            }
        )
    return {
        "recording": str(recording),
        "poses": poses,
        "detector": detector,
        "frames_used": int(frames_used),
        "frame": "world",
        "nodes": nodes,
        "edges": [[int(a), int(b)] for a, b in graph.edges()],
    }
