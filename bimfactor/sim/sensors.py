"""Simulated sensors: an RGB-D camera on a Jackal-like base, ray cast against the world, and wheel odometry.

Depth is the distance along the camera's z axis with axial noise σ(z) = sigma0 + k·(z − z0)² and dropouts
(out of range, grazing incidence, random). Colour is the instance's albedo under Lambertian shading with
ambient light, plus Gaussian noise. Odometry follows the odometry motion model of Thrun et al.,
*Probabilistic Robotics*, Table 5.6 (sample_motion_model_odometry, α1..α4).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
from scipy import special

from bimfactor.config import CameraSimConfig, Config, DepthDropoutConfig, DepthSigmaConfig
from bimfactor.odometry import odometry_increment_variances, odometry_increments
from bimfactor.sim.world import SimWorld
from bimfactor.types import CameraIntrinsics, se2_compose, se2_to_matrix, wrap_angle

# Camera axes (OpenCV: x right, y down, z forward) in the base frame (x forward, y left, z up), pitch 0.
R_BASE_CAMERA_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
LIGHT_DIRECTION = np.array([0.35, 0.55, 1.0]) / np.linalg.norm([0.35, 0.55, 1.0])  # world frame, towards the light
AMBIENT = 0.45  # shade = AMBIENT + (1 − AMBIENT)·|n·l|
BACKGROUND_RGB = np.array([150.0, 175.0, 205.0], np.float32)  # where a ray leaves the building


class Rendering(NamedTuple):
    """One simulated RGB-D image: (H, W, 3) uint8, (H, W) float32 metres (NaN: no return), (H, W) int32 (-1: none)."""

    rgb: np.ndarray
    depth_m: np.ndarray
    instance_ids: np.ndarray


def camera_mount(cfg: CameraSimConfig) -> np.ndarray:
    """(4, 4) T_base_camera: the camera `mount_forward_m` ahead, `mount_height_m` up, pitched down by the pitch."""
    pitch = np.deg2rad(cfg.mount_pitch_deg)
    c, s = np.cos(pitch), np.sin(pitch)
    R_pitch = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about base y: positive tilts x down
    T = np.eye(4)
    T[:3, :3] = R_pitch @ R_BASE_CAMERA_LEVEL
    T[:3, 3] = [cfg.mount_forward_m, 0.0, cfg.mount_height_m]
    return T


class RgbdCamera:
    """A pinhole RGB-D camera on the robot base; renders the world with a precomputed grid of rays.

    `depth_noise` is the axial σ(z) (`sensor.depth_noise`), `dropout` the returns lost at grazing incidence and at
    random (`sim.depth_dropout`); `from_config` takes all of them from a run's config."""

    def __init__(
        self,
        world: SimWorld,
        camera: CameraSimConfig,
        depth_noise: DepthSigmaConfig,
        dropout: DepthDropoutConfig,
        rgb_noise_std: float,
    ) -> None:
        self.world = world
        self.camera = camera
        self.depth_noise = depth_noise
        self.dropout = dropout
        self.rgb_noise_std = rgb_noise_std
        self.intrinsics = CameraIntrinsics.from_hfov(camera.width, camera.height, camera.hfov_deg)
        self.T_base_camera = camera_mount(camera)
        k = self.intrinsics
        u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
        # Directions with z = 1, so the hit parameter t is the depth along the camera's z axis.
        self._dirs_camera = k.backproject(u, v, np.ones(u.shape)).astype(np.float32)
        self._dir_norm = np.linalg.norm(self._dirs_camera, axis=1).astype(np.float32)
        self._shade_light = (1.0 - AMBIENT) * LIGHT_DIRECTION.astype(np.float32)
        self._albedo_255 = (world.albedo * 255.0).astype(np.float32)
        self._is_plate = np.zeros(len(world.instances) + 1, bool)  # by instance id; the last entry: no hit (-1)
        self._is_plate[list(world.textures)] = True
        # Colour noise by inverse-CDF lookup: 2^16 equiprobable Gaussian levels, far cheaper than
        # 3·H·W Gaussian draws per frame and exact to within 1/65536 in probability.
        levels = (np.arange(1 << 16) + 0.5) / (1 << 16)
        self._rgb_noise_levels = (special.ndtri(levels) * rgb_noise_std).astype(np.float32)
        self._rays = np.empty((len(self._dirs_camera), 6), np.float32)

    @classmethod
    def from_config(cls, world: SimWorld, cfg: Config) -> RgbdCamera:
        """The camera of `cfg.sim.camera`, with the sensor's depth noise, the simulator's dropouts and RGB noise."""
        return cls(world, cfg.sim.camera, cfg.sensor.depth_noise, cfg.sim.depth_dropout, cfg.sim.rgb_noise_std)

    def _print_plates(
        self, rgb: np.ndarray, rays: np.ndarray, depth: np.ndarray, instance: np.ndarray, cos_incidence: np.ndarray
    ) -> None:
        """Paint the door plates' text (`sim.world.PlateTexture`) into the (H·W, 3) albedo of the pixels that hit
        them; a pixel's footprint on the plate, depth / f widened by the incidence, picks the texture's level."""
        on_plate = np.flatnonzero(self._is_plate[instance])
        if not len(on_plate):
            return
        footprint = depth[on_plate] / self.intrinsics.fx / np.maximum(cos_incidence[on_plate], 0.2)
        points = rays[on_plate, :3] + depth[on_plate, None] * rays[on_plate, 3:]
        for iid in np.unique(instance[on_plate]):
            mine = instance[on_plate] == iid
            value = self.world.textures[int(iid)].sample(points[mine], footprint[mine])
            rgb[on_plate[mine]] = value[:, None] * 255.0

    def rays(self, T_world_base: np.ndarray, storey_elevation_m: float = 0.0) -> np.ndarray:
        """(H·W, 6) float32 world rays (camera centre, direction with unit camera-z) for a base pose.

        `T_world_base` is a (3,) planar pose on the storey's floor or a (4, 4) transform.
        """
        T_world_base = np.asarray(T_world_base, float)
        if T_world_base.shape == (3,):
            T_world_base = se2_to_matrix(T_world_base, storey_elevation_m)
        T_world_camera = T_world_base @ self.T_base_camera
        self._rays[:, :3] = T_world_camera[:3, 3]
        # Elementwise, not BLAS: OpenBLAS threads contend with Open3D's ray-casting threads on few cores.
        R = T_world_camera[:3, :3].astype(np.float32)
        d = self._dirs_camera
        for axis in range(3):
            np.multiply(d[:, 0], R[axis, 0], out=self._rays[:, 3 + axis])
            self._rays[:, 3 + axis] += d[:, 1] * R[axis, 1]
            self._rays[:, 3 + axis] += R[axis, 2]  # d[:, 2] is 1
        return self._rays

    def render(
        self, T_world_base: np.ndarray, storey_elevation_m: float = 0.0, rng: np.random.Generator | None = None
    ) -> Rendering:
        """Render colour, depth and instance ids; noise and random dropouts only when `rng` is given."""
        k, noise, dropout = self.intrinsics, self.depth_noise, self.dropout
        rays = self.rays(T_world_base, storey_elevation_m)
        depth, instance, normals = self.world.cast(rays)
        hit = instance >= 0
        dirs = rays[:, 3:]
        # |cos| of the angle between ray and surface normal (normals' sign is arbitrary).
        cos_incidence = np.abs(_rowdot(normals, dirs)) / self._dir_norm
        shade = AMBIENT + np.abs(_rowdot(normals, self._shade_light))
        rgb = np.take(self._albedo_255, np.maximum(instance, 0), axis=0)
        if self.world.textures:
            self._print_plates(rgb, rays, depth, instance, cos_incidence)
        rgb *= shade[:, None]
        rgb[~hit] = BACKGROUND_RGB
        valid = hit & (depth >= self.camera.min_range_m) & (depth <= self.camera.max_range_m)
        valid &= cos_incidence >= np.cos(np.deg2rad(dropout.grazing_dropout_deg))
        depth = depth.astype(np.float32, copy=False)  # the cast's own array: changed in place
        if rng is not None:
            if self.rgb_noise_std > 0:
                rgb += self._rgb_noise_levels[rng.integers(0, 1 << 16, size=rgb.shape, dtype=np.uint16)]
            sigma = noise.sigma_m(depth[valid]).astype(np.float32)
            depth[valid] += sigma * rng.standard_normal(len(sigma), dtype=np.float32)
            if dropout.dropout_prob > 0:
                valid &= rng.random(len(valid), dtype=np.float32) >= dropout.dropout_prob
        depth[~valid] = np.nan
        rgb_u8 = np.clip(rgb + 0.5, 0.0, 255.0).astype(np.uint8)
        return Rendering(
            rgb_u8.reshape(k.height, k.width, 3), depth.reshape(k.height, k.width), instance.reshape(k.height, k.width)
        )


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) dot products of (N, 3) rows with (N, 3) rows or one (3,) vector, without BLAS."""
    b = np.broadcast_to(b, a.shape)
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


# ------------------------------------------------------------------------------------------ wheel odometry


class WheelOdometry:
    """Wheel odometry along one drive, read between keyframes (sample_motion_model_odometry, α1..α4).

    The noise of the increment since the last keyframe is drawn once per keyframe and scales with the increment as
    it grows, so a robot can take its keyframes on what its odometry reads, as a real one does, and each keyframe's
    increment carries the model's noise. `pose` is T_odom_base at the last keyframe, from (0, 0, 0)."""

    def __init__(self, alpha: list[float] | np.ndarray, rng: np.random.Generator) -> None:
        self.alpha, self.rng = alpha, rng
        self.pose = np.zeros(3)
        self._draw = rng.standard_normal(3)

    def read(self, last: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(3,) dx, dy, dyaw the odometry reads since the keyframe at the true pose `last`, the robot now at `pose`."""
        increment = odometry_increments(np.stack([last, pose]))
        sigma = np.sqrt(odometry_increment_variances(increment, self.alpha))
        rot1, trans, rot2 = (increment - sigma * self._draw)[0]
        return np.array([trans * np.cos(rot1), trans * np.sin(rot1), wrap_angle(rot1 + rot2)])

    def take(self, last: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """A keyframe at the true `pose`: its (3,) odometry pose; the next keyframe's noise is drawn."""
        self.pose = se2_compose(self.pose, self.read(last, pose))
        self._draw = self.rng.standard_normal(3)
        return self.pose


def simulate_odometry(gt_poses: np.ndarray, alpha: list[float] | np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Wheel odometry T_odom_base (N, 3) at ground-truth keyframe poses (N, 3): `WheelOdometry` from (0, 0, 0)."""
    wheels = WheelOdometry(alpha, rng)
    poses = np.asarray(gt_poses, float)
    return np.array([np.zeros(3)] + [wheels.take(a, b).copy() for a, b in itertools.pairwise(poses)])
