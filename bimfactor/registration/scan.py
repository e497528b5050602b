"""Scans for registration: depth images back-projected into the robot base frame, and local submaps.

The base frame sits on the floor (z up), so the floor and ceiling are cut away by height: only what
the surface model holds (walls, columns, doors, windows) is left to align.
"""

from __future__ import annotations

import numpy as np

from bimfactor.config import RegistrationConfig, SensorConfig
from bimfactor.localization.measurements.scan import DepthPoints, height_band
from bimfactor.types import Frame, SequenceMeta, se2_between, se2_to_matrix

# A scan with fewer points is not registered (the fine stage) nor used (the comparison's keyframes).
MIN_SCAN_POINTS = 100


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N, 3) → (M, 3) voxel centroids (Open3D's voxel grid filter)."""
    import open3d as o3d

    if len(points) == 0:
        return np.zeros((0, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    return np.asarray(cloud.voxel_down_sample(voxel_m).points)


def frame_scan(
    frame: Frame,
    meta: SequenceMeta,
    cfg: RegistrationConfig,
    sensor: SensorConfig,
    voxel_m: float | None = None,
    points: DepthPoints | None = None,
) -> np.ndarray:
    """One frame's registration scan: (N, 3) base-frame wall points within the sensor's range, from its floor cut
    (`sensor.min_z_m`) up to `cfg.scan_max_z_m`, voxel-downsampled (default voxel from cfg); `points`, the frame's
    returns when a keyframe has them already (`DepthPoints.of_frame`)."""
    points = points if points is not None else DepthPoints.of_frame(frame, meta)
    points = height_band(points.within(sensor.max_range_m), sensor.min_z_m, cfg.scan_max_z_m)
    return voxel_downsample(points, cfg.scan_voxel_m if voxel_m is None else voxel_m)


def stitch_submap(scans_base: list[np.ndarray], poses: np.ndarray, voxel_m: float) -> np.ndarray:
    """Scans (each (N_k, 3) in its own base frame) taken at (K, 3) poses of one frame (e.g. odometry) → (M, 3).

    The result is in the base frame of the last scan, voxel-downsampled once more so overlaps do not weigh double.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(scans_base) != len(poses) or not scans_base:
        raise ValueError(f"stitch_submap: {len(scans_base)} scans but {len(poses)} poses")
    relative = se2_between(poses[-1], poses)  # (K, 3): each keyframe in the current base frame
    parts = []
    for scan, rel in zip(scans_base, relative, strict=True):
        T = se2_to_matrix(rel)
        parts.append(scan @ T[:3, :3].T + T[:3, 3])
    return voxel_downsample(np.concatenate(parts), voxel_m)
