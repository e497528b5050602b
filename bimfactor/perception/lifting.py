"""Lifting 2D masks to 3D instances: masked depth → camera points → odometry frame → voxels → DBSCAN.

The online graph lives in the odometry frame (the robot does not know its world pose), so a pixel (u, v) with
depth z becomes p_camera = z·((u − cx)/fx, (v − cy)/fy, 1) and p_odom = T_odom_base · T_base_camera · p_camera,
with T_odom_base the planar odometry pose lifted to 4 × 4. Points are downsampled to voxel centres first and
DBSCAN (Open3D `cluster_dbscan`) runs on those, keeping the largest cluster: the same denoising as on the raw
points (eps above the voxel diagonal), at a fraction of the cost. Instances are kept as integer voxel
indices, so fusing two of them is a set union.
"""

from __future__ import annotations

import numpy as np

from bimfactor.config import PerceptionConfig
from bimfactor.types import CameraIntrinsics, se2_to_matrix

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)  # voxel indices in [-2^20, 2^20): ±52 km at 5 cm
_KEY_MASK = (1 << _KEY_BITS) - 1


def T_odom_camera(T_odom_base: np.ndarray, T_base_camera: np.ndarray) -> np.ndarray:
    """(4, 4) camera → odometry transform from the (3,) planar odometry pose and the (4, 4) camera mount."""
    return se2_to_matrix(np.asarray(T_odom_base, float)) @ np.asarray(T_base_camera, float)


def backproject(
    depth_m: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, max_depth_m: float, max_points: int
) -> np.ndarray:
    """(N, 3) camera-frame points of the masked pixels with a depth return ≤ `max_depth_m`.

    `depth_m` (H, W) float (NaN: no return), `mask` (H, W) bool; more than `max_points` pixels are strided evenly.
    """
    with np.errstate(invalid="ignore"):
        valid = mask & (depth_m <= max_depth_m)  # NaN compares False
    flat = np.flatnonzero(valid)
    if len(flat) > max_points:
        flat = flat[np.linspace(0, len(flat) - 1, max_points).astype(np.int64)]
    v, u = np.divmod(flat, depth_m.shape[1])
    return intrinsics.backproject(u, v, depth_m.ravel()[flat])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points mapped by a (4, 4) transform."""
    return points @ T[:3, :3].T + T[:3, 3]


def pack_voxels(voxels: np.ndarray) -> np.ndarray:
    """(N,) int64 keys of (N, 3) integer voxel indices (order-preserving per axis, x most significant)."""
    v = np.asarray(voxels, np.int64) + _KEY_OFFSET
    return (v[:, 0] << (2 * _KEY_BITS)) | (v[:, 1] << _KEY_BITS) | v[:, 2]


def unpack_voxels(keys: np.ndarray) -> np.ndarray:
    """(N, 3) int32 voxel indices of (N,) int64 keys."""
    keys = np.asarray(keys, np.int64)
    xyz = np.column_stack([keys >> (2 * _KEY_BITS), (keys >> _KEY_BITS) & _KEY_MASK, keys & _KEY_MASK])
    return (xyz - _KEY_OFFSET).astype(np.int32)


def voxelize(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(M,) sorted unique int64 keys of the voxels that (N, 3) points fall in (voxel downsampling)."""
    return np.unique(pack_voxels(np.floor(np.asarray(points) / voxel_size_m)))


def voxel_centres(keys: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(M, 3) centres of the voxels of (M,) keys."""
    return (unpack_voxels(keys) + 0.5) * voxel_size_m


def largest_cluster(points: np.ndarray, eps_m: float, min_points: int) -> np.ndarray:
    """(N,) bool: members of the largest DBSCAN cluster of (N, 3) points (all False when every point is noise)."""
    import open3d as o3d  # 1.5 s to import: only when a detection needs clustering

    if len(points) == 0:
        return np.zeros(0, bool)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    labels = np.asarray(cloud.cluster_dbscan(eps=eps_m, min_points=min_points, print_progress=False))
    if labels.max(initial=-1) < 0:
        return np.zeros(len(points), bool)
    return labels == int(np.argmax(np.bincount(labels[labels >= 0])))


def lift_mask(
    depth_m: np.ndarray, mask: np.ndarray, intrinsics: CameraIntrinsics, T_odom_cam: np.ndarray, cfg: PerceptionConfig
) -> np.ndarray:
    """(M,) sorted int64 voxel keys (odometry frame) of one masked instance after DBSCAN denoising.

    `depth_m` (H, W) metres (NaN: no return), `mask` (H, W) bool, `T_odom_cam` (4, 4).
    """
    points = backproject(depth_m, mask, intrinsics, cfg.max_depth_m, cfg.max_points)
    keys = voxelize(transform_points(T_odom_cam, points), cfg.voxel_size_m)
    keep = largest_cluster(voxel_centres(keys, cfg.voxel_size_m), cfg.dbscan_eps_m, cfg.dbscan_min_points)
    return keys[keep]
