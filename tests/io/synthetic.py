"""Small synthetic sequences (32 × 24 images) with exactly known content, for the I/O tests."""

from __future__ import annotations

import numpy as np

from bimfactor.io.sequence import level_camera_mount
from bimfactor.types import CameraIntrinsics, Frame, SequenceMeta

WIDTH, HEIGHT = 32, 24


def make_meta(name: str = "synthetic") -> SequenceMeta:
    T_base_camera = level_camera_mount(0.5)
    T_base_camera[0, 3] = 0.15
    return SequenceMeta(
        name=name,
        source="sim",
        intrinsics=CameraIntrinsics.from_hfov(WIDTH, HEIGHT, 90.0),
        T_base_camera=T_base_camera,
        prior_sha256="0123456789abcdef" * 4,
        instances=[
            {"id": 0, "guid": "2O2Fr$t4X7Zf8NOew3FLOH", "ifc_class": "IfcWall", "object_id": -1, "label": "wall"},
            {"id": 1, "guid": "1hOSvn6df7F8_7GcBWlR72", "ifc_class": "IfcFurniture", "object_id": 4, "label": "chair"},
        ],
        extras={"seed": 7, "world": {"moved_fraction": 0.0}},
    )


def make_frames(n: int = 5, seed: int = 0) -> list[Frame]:
    """Random images and poses; frame 1 lacks ground truth and instances, frame 2 has no extras."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        depth = rng.uniform(0.2, 9.0, size=(HEIGHT, WIDTH)).astype(np.float32)
        depth[rng.random((HEIGHT, WIDTH)) < 0.1] = np.nan
        depth[0, 0] = 0.0004  # rounds to 0 mm: no return
        depth[0, 1] = 65.535  # the largest depth the format holds
        frames.append(
            Frame(
                index=10 + 2 * k,
                timestamp_s=1_700_000_000.123456789 + 0.1 * k + rng.uniform(0, 0.01),
                rgb=rng.integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8),
                depth_m=depth,
                odom_pose=rng.normal(size=3) * [3.0, 3.0, 2.0],
                gt_pose=None if k == 1 else rng.normal(size=3) * [5.0, 5.0, 2.0],
                gt_storey=None if k == 1 else k % 2,
                instance_ids=None if k == 1 else rng.integers(-1, 2, size=(HEIGHT, WIDTH)).astype(np.int32),
                extras={} if k == 2 else {"speed_mps": float(rng.uniform()), "visible": float(k)},
            )
        )
    return frames


def expected_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth as the format must read it back, computed independently of the library: mm steps, 0 → NaN."""
    mm = np.rint(depth_m.astype(np.float64) * 1000.0)
    mm[np.isnan(mm) | (mm > 65535)] = 0
    out = mm.astype(np.float32) / np.float32(1000.0)
    out[mm == 0] = np.nan
    return out
