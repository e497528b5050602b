"""Typed values passed between stages: planar poses, camera models, RGB-D frames.

Conventions (see DESIGN.md): metres, radians, seconds. Planar poses are (x, y, yaw) arrays, arrays of
them (N, 3). A transform is named by its frames: `T_world_base` maps base coordinates into world.
Camera frame is OpenCV's: x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# ------------------------------------------------------------------------------------------ SE(2) helpers


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-π, π)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ⊕ b for (..., 3) poses: apply b in a's frame."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """⊖a for (..., 3) poses."""
    a = np.asarray(a, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The relative pose ⊖a ⊕ b (b expressed in a's frame)."""
    return se2_compose(se2_inverse(a), b)


def se2_to_matrix(pose: np.ndarray, z_m: float = 0.0) -> np.ndarray:
    """(3,) planar pose → (4, 4) homogeneous transform (rotation about z), lifted to height `z_m`."""
    x, y, yaw = np.asarray(pose, float)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z_m]
    return T


def matrix_to_se2(T: np.ndarray) -> np.ndarray:
    """(4, 4) transform → (3,) planar pose (projection onto the xy-plane)."""
    return np.array([T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])])


# Open3D's parallel sums differ in the last bits from run to run: its poses are rounded to this many decimals, so
# that a run repeats bit for bit.
POSE_DECIMALS = 9


# ------------------------------------------------------------------------------------------ camera


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of an image `width` × `height` pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
        """Square pixels, principal point at the centre, the given horizontal field of view."""
        fx = (width / 2) / np.tan(np.deg2rad(hfov_deg) / 2)
        return cls(width, height, fx, fx, (width - 1) / 2, (height - 1) / 2)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def hfov_rad(self) -> float:
        return float(2 * np.arctan2(self.width / 2, self.fx))

    def backproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points (OpenCV: x right, y down, z ahead) of pixel columns `u` and rows `v` at depth
        `z` along the camera's z axis (NaN depth gives NaN points). The package's one back-projection: every stage
        that lifts depth calls it."""
        z = np.asarray(z, np.float64).ravel()
        u, v = np.asarray(u).ravel(), np.asarray(v).ravel()
        return np.column_stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z])


@dataclass
class Frame:
    """One RGB-D keyframe with what is known about where it was taken.

    `depth_m` is (H, W) float32 with NaN where there is no return; `rgb` is (H, W, 3) uint8.
    `odom_pose` is T_odom_base as (x, y, yaw); `gt_pose` is T_world_base when ground truth is known.
    `instance_ids` (H, W) int32 is present only in simulation: the sequence's instance table says which
    IFC element each id is (-1: nothing).
    """

    index: int
    timestamp_s: float
    rgb: np.ndarray
    depth_m: np.ndarray
    odom_pose: np.ndarray
    gt_pose: np.ndarray | None = None
    gt_storey: int | None = None
    instance_ids: np.ndarray | None = None
    extras: dict[str, float] = field(default_factory=dict)

    @property
    def storey_change(self) -> int:
        """The floors the robot went up (+) or down (−) since the frame before, when it was told (0: no word)."""
        return int(self.extras.get(STOREY_CHANGE, 0))


STOREY_CHANGE = "storey_change"
"""The `Frame.extras` key (frames.csv's `extra.storey_change`) of a storey-change event, as a barometer, an IMU or a
lift's interface tells it: the signed number of floors the robot went up (+) or down (−) since the frame before."""


@dataclass
class SequenceMeta:
    """What a sequence of frames shares: camera model, camera mount, where it came from.

    `T_base_camera` (4, 4) maps camera coordinates into the robot base frame (base: x forward, z up,
    on the floor). `instances` lists, for simulated sequences, what each instance id is:
    {"id", "guid", "ifc_class", "object_id" (id in the BimPrior, -1 for structure), "label"}.
    """

    name: str
    source: str
    intrinsics: CameraIntrinsics
    T_base_camera: np.ndarray
    prior_sha256: str = ""
    instances: list[dict] = field(default_factory=list)
    extras: dict = field(default_factory=dict)


@dataclass
class TextObservations:
    """Text read at one step (door plates), placed in the robot base frame like `Observations`' nodes.

    `texts` as read; `range_m` (K,) and `bearing_rad` (K,) where each was read (bearing counter-clockwise from x).
    """

    texts: list[str]
    range_m: np.ndarray
    bearing_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.texts)


@dataclass
class Observations:
    """What the robot sees at one step, as the localizer consumes it: K object nodes in view.

    `embeddings` (K, D) float32 unit rows (visual or fused embedding, same space as the BIM text embeddings);
    `range_m` (K,) and `bearing_rad` (K,) place each node in the robot base frame (bearing counter-clockwise
    from the robot's forward x axis); `labels` are the open-vocabulary label texts; `node_ids` (K,) the online
    scene-graph node ids (or detection ids); `confidence` (K,) each node's highest detector box score (None:
    unknown, every observation taken as certain). `texts` is the door-plate text read at this step, if any.
    """

    embeddings: np.ndarray
    range_m: np.ndarray
    bearing_rad: np.ndarray
    labels: list[str] = field(default_factory=list)
    node_ids: np.ndarray | None = None
    confidence: np.ndarray | None = None
    texts: TextObservations | None = None

    def __len__(self) -> int:
        return len(self.range_m)

    @property
    def n_texts(self) -> int:
        return 0 if self.texts is None else len(self.texts)

    def measurements(self) -> tuple[np.ndarray, np.ndarray]:
        """(K + T,) ranges and bearings of the K nodes, then of the T text readings: measurement k ≥ K is reading
        k − K (how the pose graphs index what a step measured)."""
        if not self.n_texts:
            return np.asarray(self.range_m, np.float64), np.asarray(self.bearing_rad, np.float64)
        assert self.texts is not None
        ranges = np.concatenate([np.asarray(self.range_m, np.float64), np.asarray(self.texts.range_m, np.float64)])
        bearings = np.concatenate([np.asarray(self.bearing_rad, np.float64), np.asarray(self.texts.bearing_rad)])
        return ranges, bearings
